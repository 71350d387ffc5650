"""`adalio compare` and the per-mode reports on a short simulated sequence."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from typer.testing import CliRunner

from adalio.errors import ConfigError
from adalio.eval.compare import DIVERGED_MAX_ERROR_M, parse_modes
from adalio.eval.demo import (  # shares the demo's cache
    DEMO_FORMAT,
    DEMO_SCENE,
    SHORT_COLUMNS,
    SHORT_DURATION_S,
)
from adalio.eval.files import read_scans_csv
from adalio.eval.metrics import ate


def assert_png_image(path: Path, min_px: int = 200) -> None:
    assert path.is_file() and path.stat().st_size > 1000, path
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] >= min_px and img.shape[1] >= min_px, img.shape
    assert float(np.ptp(img[..., :3])) > 0.2, f"{path} is a constant image"


def test_parse_modes():
    assert parse_modes("fixed, adaptive+") == ["fixed", "adaptive+"]
    for bad in ("", "fixed,turbo", "fixed,fixed"):
        with pytest.raises(ConfigError):
            parse_modes(bad)


@pytest.mark.slow
def test_compare_cli_on_simulated_run(tmp_path):
    from adalio.cli import app
    from adalio.sim import cached_sequence

    sim = cached_sequence(DEMO_SCENE, seed=0, duration_s=SHORT_DURATION_S,
                          columns=SHORT_COLUMNS, fmt=DEMO_FORMAT)
    out = tmp_path / "cmp"
    res = CliRunner().invoke(app, ["compare", str(sim.bag_path), "--modes", "fixed,adaptive",
                                   "--gt", str(sim.gt_path), "--config", str(sim.config_path),
                                   "--out", str(out), "--max-scans", "40"])
    assert res.exit_code == 0, res.output + repr(res.exception)
    assert "ATE rmse" in res.output and "adaptive" in res.output
    data = json.loads((out / "compare.json").read_text())
    assert [r["mode"] for r in data["rows"]] == ["fixed", "adaptive"]
    for name in ("compare_top.png", "compare_side.png", "compare_error.png"):
        assert_png_image(out / name)
    assert "compare_top.png" in (out / "compare.md").read_text()
    # the overlay stands on the world's up, in the GT's frame: the simulated LiDAR is level, so
    # up is along its z, taken into the GT's frame by the GT's first pose (the IMU's)
    from adalio.config import load_config
    from adalio.eval.files import read_trajectory

    gt0 = np.asarray(read_trajectory(sim.gt_path, "ground-truth").poses_se3)[0]
    lidar_z = np.asarray(load_config(config_file=sim.config_path).sensor.T_imu_lidar)[:3, 2]
    assert abs(np.dot(data["figures_up"], gt0[:3, :3] @ lidar_z)) > np.cos(np.radians(2.0))
    for row in data["rows"]:
        run_dir = Path(row["out_dir"])
        assert row["aborted"] is None, row
        expected = ate(run_dir / "trajectory.tum", sim.gt_path, "se3")
        assert row["ate_rmse_m"] == pytest.approx(expected["rmse_m"])
        assert row["max_error_m"] == pytest.approx(expected["max_m"])
        assert row["diverged"] == (expected["max_m"] > DIVERGED_MAX_ERROR_M)
        scans = read_scans_csv(run_dir / "scans.csv")
        assert row["n_scans"] == len(scans["t_s"])
        assert row["degenerate_pct"] == pytest.approx(100 * scans["degenerate"].mean())
        report = Path(row["report"])
        assert report.is_file()
        for png in ("trajectory_top.png", "trajectory_side.png", "error.png", "degeneracy.png",
                    "map_top.png"):
            assert_png_image(run_dir / png)
            assert png in report.read_text()


def test_compare_keeps_going_when_the_gt_does_not_cover_the_run(tmp_path):
    """A ground truth from another recording (no stamp within reach of the run's) cannot align:
    each mode's evaluation is reported as failed, naming why (the run itself completed: neither
    aborted nor diverged), and the comparison is still written (no traceback, no figure up taken
    from a report that was never made)."""
    from adalio.eval.compare import compare_modes
    from adalio.sim import cached_sequence

    sim = cached_sequence(DEMO_SCENE, seed=0, duration_s=SHORT_DURATION_S,
                          columns=SHORT_COLUMNS, fmt=DEMO_FORMAT)
    rows = np.loadtxt(sim.gt_path)
    rows[:, 0] += 1e5  # a day later
    gt = tmp_path / "other_day.tum"
    np.savetxt(gt, rows, fmt="%.9f")
    res = compare_modes(sim.bag_path, ["fixed"], tmp_path / "cmp", gt=gt,
                        config_file=sim.config_path, max_scans=20, progress=False)
    from adalio.eval.compare import table_rows

    row = res.rows[0]
    assert row.n_scans == 20 and (tmp_path / "cmp" / "fixed" / "trajectory.tum").is_file()
    assert row.aborted is None and not row.diverged
    assert "no estimate/GT pose pairs" in row.eval_failed
    assert table_rows(res.rows)[0][3] == "- (evaluation failed)"
    data = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert data["figures_up"] is None
    assert data["rows"][0]["aborted"] is None and data["rows"][0]["diverged"] is False
    assert data["rows"][0]["eval_failed"] == row.eval_failed
    md = (tmp_path / "cmp" / "compare.md").read_text()
    assert "aborted" not in md and "yes" not in md
    assert f"`fixed` evaluation against the ground truth failed (the run completed): " \
           f"{row.eval_failed}" in md
    assert "--gt" in res.failure() and str(gt) in res.failure()
    assert row.eval_failed in res.failure()


def test_compare_keeps_an_aborted_modes_whole_reason(tmp_path, monkeypatch):
    """A mode whose run stops is reported with the whole first line of why (it named a file and
    a setting past 200 characters, and was cut mid-word there); later lines are left out."""
    import adalio.eval.compare as cmp
    from adalio.errors import AdalioError

    reason = "the run stopped at scan 3: " + "x" * 220 + " set filter.some_setting to fix it"

    def stops(*args, **kwargs):
        raise AdalioError(reason + "\nsecond line")

    monkeypatch.setattr("adalio.pipeline.run_bag", stops)
    res = cmp.compare_modes(tmp_path / "any.bag", ["fixed"], tmp_path / "cmp", progress=False)
    assert res.rows[0].aborted == f"AdalioError: {reason}"
    data = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert data["rows"][0]["aborted"].endswith("set filter.some_setting to fix it")


def test_compare_names_an_earlier_comparisons_mode_folders(tmp_path, monkeypatch):
    """A mode folder left in --out by an earlier comparison of other modes is named as such in
    compare.md (and kept: it is the user's), not silently beside this comparison's."""
    import adalio.eval.compare as cmp
    from adalio.errors import AdalioError

    def stops(*args, **kwargs):
        raise AdalioError("stopped")

    monkeypatch.setattr("adalio.pipeline.run_bag", stops)
    out = tmp_path / "cmp"
    (out / "adaptive_plus").mkdir(parents=True)
    (out / "adaptive_plus" / "trajectory.tum").write_text("1 0 0 0 0 0 0 1\n")
    (out / "fixed").mkdir()
    (out / "other").mkdir()
    res = cmp.compare_modes(tmp_path / "any.bag", ["fixed"], out, progress=False)
    assert res.earlier == ["adaptive_plus"]
    md = (out / "compare.md").read_text()
    assert "folders from an earlier comparison, not run now: `adaptive_plus`" in md
    assert (out / "adaptive_plus" / "trajectory.tum").is_file()
    res = cmp.compare_modes(tmp_path / "any.bag", ["fixed", "adaptive+"], out, progress=False)
    assert res.earlier == [] and "earlier comparison" not in (out / "compare.md").read_text()
