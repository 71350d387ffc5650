"""Inputs that are almost right get an error that says what they are (session 74)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from adalio.config import load_config
from adalio.errors import ConfigError, InputError
from adalio.eval.report import make_report


def test_a_config_folder_is_named_a_folder(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"is a folder: give the YAML file in it"):
        load_config(config_file=tmp_path)


@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan"])
def test_a_non_finite_setting_says_finite(tmp_path: Path, value: str) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"preprocess:\n  blind_m: {value}\n")
    with pytest.raises(ConfigError, match=r"preprocess.blind_m must be finite and >= 0"):
        load_config(config_file=cfg)


def test_report_on_a_file_says_it_is_a_file(tmp_path: Path) -> None:
    bag = tmp_path / "hall.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n")
    with pytest.raises(InputError, match="is a file: give the --out folder of a run"):
        make_report(bag)


@pytest.mark.parametrize("value", ["inf", "nan", "0", "-1"])
def test_eval_max_diff_must_be_finite_and_positive(tmp_path: Path, value: str) -> None:
    from typer.testing import CliRunner

    from adalio.cli import app

    tum = tmp_path / "a.tum"
    t = np.arange(10) * 0.1
    tum.write_text("".join(f"{x:.1f} {x:.1f} 0 0 0 0 0 1\n" for x in t))
    for hilti in ([], ["--hilti"]):  # the ATE's association and the HILTI score's matching
        res = CliRunner().invoke(app, ["eval", str(tum), str(tum), "--max-diff", value, *hilti])
        assert isinstance(res.exception, InputError), res.output  # cli.main: one line, exit 2
        assert "--max-diff must be a finite number of seconds > 0" in str(res.exception)


def test_eval_hilti_on_a_dense_ground_truth_warns(tmp_path: Path) -> None:
    """A dense trajectory given to --hilti is scored (the rule is the rule) with a warning that
    it is not control points; control points (identity orientations, 1 s apart) are not."""
    from typer.testing import CliRunner

    from adalio.cli import app

    est, dense, points = tmp_path / "e.tum", tmp_path / "d.tum", tmp_path / "p.tum"
    t = np.arange(0.0, 10.0, 0.1)
    rows = [f"{x:.1f} {x:.2f} {np.sin(x):.4f} 0 0 0 0 1\n" for x in t]
    est.write_text("".join(rows))
    dense.write_text("".join(rows))
    points.write_text("".join(rows[::20]))
    for gt, warned in ((dense, True), (points, False)):
        res = CliRunner().invoke(app, ["eval", str(est), str(gt), "--hilti"])
        assert res.exit_code == 0, res.output
        assert ("does not look like HILTI control points" in res.stderr) == warned
