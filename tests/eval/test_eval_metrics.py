"""ATE / RPE against hand computations in numpy (independent of evo)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp
from typer.testing import CliRunner

from adalio.errors import AdalioError, InputError
from adalio.eval.metrics import align_pair, ate, rpe


def write_tum(path: Path, t_s: np.ndarray, xyz: np.ndarray, rot: Rotation) -> Path:
    q = rot.as_quat()  # x y z w
    rows = np.column_stack([t_s, xyz, q])
    np.savetxt(path, rows, fmt="%.9f", delimiter=" ")
    return path


def umeyama_np(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimizing sum |dst - (R src + t)|^2 (Umeyama 1991, no scale)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    return R, mu_d - R @ mu_s


@pytest.fixture(scope="module")
def synthetic_pair(tmp_path_factory):
    """Dense GT (100 Hz) and a 10 Hz estimate with a rigid offset, position and heading noise."""
    d = tmp_path_factory.mktemp("pair")
    rng = np.random.default_rng(7)
    t_gt = 1000.0 + np.arange(0, 20.0, 0.01)
    xyz_gt = np.column_stack([3 * np.cos(0.3 * (t_gt - 1000)), 2 * np.sin(0.5 * (t_gt - 1000)),
                              0.1 * (t_gt - 1000)])
    rot_gt = Rotation.from_euler("zyx", np.column_stack([0.4 * (t_gt - 1000),
                                                         0.1 * np.sin(t_gt), 0.05 * np.cos(t_gt)]))
    # estimate: 10 Hz, stamps jittered by up to 4 ms around GT stamps
    idx = np.arange(5, len(t_gt) - 5, 10)
    t_est = t_gt[idx] + rng.uniform(-0.004, 0.004, idx.size)
    R_off = Rotation.from_euler("xyz", [10, -5, 35], degrees=True)
    t_off = np.array([1.5, -2.0, 0.3])
    noise = rng.normal(0, 0.02, (idx.size, 3))
    xyz_est = R_off.apply(xyz_gt[idx]) + t_off + noise
    rot_noise = Rotation.from_rotvec(rng.normal(0, np.deg2rad(1.0), (idx.size, 3)))
    rot_est = R_off * rot_gt[idx] * rot_noise
    gt = write_tum(d / "gt.tum", t_gt, xyz_gt, rot_gt)
    est = write_tum(d / "est.tum", t_est, xyz_est, rot_est)
    # expected values use the numbers as written (9 decimals)
    t_gt, xyz_gt, rot_gt = _reload(gt)
    t_est, xyz_est, rot_est = _reload(est)
    # independent association: nearest GT stamp to each estimate stamp, and the GT interpolated
    # there (numpy's linear interpolation, scipy's Slerp class): the GT is 100 Hz, so every
    # estimate has GT poses within the 20 ms default on both sides
    nearest = np.abs(t_gt[None, :] - t_est[:, None]).argmin(1)
    xyz_i = np.column_stack([np.interp(t_est, t_gt, xyz_gt[:, k]) for k in range(3)])
    rot_i = Slerp(t_gt, rot_gt)(t_est)
    return {"gt": gt, "est": est, "xyz_gt": xyz_i, "rot_gt": rot_i,
            "xyz_gt_nearest": xyz_gt[nearest], "xyz_est": xyz_est, "rot_est": rot_est,
            "noise": noise, "nearest": nearest, "idx": idx}


def _reload(path: Path) -> tuple[np.ndarray, np.ndarray, Rotation]:
    m = np.loadtxt(path)
    return m[:, 0], m[:, 1:4], Rotation.from_quat(m[:, 4:8])


def _stats(err: np.ndarray) -> dict:
    return {"rmse_m": np.sqrt(np.mean(err**2)), "mean_m": err.mean(), "median_m": np.median(err),
            "max_m": err.max(), "n": err.size}


def _check(result: dict, expected: dict) -> None:
    assert result["n"] == expected["n"]
    for key in ("rmse_m", "mean_m", "median_m", "max_m"):
        assert result[key] == pytest.approx(expected[key], rel=1e-9, abs=1e-12), key


def test_association_is_nearest_gt_without_interpolation(synthetic_pair):
    assert np.array_equal(synthetic_pair["nearest"], synthetic_pair["idx"])
    pair = align_pair(synthetic_pair["est"], synthetic_pair["gt"], "none", interpolate=False)
    assert np.allclose(pair.gt.positions_xyz, synthetic_pair["xyz_gt_nearest"], atol=1e-8)


def test_gt_is_interpolated_at_the_estimate_stamps(synthetic_pair):
    p = synthetic_pair
    pair = align_pair(p["est"], p["gt"], "none")
    assert np.allclose(pair.gt.positions_xyz, p["xyz_gt"], atol=1e-8)
    rot = Rotation.from_quat(np.asarray(pair.gt.orientations_quat_wxyz)[:, [1, 2, 3, 0]])
    assert np.degrees((rot.inv() * p["rot_gt"]).magnitude()).max() < 1e-6
    np.testing.assert_array_equal(pair.gt.timestamps, pair.est.timestamps)


def test_interpolated_gt_removes_the_motion_between_stamps(tmp_path):
    """An exact estimate whose stamps sit 3.6 ms off a 100 Hz GT grid (the simulated OS1-64's
    scans against its GT): paired with the nearest GT pose it shows the 4.5 mm the sensor
    moves in 3.6 ms at 1.25 m/s (and the turn's 0.1 deg); with the GT interpolated, what is
    left is the interpolation's own error on the arc (far below a millimetre). Quaternion signs
    flip from pose to pose in the GT file; the slerp must take the short way anyway."""
    speed, radius, yaw_rate = 1.25, 2.0, np.radians(30.0)

    def truth(t):
        a = speed / radius * t
        xyz = np.column_stack([radius * np.cos(a), radius * np.sin(a), 0.1 * t])
        return xyz, Rotation.from_euler("zyx", np.column_stack(
            [yaw_rate * t, 0.2 * np.sin(t), 0.1 * np.cos(2 * t)]))

    t_gt = 100.0 + np.arange(0, 10.0, 0.01)
    xyz, rot = truth(t_gt - 100.0)
    q = rot.as_quat()
    q[1::2] *= -1.0  # the same rotations, the other sign
    np.savetxt(tmp_path / "gt.tum", np.column_stack([t_gt, xyz, q]), fmt="%.9f")
    t_est = t_gt[5:-5:10] + 0.0036
    xyz_e, rot_e = truth(t_est - 100.0)
    est = write_tum(tmp_path / "est.tum", t_est, xyz_e, rot_e)
    near = ate(est, tmp_path / "gt.tum", align="none", interpolate=False)
    interp = ate(est, tmp_path / "gt.tum", align="none")
    assert near["n"] == interp["n"] == t_est.size
    assert near["mean_m"] == pytest.approx(np.hypot(speed, 0.1) * 0.0036, rel=0.02)
    assert interp["max_m"] < 2e-5
    r_near = rpe(est, tmp_path / "gt.tum", [1.0], interpolate=False)[0]["rot_rmse_deg"]
    r_interp = rpe(est, tmp_path / "gt.tum", [1.0])[0]["rot_rmse_deg"]
    assert r_near > 0.05 and r_interp < 1e-3


def test_sparse_gt_is_not_interpolated(tmp_path):
    """GT poses more than max_diff apart on either side of an estimate are not bridged: the
    estimate keeps its nearest GT pose."""
    from adalio.eval.metrics import associate

    t_gt = 10.0 + np.arange(0, 5, 0.1)  # 10 Hz: no estimate has GT within 20 ms on both sides
    xyz = np.column_stack([t_gt, t_gt**2, np.zeros_like(t_gt)])
    gt = write_tum(tmp_path / "gt.tum", t_gt, xyz, Rotation.identity(t_gt.size))
    t_est = t_gt[1:-1] + 0.015
    est = write_tum(tmp_path / "est.tum", t_est, xyz[1:-1], Rotation.identity(t_est.size))
    gt_s, _ = associate(est, gt)
    np.testing.assert_allclose(gt_s.positions_xyz, xyz[1:-1], atol=1e-9)


def test_ate_none_is_raw_difference(synthetic_pair):
    p = synthetic_pair
    err = np.linalg.norm(p["xyz_est"] - p["xyz_gt"], axis=1)
    _check(ate(p["est"], p["gt"], align="none"), _stats(err))
    assert err.mean() > 1.0  # the rigid offset dominates without alignment


def test_ate_first_pose_composition(synthetic_pair):
    p = synthetic_pair
    T_gt0 = np.eye(4)
    T_gt0[:3, :3] = p["rot_gt"][0].as_matrix()
    T_gt0[:3, 3] = p["xyz_gt"][0]
    T_est0 = np.eye(4)
    T_est0[:3, :3] = p["rot_est"][0].as_matrix()
    T_est0[:3, 3] = p["xyz_est"][0]
    T = T_gt0 @ np.linalg.inv(T_est0)
    aligned = p["xyz_est"] @ T[:3, :3].T + T[:3, 3]
    err = np.linalg.norm(aligned - p["xyz_gt"], axis=1)
    _check(ate(p["est"], p["gt"], align="first"), _stats(err))
    assert err[0] == pytest.approx(0.0, abs=1e-9)


def test_ate_se3_umeyama(synthetic_pair):
    p = synthetic_pair
    R, t = umeyama_np(p["xyz_est"], p["xyz_gt"])
    err = np.linalg.norm(p["xyz_est"] @ R.T + t - p["xyz_gt"], axis=1)
    res = ate(p["est"], p["gt"], align="se3")
    _check(res, _stats(err))
    # with the rigid offset removed, what is left is the injected noise (sigma 2 cm per axis)
    assert res["rmse_m"] == pytest.approx(np.sqrt(np.mean(np.sum(p["noise"]**2, 1))), rel=0.05)


def test_denser_estimate_associates_each_gt(tmp_path):
    t_gt = 10.0 + np.arange(0, 5, 0.5)
    xyz = np.column_stack([t_gt, np.sin(t_gt), 0.2 * t_gt**1.5])
    gt = write_tum(tmp_path / "gt.tum", t_gt, xyz, Rotation.identity(t_gt.size))
    t_est = 10.0 + np.arange(0, 5, 0.01) + 0.003
    xyz_est = np.column_stack([t_est, np.sin(t_est), 0.2 * t_est**1.5])
    est = write_tum(tmp_path / "est.tum", t_est, xyz_est, Rotation.identity(t_est.size))
    res = ate(est, gt, align="none")
    assert res["n"] == t_gt.size
    assert res["max_m"] < 0.01  # nearest estimate is 3 ms away


def test_gt_shorter_than_the_run_pairs_each_estimate_once(tmp_path):
    """A 100 Hz GT over 0.7 s has fewer poses (70) than a 10 Hz estimate over 20 s (200): each
    estimate within the GT's reach is still one pair, with the GT interpolated at its stamp."""
    t_gt = 100.0 + np.arange(70) * 0.01

    def path(t):
        return np.column_stack([np.sin(t), 0.5 * t, np.cos(2 * t)])

    gt = write_tum(tmp_path / "gt.tum", t_gt, path(t_gt), Rotation.identity(t_gt.size))
    t_est = 96.0 + np.arange(200) * 0.1 + 0.054
    rng = np.random.default_rng(3)
    xyz_est = path(t_est) + rng.normal(0, 0.01, (t_est.size, 3))
    est = write_tum(tmp_path / "est.tum", t_est, xyz_est, Rotation.identity(t_est.size))
    t_gt, xyz_gt, _ = _reload(gt)
    t_est, xyz_est, _ = _reload(est)
    # brute force: the estimates with a GT stamp within 20 ms; inside the GT's span (every one
    # here) the GT linearly interpolated at the estimate's stamp
    near = np.array([np.min(np.abs(t_gt - t)) <= 0.02 for t in t_est])
    assert np.all((t_est[near] > t_gt[0]) & (t_est[near] < t_gt[-1]))
    xyz_i = np.column_stack([np.interp(t_est[near], t_gt, xyz_gt[:, k]) for k in range(3)])
    res = ate(est, gt, align="none")
    _check(res, _stats(np.linalg.norm(xyz_est[near] - xyz_i, axis=1)))
    assert res["n"] == 7


def test_estimate_side_association_is_evo_s_when_the_gt_is_denser(synthetic_pair):
    """With no more estimated poses than GT poses, the pairs are evo's associate_trajectories'
    (the figures of every run against a dense GT stay as they were)."""
    from evo.core import sync

    from adalio.eval.files import read_trajectory
    from adalio.eval.metrics import associate, interpolate_gt

    p = synthetic_pair
    est_t = read_trajectory(p["est"], "estimate")
    gt_t = read_trajectory(p["gt"], "ground-truth")
    assert est_t.num_poses < gt_t.num_poses
    for max_diff in (0.02, 0.003):
        gt_e, est_e = sync.associate_trajectories(gt_t, est_t, max_diff=max_diff)
        gt_s, est_s = associate(p["est"], p["gt"], max_diff, interpolate=False)
        np.testing.assert_array_equal(est_s.timestamps, est_e.timestamps)
        np.testing.assert_array_equal(gt_s.timestamps, gt_e.timestamps)
        np.testing.assert_array_equal(gt_s.positions_xyz, gt_e.positions_xyz)
        gt_s, _ = associate(p["est"], p["gt"], max_diff)
        gt_i = interpolate_gt(gt_t, gt_e, np.asarray(est_e.timestamps), max_diff)
        np.testing.assert_array_equal(gt_s.positions_xyz, gt_i.positions_xyz)
        np.testing.assert_array_equal(gt_s.orientations_quat_wxyz, gt_i.orientations_quat_wxyz)


def test_sparse_gt_pose_pairs_with_its_nearest_estimate_only(tmp_path):
    """A 1 Hz GT against a 100 Hz estimate: several estimates lie within --max-diff of each GT
    pose; the GT pose (not interpolated) is paired once, with the nearest of them."""
    t_gt = 10.0 + np.arange(8.0)
    gt = write_tum(tmp_path / "gt.tum", t_gt, np.column_stack([t_gt, 0 * t_gt, 0 * t_gt]),
                   Rotation.identity(t_gt.size))
    t_est = 9.5 + np.arange(900) * 0.01 + 0.0025
    est = write_tum(tmp_path / "est.tum", t_est, np.column_stack([t_est, 0 * t_est, 0 * t_est]),
                    Rotation.identity(t_est.size))
    t_gt, _, _ = _reload(gt)
    t_est, _, _ = _reload(est)
    nearest = np.array([np.argmin(np.abs(t_est - t)) for t in t_gt])
    for interpolate in (True, False):
        pair = align_pair(est, gt, "none", 0.02, interpolate=interpolate)
        np.testing.assert_array_equal(pair.est.timestamps, t_est[nearest])
        np.testing.assert_allclose(pair.errors_m, np.abs(t_est[nearest] - t_gt), atol=1e-9)


def test_max_diff_controls_association(tmp_path, synthetic_pair):
    t, xyz, rot = _reload(synthetic_pair["gt"])
    sparse = write_tum(tmp_path / "sparse.tum", t[::50], xyz[::50], rot[::50])  # 2 Hz
    late = write_tum(tmp_path / "late.tum", t[::50] + 0.05, xyz[::50], rot[::50])
    with pytest.raises(InputError, match="no estimate/GT pose pairs"):
        ate(late, sparse)
    assert ate(late, sparse, max_diff_s=0.06)["n"] == t[::50].size


def test_rpe_scale_drift(tmp_path):
    t = 50.0 + np.arange(0, 10, 0.05)
    xyz = np.column_stack([t - 50.0, np.zeros_like(t), np.zeros_like(t)])  # 1 m/s along x
    rot = Rotation.from_euler("z", np.full((t.size, 1), 20.0), degrees=True)
    gt = write_tum(tmp_path / "gt.tum", t, xyz, rot)
    est = write_tum(tmp_path / "est.tum", t, xyz * 1.02, rot)
    rigid = write_tum(tmp_path / "rigid.tum", t,
                      Rotation.from_euler("z", 40, degrees=True).apply(xyz) + [3, 1, 2],
                      Rotation.from_euler("z", 40, degrees=True) * rot)
    rows = {r["delta_m"]: r for r in rpe(est, gt, (1.0, 5.0, 50.0))}
    for delta in (1.0, 5.0):
        assert rows[delta]["n"] > 0
        # 2 % scale error: the relative translation error is 0.02 x segment length
        assert rows[delta]["mean_m"] == pytest.approx(0.02 * delta, rel=0.12)
        assert rows[delta]["rot_rmse_deg"] == pytest.approx(0.0, abs=1e-6)
    assert rows[50.0]["n"] == 0 and rows[50.0]["rmse_m"] is None
    assert all(r["max_m"] < 1e-6 for r in rpe(rigid, gt, (1.0, 5.0)))


def test_bad_files(tmp_path, synthetic_pair):
    bad = tmp_path / "bad.txt"
    bad.write_text("hello world\n1 2 3\n")
    with pytest.raises(InputError, match="not a TUM trajectory"):
        ate(bad, synthetic_pair["gt"])
    with pytest.raises(InputError, match="does not exist"):
        ate(tmp_path / "missing.tum", synthetic_pair["gt"])
    back = tmp_path / "back.tum"
    back.write_text("2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="time goes backwards"):
        ate(back, synthetic_pair["gt"])
    with pytest.raises(InputError, match="--align"):
        ate(synthetic_pair["est"], synthetic_pair["gt"], align="sim3")


def test_equal_time_stamps(tmp_path, synthetic_pair):
    """A line repeated as it is is read once (the same ATE as without it); two different poses
    at one time stamp are an error naming the file and the two poses (the GT with every 10th row
    repeated 1 m off gave an ATE of 0.21 m for 1.5 mm, an estimate whose rows all carried one
    stamp was scored)."""
    p = synthetic_pair
    lines = p["gt"].read_text().splitlines(keepends=True)
    repeated, conflict = [], []
    for k, line in enumerate(lines):
        repeated.append(line)
        conflict.append(line)
        if k % 10 == 0:
            repeated.append(line)
            f = line.split()
            f[1] = f"{float(f[1]) + 1.0:.9f}"
            conflict.append(" ".join(f) + "\n")
    (tmp_path / "repeated.tum").write_text("".join(repeated))
    # from the GT's second line on: its 10th line is pose 10, its 1 m twin pose 11
    (tmp_path / "conflict.tum").write_text("# t x y z qx qy qz qw\n" + "".join(conflict[2:]))
    assert ate(p["est"], tmp_path / "repeated.tum") == ate(p["est"], p["gt"])
    with pytest.raises(InputError, match=r"ground-truth file .*conflict\.tum: poses 10 and 11 "
                                         r"have the same time stamp"):
        ate(p["est"], tmp_path / "conflict.tum")
    est_lines = p["est"].read_text().splitlines()
    one_stamp = [" ".join(["1005.0", *line.split()[1:]]) for line in est_lines]
    (tmp_path / "one_stamp.tum").write_text("\n".join(one_stamp) + "\n")
    with pytest.raises(InputError, match=r"estimate file .*one_stamp\.tum: poses 1 and 2"):
        ate(tmp_path / "one_stamp.tum", p["gt"], align="first")


def test_bad_file_messages_say_what_and_where(tmp_path, synthetic_pair):
    """A folder is called a folder (not 'does not exist'), naming the run's trajectory.tum when
    it holds one; a line that is not 8 numbers is named by its number in the file (comments and
    blank lines counted); coordinates beyond 1e9 m are refused naming the pose, with no numpy
    warning on stderr (1e200 gave an ATE of inf and exit 0, 1e308 RuntimeWarnings)."""
    gt = synthetic_pair["gt"]
    folder = tmp_path / "run"
    folder.mkdir()
    with pytest.raises(InputError, match=r"estimate file .*run is a folder, not a TUM "
                                         r"trajectory: give a TUM file"):
        ate(folder, gt)
    (folder / "trajectory.tum").write_text(synthetic_pair["est"].read_text())
    with pytest.raises(InputError, match=r"is a folder.*run/trajectory\.tum\?"):
        ate(synthetic_pair["est"], folder)
    lines = gt.read_text().splitlines()
    bad = tmp_path / "bad_line.tum"
    bad.write_text("# t x y z qx qy qz qw\n\n" + "\n".join(lines[:300]) + "\n1000.0 1 2 3\n"
                   + "\n".join(lines[300:]) + "\n")
    with pytest.raises(InputError, match=r"line 303 \('1000\.0 1 2 3'\) has 4 numbers"):
        ate(synthetic_pair["est"], bad)
    words = tmp_path / "words.tum"
    words.write_text("\n".join(lines[:5]) + "\n1000.0 1 2 3 0 0 0 one\n")
    with pytest.raises(InputError, match=r"line 6 .* has text that is not a number"):
        ate(synthetic_pair["est"], words)
    for value in ("1e200", "1e308", "-2e9"):
        far = tmp_path / f"far{value}.tum"
        rows = [line.split() for line in lines]
        rows[7][2] = value
        far.write_text("\n".join(" ".join(r) for r in rows) + "\n")
        proc = subprocess.run([sys.executable, "-m", "adalio.cli", "eval",
                               str(synthetic_pair["est"]), str(far)], capture_output=True,
                              text=True, timeout=120, check=False)
        assert proc.returncode == 2, proc.stdout
        expected = (f"error: ground-truth file {far}: pose 8 has a coordinate of "
                    f"{float(value):g} m, beyond ±1e+09 m: are its x y z in metres?")
        assert proc.stderr.strip().splitlines() == [expected]


def test_cli_json_and_table(synthetic_pair):
    import json

    from adalio.cli import app

    runner = CliRunner()
    p = synthetic_pair
    out = runner.invoke(app, ["eval", str(p["est"]), str(p["gt"]), "--json", "--align", "first"])
    assert out.exit_code == 0, out.output
    data = json.loads(out.output)
    assert data["ate"] == ate(p["est"], p["gt"], align="first")
    assert [r["delta_m"] for r in data["rpe"]] == [1.0, 5.0]
    out = runner.invoke(app, ["eval", str(p["est"]), str(p["gt"]), "--json", "--align", "first",
                              "--nearest"])
    assert out.exit_code == 0, out.output
    assert json.loads(out.output)["ate"] == ate(p["est"], p["gt"], align="first",
                                                interpolate=False)
    assert json.loads(out.output)["ate"] != data["ate"]
    out = runner.invoke(app, ["eval", str(p["est"]), str(p["gt"]), "--rpe-delta", "2"])
    assert out.exit_code == 0 and "RMSE" in out.output
    out = runner.invoke(app, ["eval", str(p["est"]), "/nonexistent.tum"])
    assert isinstance(out.exception, AdalioError)


@pytest.mark.parametrize("text, deltas", [("1 5", (1.0, 5.0)), ("1, 5", (1.0, 5.0)),
                                           (" 1 ,5 ", (1.0, 5.0)), ("0.5\t2  5", (0.5, 2.0, 5.0))])
def test_cli_rpe_delta_takes_commas_and_or_spaces(synthetic_pair, text, deltas):
    import json

    from adalio.cli import app

    p = synthetic_pair
    out = CliRunner().invoke(app, ["eval", str(p["est"]), str(p["gt"]), "--json",
                                   "--rpe-delta", text])
    assert out.exit_code == 0, out.output
    assert json.loads(out.output)["rpe"] == rpe(p["est"], p["gt"], deltas)


def test_cli_rpe_delta_not_numbers_is_an_error(synthetic_pair):
    from adalio.cli import app

    p = synthetic_pair
    out = CliRunner().invoke(app, ["eval", str(p["est"]), str(p["gt"]), "--rpe-delta", "1;5"])
    assert out.exit_code != 0
    assert isinstance(out.exception, InputError) and "--rpe-delta" in str(out.exception)


def test_cli_table_says_how_the_gt_poses_were_paired(tmp_path, synthetic_pair):
    """The ATE table's title says 'GT interpolated' only where the GT was interpolated: a 2 Hz GT
    keeps the nearest pose (the title said 'GT interpolated' there too), a GT that ends inside
    the run has the nearest pose past its end; counted by brute force."""
    import json

    from adalio.cli import app

    p = synthetic_pair
    t, xyz, rot = _reload(p["gt"])
    sparse = write_tum(tmp_path / "sparse.tum", t[5::50], xyz[5::50], rot[5::50])
    cut = write_tum(tmp_path / "cut.tum", t[:1005], xyz[:1005], rot[:1005])
    t_est = _reload(p["est"])[0]
    for gt, title in ((p["gt"], "GT interpolated,"), (sparse, "nearest GT pose,"),
                      (cut, None)):
        tg = _reload(gt)[0]
        paired = np.array([np.min(np.abs(tg - x)) <= 0.02 for x in t_est])
        inside = np.array([np.any((tg < x) & (tg >= x - 0.02)) and np.any((tg >= x) &
                                                                          (tg <= x + 0.02))
                           for x in t_est])
        n, k = int(paired.sum()), int((paired & inside).sum())
        if title is None:
            assert 0 < k < n
            title = f"GT interpolated at {k}, nearest GT pose at {n - k},"
        res = CliRunner().invoke(app, ["eval", str(p["est"]), str(gt)], terminal_width=300)
        assert res.exit_code == 0, res.output
        assert f"{n} pairs within 0.02 s, {title}" in res.output
        res = CliRunner().invoke(app, ["eval", str(p["est"]), str(gt), "--json"])
        assert json.loads(res.output)["ate"]["n_interpolated"] == k


def test_cli_error_is_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "adalio.cli", "eval", str(tmp_path / "a.tum"),
                           str(tmp_path / "b.tum")], capture_output=True, text=True, timeout=120,
                          check=False)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "does not exist" in proc.stderr


