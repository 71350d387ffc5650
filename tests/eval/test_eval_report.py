"""Run reports and map/scans readers on a run folder written with adalio's own writers."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from adalio.config import Config
from adalio.errors import InputError
from adalio.eval.files import read_map_points, read_scans_csv
from adalio.eval.metrics import ate
from adalio.eval.report import make_report
from adalio.io.writers import ScansCsvWriter, TumWriter, write_pcd, write_ply
from adalio.types import ScanStats

FIGURES = ("trajectory_top.png", "trajectory_side.png", "error.png", "degeneracy.png",
           "map_top.png")


def assert_png_image(path: Path, min_px: int = 200) -> None:
    assert path.is_file() and path.stat().st_size > 1000, path
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] >= min_px and img.shape[1] >= min_px, img.shape
    assert float(np.ptp(img[..., :3])) > 0.2, f"{path} is a constant image"


def _pose(t: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 0.3 * t).as_matrix()
    T[:3, 3] = [2 * np.cos(0.3 * t), 2 * np.sin(0.3 * t), -0.2 * t]
    return T


@pytest.fixture()
def run_dir(tmp_path):
    return make_run_dir(tmp_path)


def make_run_dir(tmp_path: Path) -> tuple[Path, Path]:
    """A run folder: 10 Hz estimate = GT + 3 cm noise, scans.csv with a degenerate span."""
    out = tmp_path / "run"
    out.mkdir()
    t0_ns = 1_700_000_000_000_000_000
    times_ns = t0_ns + np.arange(120) * 100_000_000
    gt_path = tmp_path / "gt.tum"
    with TumWriter(gt_path) as gt_w:
        for k in range(1200):
            gt_w.write(t0_ns + k * 10_000_000, _pose(k * 0.01))
    rng = np.random.default_rng(0)
    with TumWriter(out / "trajectory.tum") as tw:
        for k, t_ns in enumerate(times_ns):
            T = _pose(k * 0.1)
            T[:3, 3] += rng.normal(0, 0.03, 3)
            tw.write(int(t_ns), T)
    csvw = ScansCsvWriter(out / "scans.csv")
    for k, t_ns in enumerate(times_ns):
        degen = 40 <= k < 70
        csvw.write(ScanStats(t_ns=int(t_ns), n_raw=20000, n_down=1500 if not degen else 600,
                             n_down_general=1400 if not degen else 500, n_near=300,
                             degenerate=degen, trigger="count" if degen else "",
                             voxel_size_m=0.2, search_radius_m=3.0, plane_margin_m=0.05,
                             n_matched=900, iterations=3, wall_ms=12.0 + k % 3,
                             eigenvalues=np.geomspace(1e1 if not degen else 1e-2, 1e5, 6)))
    csvw.close()
    walls = rng.uniform(-5, 5, (20000, 2))
    write_ply(out / "map.ply", np.column_stack([walls, rng.uniform(-2, 1, 20000)]))
    (out / "config.yaml").write_text(Config().to_yaml())
    return out, gt_path


def test_readers_roundtrip(tmp_path):
    pts = np.random.default_rng(1).normal(size=(500, 3)).astype(np.float32).astype(np.float64)
    assert np.array_equal(read_map_points(write_ply(tmp_path / "m.ply", pts)), pts)
    assert np.array_equal(read_map_points(write_pcd(tmp_path / "m.pcd", pts)), pts)
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n")
    with pytest.raises(InputError):
        read_map_points(tmp_path / "bad.ply")


def test_make_report_with_gt(run_dir):
    out, gt = run_dir
    report = make_report(out, gt)
    assert report == out / "report.md"
    text = report.read_text()
    for name in FIGURES:
        assert_png_image(out / name)
        assert f"]({name})" in text
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ate_se3"] == ate(out / "trajectory.tum", gt, "se3")
    assert metrics["ate_se3"]["n"] == 120
    assert 0.02 < metrics["ate_se3"]["rmse_m"] < 0.09  # 3 cm per axis noise
    assert metrics["scans"]["n_scans"] == 120
    assert metrics["scans"]["degenerate_pct"] == pytest.approx(25.0)
    assert metrics["map_points"] == 20000
    scans = read_scans_csv(out / "scans.csv")
    assert scans["degenerate"].sum() == 30 and set(scans["trigger"]) == {"", "count"}
    assert f"{metrics['ate_se3']['rmse_m']:.4f}" in text


def test_report_without_gt_and_cli(run_dir):
    from adalio.cli import app

    out, _ = run_dir
    res = CliRunner().invoke(app, ["report", str(out)])
    assert res.exit_code == 0, res.output
    assert not (out / "error.png").exists()
    for name in ("trajectory_top.png", "degeneracy.png", "map_top.png"):
        assert_png_image(out / name)
    res = CliRunner().invoke(app, ["report", str(out.parent / "nope")])
    assert isinstance(res.exception, InputError)


def test_report_detects_hilti_control_points(tmp_path):
    from adalio.eval.hilti import hilti_score

    gt_dir = Path(__file__).resolve().parents[1] / "data" / "real" / "hilti2022_gt"
    dense = sorted(gt_dir.glob("exp_05_*_imu.txt"))
    if not dense:
        pytest.fail(f"HILTI ground truth missing in {gt_dir} (it ships in the repository)")
    sparse = gt_dir / "exp05_construction_upper_level_2.txt"
    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory.tum").write_text(dense[0].read_text())
    make_report(run, sparse)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["hilti"] == hilti_score(dense[0], sparse)
    assert "ate_se3" not in metrics
    assert f"{metrics['hilti']['score']:.1f} / 100" in (run / "report.md").read_text()
    assert_png_image(run / "trajectory_top.png")
    with pytest.raises(InputError, match="--hilti"):
        ate(dense[0], sparse)


def test_report_states_sigma_consistency_and_how_the_error_drifts(tmp_path):
    """With honest sigma columns (3 cm, the estimate's white noise) the report finds about
    99.7 % of the scans within 3σ, a mean NEES near 3 and a median |error| / σ near 0.67, and the increments of a white error
    swing back (their lag-1 correlation is -0.5 in theory; 11 increments per axis here, so the
    three axes' mean is checked)."""
    out, gt = make_run_dir(tmp_path)
    rows = read_scans_csv(out / "scans.csv")
    csvw = ScansCsvWriter(out / "scans.csv")
    for t_s in rows["t_s"]:
        csvw.write(ScanStats(t_ns=round(float(t_s) * 1e9), n_raw=20000, n_down=1500,
                             n_down_general=1400, n_near=300, voxel_size_m=0.2,
                             search_radius_m=3.0, plane_margin_m=0.05, n_matched=900,
                             iterations=3, wall_ms=12.0, eigenvalues=np.geomspace(1e1, 1e5, 6),
                             sigma_p_world_m=np.full(3, 0.03),
                             sigma_rot_world_deg=np.full(3, 0.1)))
    csvw.close()
    text = make_report(out, gt).read_text()
    sigma = json.loads((out / "metrics.json").read_text())["sigma"]
    assert sigma["n"] == 120
    assert min(sigma["within_3sigma_xyz"]) > 0.95
    assert 2.0 < sigma["mean_nees"] < 4.0
    assert all(0.45 < v < 0.95 for v in sigma["median_abs_z_xyz"])  # 0.674 for honest sigmas
    assert "Median |error| / σ" in text
    r = np.array(sigma["increment_correlation_xyz"])
    assert -0.8 < r.mean() < -0.2, r
    assert "Correlation of consecutive 1 s increments" in text


@pytest.mark.parametrize("with_gt", [False, True])
def test_figures_stand_on_the_worlds_up_whatever_the_imu_mounting(tmp_path, monkeypatch,
                                                                   with_gt):
    """The world is the IMU frame at init, so with the IMU on its side its z is horizontal: the
    figures turn it so that the up of the gravity the filter took (``config.yaml``'s
    ``measured.gravity_world_m_s2``) is their z. A level helix (_pose: radius 2 m, 0.2 m/s down)
    written in a world rolled 90 deg (and a GT in a frame of its own) must come out with its
    descent on the figures' z and its circle in their x-y, the map's floor as well."""
    from adalio.eval import plots

    out, gt_level = make_run_dir(tmp_path)
    R_w = Rotation.from_euler("xz", [90, 30], degrees=True).as_matrix()  # level -> world
    T_w = np.eye(4)
    T_w[:3, :3] = R_w
    est = _turn_tum(out / "trajectory.tum", out / "trajectory.tum", T_w)
    floor = np.column_stack([np.random.default_rng(1).uniform(-3, 3, (500, 2)), np.full(500, -2.5)])
    write_ply(out / "map.ply", floor @ R_w.T)
    text = Config().to_yaml() + yaml_measured(R_w @ [0.0, 0.0, -9.81])
    (out / "config.yaml").write_text(text)
    gt = None
    if with_gt:  # the GT in a frame whose z points down
        gt = tmp_path / "gt_down.tum"
        _turn_tum(gt_level, gt, np.diag([1.0, -1.0, -1.0, 1.0]))
    seen = {}
    real_traj, real_map = plots.plot_trajectories, plots.plot_map_top

    def traj(est_xyz, gt_xyz, *a, **kw):
        seen["est"], seen["gt"] = next(iter(est_xyz.values())), gt_xyz
        return real_traj(est_xyz, gt_xyz, *a, **kw)

    def map_top(points, *a, **kw):
        seen["map"] = points
        return real_map(points, *a, **kw)

    monkeypatch.setattr(plots, "plot_trajectories", traj)
    monkeypatch.setattr(plots, "plot_map_top", map_top)
    make_report(out, gt)
    level = est[:, 1:4]  # the estimate as written in the level frame (GT + 3 cm noise)
    fig = seen["est"]
    # the descent (2.4 m over the 12 s) on the figures' z, the arc in their x-y (up to a yaw)
    np.testing.assert_allclose(fig[:, 2] - fig[0, 2], level[:, 2] - level[0, 2], atol=0.08)
    np.testing.assert_allclose(np.linalg.norm(fig[:, :2] - fig[0, :2], axis=1),
                               np.linalg.norm(level[:, :2] - level[0, :2], axis=1), atol=0.08)
    if with_gt:
        assert np.ptp(seen["gt"][:, 2]) > 2.0 and seen["gt"][-1, 2] < seen["gt"][0, 2]
    np.testing.assert_allclose(seen["map"][:, 2], -2.5, atol=1e-9)
    up = json.loads((out / "metrics.json").read_text())["figures_up"]
    assert up is not None
    assert_png_image(out / "trajectory_side.png")


def _turn_tum(src: Path, dst: Path, T_left: np.ndarray) -> np.ndarray:
    """Write ``src``'s poses turned by ``T_left`` (``T_left @ T``) to ``dst``; return ``src``'s
    rows as read."""
    rows = np.loadtxt(src)
    with TumWriter(dst) as tw:
        for row in rows:
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(row[4:]).as_matrix()
            T[:3, 3] = row[1:4]
            tw.write(round(row[0] * 1e9), T_left @ T)
    return rows


def yaml_measured(gravity_world_m_s2) -> str:
    import yaml

    return yaml.safe_dump({"measured": {"gravity_world_m_s2": [float(v) for v in
                                                               gravity_world_m_s2]}})


def test_figures_keep_the_world_frame_when_the_run_does_not_say_where_up_is(run_dir):
    out, gt = run_dir  # config.yaml without a measured block (a run older than the field)
    make_report(out, gt)
    assert json.loads((out / "metrics.json").read_text())["figures_up"] is None


def test_report_hilti_on_a_dense_ground_truth_warns(run_dir, tmp_path):
    """As `eval --hilti`: a dense GT given to `report --hilti` is scored with a warning that it
    is not control points, naming the command to run instead; control points (identity
    orientations, 1 s apart) and a dense GT without --hilti are not warned about."""
    from adalio.cli import app

    out, gt = run_dir
    rows = np.loadtxt(gt)[::100]
    rows[:, 4:8] = [0.0, 0.0, 0.0, 1.0]
    points = tmp_path / "points.tum"
    np.savetxt(points, rows, fmt="%.9f")
    for gt_file, flags, warned in ((gt, ["--hilti"], True), (points, ["--hilti"], False),
                                   (gt, [], False)):
        res = CliRunner().invoke(app, ["report", str(out), "--gt", str(gt_file), *flags])
        assert res.exit_code == 0, res.output
        assert ("does not look like HILTI control points" in res.stderr) == warned, res.stderr
        assert ("use report without --hilti" in res.stderr) == warned
        assert ("hilti" in json.loads((out / "metrics.json").read_text())) == bool(flags)


def _with_sigma_columns(out: Path, sigma_m: float = 0.03, growth_m_s: float = 0.0) -> None:
    rows = read_scans_csv(out / "scans.csv")
    csvw = ScansCsvWriter(out / "scans.csv")
    for t_s in rows["t_s"]:
        sigma = sigma_m + growth_m_s * (float(t_s) - float(rows["t_s"][0]))
        csvw.write(ScanStats(t_ns=round(float(t_s) * 1e9), n_raw=20000, n_down=1500,
                             n_down_general=1400, n_near=300, voxel_size_m=0.2,
                             search_radius_m=3.0, plane_margin_m=0.05, n_matched=900,
                             iterations=3, wall_ms=12.0, eigenvalues=np.geomspace(1e1, 1e5, 6),
                             sigma_p_world_m=np.full(3, sigma),
                             sigma_rot_world_deg=np.full(3, 0.1)))
    csvw.close()


def test_report_says_where_the_sigma_check_is_anchored_and_warns_off_the_first_scan(tmp_path):
    """The uncertainty section names the time of the pose the GT is aligned on; a GT that starts
    6 s into the 12 s run aligns on the first scan it covers (6.00 s after the first scan), which
    the report must say, with a warning (report.md, metrics.json, stderr), not claim the filter's
    first scan."""
    from adalio.cli import app

    out, gt = make_run_dir(tmp_path)
    _with_sigma_columns(out)
    text = make_report(out, gt).read_text()
    sigma = json.loads((out / "metrics.json").read_text())["sigma"]
    assert sigma["anchor_is_first_scan"] and sigma["anchor_t_s"] == pytest.approx(0.0)
    assert "aligned on the filter's first scan, at 0.00 s" in text and "Warning" not in text
    late = tmp_path / "late_gt.tum"
    rows = np.loadtxt(gt)
    t_est = np.loadtxt(out / "trajectory.tum")[:, 0]
    late_rows = rows[rows[:, 0] >= t_est[0] + 6.0 - 1e-6]
    np.savetxt(late, late_rows, fmt="%.9f")
    res = CliRunner().invoke(app, ["report", str(out), "--gt", str(late)])
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text())
    sigma = metrics["sigma"]
    # the first estimate with a GT pose within 20 ms: the one 6.0 s after the first
    first_covered = t_est[np.argmax(t_est >= late_rows[0, 0] - 0.02)] - t_est[0]
    assert first_covered == pytest.approx(6.0, abs=1e-6)
    assert not sigma["anchor_is_first_scan"]
    assert sigma["anchor_t_s"] == pytest.approx(first_covered, abs=1e-6)
    assert sigma["first_scan_t_s"] == pytest.approx(0.0)
    assert sigma["anchor_sigma_max_m"] == pytest.approx(0.03)
    text = (out / "report.md").read_text()
    assert "aligned on the scan at 6.00 s, the first the ground truth covers" in text
    assert "filter's first scan at 0.00 s" in text and "**Warning:**" in text
    assert "warning: the ground truth starts after the filter's first scan" in res.stderr
    assert metrics["warnings"] and "optimistic" in metrics["warnings"][0]


def test_a_gt_one_scan_late_where_sigma_is_small_is_not_warned_about(tmp_path):
    """The anchor warning is for figures that move: a GT that starts one scan late, where the
    sigma (0.1 mm, growing 1 cm/s) is a sliver of the run's median, aligns on that scan and
    says so, without the warning; the same GT with sigmas of 3 cm throughout warns."""
    out, gt = make_run_dir(tmp_path)
    rows = np.loadtxt(gt)
    t_est = np.loadtxt(out / "trajectory.tum")[:, 0]
    late = tmp_path / "one_scan_late.tum"
    np.savetxt(late, rows[rows[:, 0] >= t_est[1] - 0.005], fmt="%.9f")
    _with_sigma_columns(out, sigma_m=1e-4, growth_m_s=0.01)
    make_report(out, late)
    metrics = json.loads((out / "metrics.json").read_text())
    assert not metrics["sigma"]["anchor_is_first_scan"] and not metrics["warnings"]
    _with_sigma_columns(out)
    make_report(out, late)
    assert json.loads((out / "metrics.json").read_text())["warnings"]


@pytest.mark.parametrize("base", [(0, 0, -1), (0, 0, 1), (1, 0, 0), (0, -1, 0),
                                  (0.3, 0.2, -0.93), (0.2, 0.1, 0.97)])
def test_leveling_turns_up_to_z_with_a_heading_that_moves_as_little_as_up(base):
    """The figures' leveling takes up to +z, and two ups a fraction of a degree apart (the tilt
    by which a z-down rig's figures differed) give levelings a fraction of a degree apart: the
    same walk is drawn in the same heading (the smallest rotation alone turned an up near -z by
    180 deg about an axis set by that tilt)."""
    from adalio.eval.report import leveling

    rng = np.random.default_rng(5)
    base = np.asarray(base, dtype=np.float64) / np.linalg.norm(base)
    for _ in range(50):
        ups = [Rotation.from_rotvec(np.radians(0.3) * v / np.linalg.norm(v)).apply(base)
               for v in rng.normal(size=(2, 3))]
        R1, R2 = (leveling(u) for u in ups)
        for R, u in ((R1, ups[0]), (R2, ups[1])):
            np.testing.assert_allclose(R @ u, [0, 0, 1], atol=1e-9)
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
            assert np.linalg.det(R) == pytest.approx(1.0)
        # the two figures' frames differ by less than a degree (ups are <= 0.6 deg apart)
        assert np.degrees(Rotation.from_matrix(R1 @ R2.T).magnitude()) < 1.0


def test_report_with_a_gt_of_the_still_start_only_keeps_the_rest(tmp_path):
    """A GT that covers only a stretch at rest (the first 2 s, not moving) cannot be
    SE(3)-aligned: `adalio report` still writes the report and its figures without the
    ground-truth sections, says why on stderr and in report.md, and its hint names a command
    that exists (`adalio eval <the run's trajectory> <the GT> --align first`), not options that
    `report` lacks (was: exit 2, no report, 'use --align first or a larger --max-diff')."""
    from adalio.cli import app

    out, gt = make_run_dir(tmp_path)
    rows = np.loadtxt(gt)
    still = rows[rows[:, 0] <= rows[0, 0] + 2.0].copy()
    still[:, 1:] = rows[0, 1:]
    still_gt = tmp_path / "still.tum"
    np.savetxt(still_gt, still, fmt="%.9f")
    with pytest.raises(InputError, match="a stretch at rest") as exc:  # the Python default
        make_report(out, still_gt)
    est = out / "trajectory.tum"
    assert f"`adalio eval {est} {still_gt} --align first`" in str(exc.value)
    assert "use --align" not in str(exc.value)
    res = CliRunner().invoke(app, ["report", str(out), "--gt", str(still_gt)])
    assert res.exit_code == 0, res.output + repr(res.exception)
    assert f"warning: --gt {still_gt} is not used: se3 alignment failed" in res.stderr
    assert f"`adalio eval {est} {still_gt} --align first`" in res.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert "ate_se3" not in metrics and "a stretch at rest" in metrics["gt_not_used"]
    text = (out / "report.md").read_text()
    assert "**not used**" in text and "Absolute trajectory error" not in text
    for name in ("trajectory_top.png", "trajectory_side.png", "degeneracy.png", "map_top.png"):
        assert_png_image(out / name)
        assert f"]({name})" in text
    # a GT of another clock (no pair at all) stays an error
    other = tmp_path / "other.tum"
    rows[:, 0] += 1e5
    np.savetxt(other, rows, fmt="%.9f")
    res = CliRunner().invoke(app, ["report", str(out), "--gt", str(other)])
    assert isinstance(res.exception, InputError) and "no estimate/GT pose pairs" in str(
        res.exception)


def test_too_few_pairs_hint_names_a_command_not_an_option():
    """Fewer than 3 pairs: the hint is a command the user can run (report, compare and run
    --gt share the message and have no --align / --max-diff of their own)."""
    from evo.core.trajectory import PoseTrajectory3D

    from adalio.eval.metrics import align_pair

    t = np.arange(10) * 0.1
    est = PoseTrajectory3D(positions_xyz=np.column_stack([t, t * 0, t * 0]),
                           orientations_quat_wxyz=np.tile([1.0, 0, 0, 0], (10, 1)), timestamps=t)
    gt = PoseTrajectory3D(positions_xyz=np.zeros((2, 3)),
                          orientations_quat_wxyz=np.tile([1.0, 0, 0, 0], (2, 1)),
                          timestamps=t[:2].copy())
    with pytest.raises(InputError, match=r"only 2 associated poses") as exc:
        align_pair(est, gt)
    assert "`adalio eval EST GT --align first`" in str(exc.value)
    assert "use --align" not in str(exc.value)


def test_report_removes_an_earlier_reports_figures_it_does_not_make(tmp_path):
    """A report with a GT and sigma columns draws error.png and error_sigma.png; a report without
    a GT into the same folder must not leave them beside a report.md that no longer has a GT.
    Files that are not a report's stay."""
    from adalio.io.writers import REPORT_FILES

    out, gt = make_run_dir(tmp_path)
    _with_sigma_columns(out)
    (out / "notes.png").write_bytes(b"mine")
    make_report(out, gt)
    assert (out / "error.png").is_file() and (out / "error_sigma.png").is_file()
    text = make_report(out).read_text()
    pngs = {p.name for p in out.glob("*.png")}
    linked = {name for name in REPORT_FILES if f"]({name})" in text}
    assert pngs == linked | {"notes.png"}
    assert not (out / "error.png").exists() and not (out / "error_sigma.png").exists()


def test_report_tables_show_millimetre_errors(tmp_path):
    """An estimate 1.5 mm off the GT: the ATE / RPE cells of report.md read back within 0.05 mm
    of ate() / rpe() (metres to 3 decimals read 1.5 mm as 0.001 or 0.002), and compare's table
    (same cells) as well."""
    from adalio.eval.compare import ModeResult, table_rows
    from adalio.eval.metrics import rpe

    out, gt = make_run_dir(tmp_path)
    rows = np.loadtxt(gt)[::10]
    rows[:, 1:4] += np.random.default_rng(2).normal(0, 0.0015 / np.sqrt(3), (len(rows), 3))
    np.savetxt(out / "trajectory.tum", rows, fmt="%.9f")
    text = make_report(out, gt).read_text()
    a = ate(out / "trajectory.tum", gt, "se3")
    assert 0.0005 < a["rmse_m"] < 0.003
    cells = next(line for line in text.splitlines() if line.startswith("| se3 |")).split("|")
    for cell, key in zip(cells[2:6], ("rmse_m", "mean_m", "median_m", "max_m"), strict=True):
        assert float(cell) == pytest.approx(a[key], abs=5e-5)
    r = rpe(out / "trajectory.tum", gt)[0]
    cells = next(line for line in text.splitlines() if line.startswith("| 1 |")).split("|")
    assert float(cells[2]) == pytest.approx(r["rmse_m"], abs=5e-5)
    cells = table_rows([ModeResult("fixed", str(out), ate_rmse_m=a["rmse_m"],
                                   max_error_m=a["max_m"])])[0]
    assert float(cells[1]) == pytest.approx(a["rmse_m"], abs=5e-5)
    assert float(cells[2]) == pytest.approx(a["max_m"], abs=5e-5)
