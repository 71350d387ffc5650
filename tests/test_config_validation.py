"""Config.validate(): every numeric field has a range rule, each rule rejects values outside it
naming the key and the allowed range, and accepts its own bounds where they are inclusive."""

from __future__ import annotations

import math

import pytest

from adalio.config import CHOICES, RANGES, Config, _leaf_values, available_presets, load_config
from adalio.errors import ConfigError


def _outside(rule) -> list[float]:
    """Values just outside a rule (the bound itself where it is excluded)."""
    out = []
    if rule.lo is not None:
        out.append(rule.lo if rule.lo_open else rule.lo - 1)
    if rule.hi is not None:
        out.append(rule.hi if rule.hi_open else rule.hi + 1)
    return out


def test_every_numeric_field_has_a_rule():
    numeric = [k for k, v in _leaf_values(Config()).items()
               if isinstance(v, (int, float)) and not isinstance(v, bool)]
    missing = [k for k in numeric if k not in RANGES and k not in CHOICES]
    assert not missing, f"add a RANGES entry for {missing}"
    assert set(RANGES) <= set(_leaf_values(Config())), "a rule names a field that does not exist"


@pytest.mark.parametrize("key", sorted(RANGES))
def test_out_of_range_rejected_with_key_and_range(key):
    rule = RANGES[key]
    default = _leaf_values(Config())[key]
    bad = _outside(rule)
    assert bad, key
    if isinstance(default, float):
        bad += [math.nan, math.inf]
    for value in bad:
        value = int(value) if isinstance(default, int) and math.isfinite(value) else value
        with pytest.raises(ConfigError) as info:
            load_config(overrides={key: value})
        msg = str(info.value)
        need = rule.describe() if math.isfinite(value) or rule.describe() == "finite" \
            else f"finite and {rule.describe()}"  # inf >= 0 holds: say what it breaks
        assert msg.startswith(f"{key} must be {need} (got "), msg
        assert "\n" not in msg


@pytest.mark.parametrize("key", sorted(RANGES))
def test_inclusive_bounds_accepted(key):
    rule = RANGES[key]
    for bound, is_open in ((rule.lo, rule.lo_open), (rule.hi, rule.hi_open)):
        if bound is None or is_open:
            continue
        if key == "filter.knn_k":  # min_neighbors (default 3) must stay <= knn_k
            bound = max(bound, 3)
        if key == "preprocess.max_range_m" or key == "preprocess.blind_m":
            continue  # related by a cross-field rule, tested below
        load_config(overrides={key: bound})


def test_issue_example_message():
    with pytest.raises(ConfigError, match=r"^sensor\.imu_rate_hz must be > 0 \(got -400"):
        load_config(overrides={"sensor.imu_rate_hz": -400})


def test_cross_field_rules():
    with pytest.raises(ConfigError, match="preprocess.max_range_m must be > preprocess.blind_m"):
        load_config(overrides={"preprocess.blind_m": 5.0, "preprocess.max_range_m": 2.0})
    with pytest.raises(ConfigError, match="filter.min_neighbors must be <= filter.knn_k"):
        load_config(overrides={"filter.knn_k": 4, "filter.min_neighbors": 5})


@pytest.mark.parametrize("key", sorted(CHOICES))
def test_choices_rejected(key):
    default = _leaf_values(Config())[key]
    bad = 7 if isinstance(default, int) else "bogus"
    with pytest.raises(ConfigError, match=f"^{key} must be one of"):
        load_config(overrides={key: bad})


@pytest.mark.parametrize("preset", available_presets())
def test_presets_valid(preset):
    load_config(preset)


def test_yaml_file_value_rejected(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("adaptive:\n  near_ratio: 1.5\n")
    with pytest.raises(ConfigError, match=r"adaptive\.near_ratio must be in \[0, 1\] \(got 1.5"):
        load_config(config_file=f)
