"""`adalio demo` end to end (simulation, two modes, tables, reports) and its table over seeds."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from adalio.eval.compare import CompareResult, ModeResult
from adalio.eval.demo import DemoResult, SeedResult, summary_rows, wins_line


@pytest.mark.slow
def test_demo_short(tmp_path):
    from adalio.cli import app

    out = tmp_path / "demo"
    res = CliRunner().invoke(app, ["demo", "--short", "--out", str(out)])
    assert res.exit_code == 0, res.output + repr(res.exception)
    data = json.loads((out / "seed0" / "compare.json").read_text())
    assert [r["mode"] for r in data["rows"]] == ["fixed", "adaptive"]
    for row in data["rows"]:
        assert row["n_scans"] > 10
        assert row["ate_rmse_m"] is not None and row["ate_rmse_m"] >= 0
        assert (out / "seed0" / row["out_dir"].split("/")[-1] / "report.md").is_file()
    summary = json.loads((out / "demo.json").read_text())
    assert summary["seeds"] == [0]
    # the table over the seeds carries each seed's own figures
    assert [m["ate_rmse_m"] for m in summary["modes"]] == [[r["ate_rmse_m"]] for r in data["rows"]]
    assert "ATE rmse" in res.output and "demo.md" in res.output
    assert "seed0/compare.md" in (out / "demo.md").read_text()


def _seed(seed: int, fixed: float | None, adaptive: float | None,
          diverged: tuple[bool, bool] = (False, False)) -> SeedResult:
    rows = [ModeResult(mode=m, out_dir=m, ate_rmse_m=a, diverged=d)
            for m, a, d in zip(("fixed", "adaptive"), (fixed, adaptive), diverged, strict=True)]
    return SeedResult(seed, CompareResult(rows=rows, out_dir=Path(".")), Path("bag"), Path("gt"))


def test_demo_table_over_seeds_is_the_seeds_mean_and_worst():
    """Means, worsts, divergences and the win count over seeds, against hand-computed values;
    a seed where one mode has no ATE counts for neither the mean nor the comparison."""
    res = DemoResult([_seed(0, 0.076, 0.081), _seed(1, 0.161, 0.046),
                      _seed(2, 0.293, None, (True, True))], Path("."), 0.0, 0.0)
    fixed, adaptive = res.summary()
    assert fixed.mean_m == pytest.approx((0.076 + 0.161 + 0.293) / 3)
    assert fixed.worst_m == 0.293 and adaptive.worst_m == 0.081
    assert adaptive.mean_m == pytest.approx((0.081 + 0.046) / 2)
    assert (fixed.diverged, adaptive.diverged) == (1, 1)
    assert res.wins() == (1, 2)
    assert wins_line(res) == "adaptive has the lower ATE on 1 of 2 seeds"
    assert summary_rows(res) == [("fixed", "7.6", "16.1", "29.3", "17.7", "29.3", "1/3"),
                                 ("adaptive", "8.1", "4.6", "-", "6.3", "8.1", "1/3")]