@pytest.mark.parametrize("scale", [1.0, 0.5, 10.0])
def test_sigma_consistency_against_known_errors(tmp_path, scale):
    """The estimate is the GT moved by an arbitrary rigid transform (the first-pose alignment
    must undo it), rotated-frame errors drawn with known per-axis sigma: honest sigmas give 99.7 %
    within 3 sigma, NEES 3 and a median |error| / sigma of 0.674; sigmas reported at half the
    truth give NEES 12; ten times the truth pass the 3-sigma test on every scan, and only the
    median |error| / sigma (0.067) shows them."""
    from adalio.eval.metrics import MEDIAN_ABS_Z, sigma_consistency

    rng = np.random.default_rng(7)
    n = 4000
    t = 100.0 + 0.1 * np.arange(n)
    xyz_gt = np.column_stack([np.cos(0.01 * t), np.sin(0.013 * t), 0.001 * t]) * 5.0
    rot_gt = Rotation.from_euler("z", 0.02 * t[:, None])
    T = Rotation.from_euler("zyx", [0.7, -0.2, 0.1])
    shift = np.array([3.0, -1.0, 0.5])
    sigma = np.column_stack([0.01 + 0.005 * np.sin(0.003 * t), np.full(n, 0.02),
                             0.03 + 0.02 * (t - t[0]) / (t[-1] - t[0])])
    err = rng.normal(size=(n, 3)) * sigma
    err[0] = 0.0  # the first pose defines the alignment
    # est world = T * gt world (+ errors expressed in the est world)
    xyz_est = T.apply(xyz_gt - xyz_gt[0]) + shift + err
    rot_est = T * rot_gt
    gt = write_tum(tmp_path / "gt.tum", t, xyz_gt, rot_gt)
    est = write_tum(tmp_path / "est.tum", t, xyz_est, rot_est)
    scans = {"t_s": t, "sigma_x_m": sigma[:, 0] * scale, "sigma_y_m": sigma[:, 1] * scale,
             "sigma_z_m": sigma[:, 2] * scale}
    c = sigma_consistency(est, gt, scans)
    assert len(c.t_s) == n
    np.testing.assert_allclose(c.errors_world_m, err, atol=1e-6)
    z = err / sigma
    np.testing.assert_allclose(c.within_3sigma, np.mean(np.abs(z / scale) <= 3, axis=0))
    assert abs(c.mean_nees - 3.0 / scale**2) < 0.1 * 3.0 / scale**2
    np.testing.assert_allclose(c.median_abs_z, np.median(np.abs(z), axis=0) / scale, rtol=1e-4)
    np.testing.assert_allclose(c.median_abs_z, MEDIAN_ABS_Z / scale, rtol=0.06)
    if scale >= 1.0:
        assert np.all(c.within_3sigma > 0.99)
    else:
        assert np.all(c.within_3sigma < 0.9)
    with pytest.raises(InputError, match="sigma_x_m"):
        sigma_consistency(est, gt, {"t_s": t})


def test_increment_correlation_tells_drift_from_random_walk_and_swing():
    """Error series with known increment structure, sampled at 10 Hz with jittered times: a
    random walk (independent 1 s increments, correlation 0), an AR(1) increment process with
    coefficient 0.8 (a drift that persists; correlation 0.8) and white noise on a fixed
    offset (increments e_k+1 - e_k, correlation -0.5); the 1 s sampling and the per-axis result
    are checked against these values."""
    from adalio.eval.metrics import increment_correlation

    rng = np.random.default_rng(21)
    n_s = 4000  # seconds
    t = np.arange(n_s * 10) * 0.1 + rng.uniform(0, 0.02, n_s * 10)
    walk = np.cumsum(rng.normal(size=n_s))
    ar = np.zeros(n_s)
    for k in range(1, n_s):
        ar[k] = 0.8 * ar[k - 1] + rng.normal()
    drift = np.cumsum(ar)
    swing = rng.normal(size=n_s)
    per_second = np.column_stack([walk, drift, swing])
    err = per_second[np.minimum(((t - t[0]) // 1.0).astype(int), n_s - 1)]
    r = increment_correlation(t, err)
    np.testing.assert_allclose(r, [0.0, 0.8, -0.5], atol=0.06)
    assert np.isnan(increment_correlation(t[:25], err[:25])).all()


def test_sigma_consistency_aligns_on_the_filter_s_first_scan_not_the_backfill(tmp_path):
    """With a backfill (poses before the filter's first scan, written after it), the sigmas are
    relative to the filter's first scan: the errors must be measured from there too. The
    estimate is the GT rigidly moved, with a drift that is zero at the anchor scan and grows on
    both sides; the recovered errors are that drift exactly, also for the backfilled poses."""
    from adalio.eval.metrics import sigma_consistency

    n, anchor = 300, 120
    t = 50.0 + 0.1 * np.arange(n)
    xyz_gt = np.column_stack([np.cos(0.05 * t), np.sin(0.04 * t), 0.01 * t]) * 3.0
    rot_gt = Rotation.from_euler("z", 0.03 * t[:, None])
    T = Rotation.from_euler("zyx", [-1.1, 0.1, 0.3])
    drift = np.column_stack([0.01, -0.02, 0.005]) * (t - t[anchor])[:, None]
    xyz_est = T.apply(xyz_gt - xyz_gt[anchor]) + np.array([1.0, 2.0, -0.3]) + drift
    gt = write_tum(tmp_path / "gt.tum", t, xyz_gt, rot_gt)
    est = write_tum(tmp_path / "est.tum", t, xyz_est, T * rot_gt)
    sigma = 0.01 + np.abs(t - t[anchor])[:, None] * np.array([0.01, 0.02, 0.005])
    backfill = (np.arange(n) < anchor).astype(float)
    rows = np.r_[np.arange(anchor, n), np.arange(anchor)]  # backfill rows written last
    scans = {"t_s": t[rows], "backfill": backfill[rows], "sigma_x_m": sigma[rows, 0],
             "sigma_y_m": sigma[rows, 1], "sigma_z_m": sigma[rows, 2]}
    c = sigma_consistency(est, gt, scans)
    np.testing.assert_allclose(c.errors_world_m, drift, atol=1e-6)
    np.testing.assert_allclose(c.sigma_world_m, sigma, atol=1e-12)
    assert np.all(c.within_3sigma == 1.0)
    # the backfill's worst error is the drift at its first pose, the farthest from the anchor
    assert c.backfill_max_error_m == pytest.approx(np.linalg.norm(drift[0]), abs=1e-6)
    # without the backfill column the first pose is the anchor, as before, and no backfill
    del scans["backfill"]
    c0 = sigma_consistency(est, gt, scans)
    assert np.isnan(c0.backfill_max_error_m)
    np.testing.assert_allclose(c0.errors_world_m, drift - drift[0], atol=1e-6)


@pytest.mark.parametrize("motion", ["rest", "line"])
def test_se3_on_a_degenerate_stretch_says_what_it_is(tmp_path, motion):
    """A ground truth at rest (a still start cut short) or on an exact line cannot fix an SE(3)
    alignment: the error says which, and offers the first-pose alignment, which works."""
    t = np.arange(20) * 0.1
    xyz = np.zeros((20, 3)) if motion == "rest" else np.c_[t, 0.0 * t, 0.0 * t]
    rot = Rotation.identity(20)
    gt = write_tum(tmp_path / "gt.tum", t, xyz, rot)
    est = write_tum(tmp_path / "est.tum", t, xyz + 0.001, rot)
    what = "does not move" if motion == "rest" else "lie on a line"
    with pytest.raises(InputError, match=f"{what}.*--align first"):
        align_pair(est, gt, "se3")
    assert ate(est, gt, align="first")["rmse_m"] < 1e-9
