"""`adalio info` / `adalio run` / `adalio config show` through the console entry point:
bad inputs give one line and exit 2; runs write parseable outputs, also when interrupted."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent / "io"))
import bagfactory as bf

from adalio import cli
from adalio.config import config_from_dict, load_config
from adalio.io.bagwrite import BagWriter
from adalio.io.writers import SCANS_CSV_COLUMNS, read_ply_points, read_tum
from adalio.pipeline import _no_pose_reason


def run_cli(monkeypatch, capsys, *argv: str) -> tuple[int, str, str]:
    monkeypatch.setattr(sys, "argv", ["adalio", *map(str, argv)])
    try:
        cli.main()
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, err: str, *fragments: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1, err
    for frag in fragments:
        assert frag in errors[0], errors[0]


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Path:
    return bf.write_static_rig(tmp_path_factory.mktemp("rig") / "rig.bag", duration_s=2.0,
                               columns=180)


# ------------------------------------------------------------------ bad inputs
@pytest.mark.parametrize("cmd", ["run", "info"])
def test_missing_path(monkeypatch, capsys, tmp_path, cmd):
    code, _, err = run_cli(monkeypatch, capsys, cmd, tmp_path / "nope.bag")
    assert_one_line_error(code, err, "nope.bag does not exist")


def test_not_a_bag(monkeypatch, capsys, tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    code, _, err = run_cli(monkeypatch, capsys, "run", tmp_path / "notes.txt")
    assert_one_line_error(code, err, "notes.txt is not a bag")
    (tmp_path / "fake.bag").write_text("hello, I am not a bag")
    code, _, err = run_cli(monkeypatch, capsys, "info", tmp_path / "fake.bag")
    assert_one_line_error(code, err, "fake.bag is not a ROS1 bag")


@pytest.mark.parametrize("fmt,name", [("ros1", "r.bag"), ("mcap_file", "r.mcap")])
def test_truncated_bag(monkeypatch, capsys, tmp_path, fmt, name):
    good = bf.write_static_rig(tmp_path / name, fmt, duration_s=0.5, columns=30)
    data = good.read_bytes()
    bad = tmp_path / f"cut_{name}"
    bad.write_bytes(data[: len(data) * 2 // 3])
    code, _, err = run_cli(monkeypatch, capsys, "run", bad, "--out", tmp_path / "o")
    assert_one_line_error(code, err, f"cannot read bag {bad}", "truncated or corrupted")


@pytest.mark.slow
def test_bag_corrupted_mid_run_keeps_rows(monkeypatch, capsys, tmp_path):
    folder = bf.write_static_rig(tmp_path / "db", "sqlite3", duration_s=2.0, columns=180)
    db = next(folder.glob("*.db3"))
    data = bytearray(db.read_bytes())
    page = int(len(data) * 0.6) // 4096 * 4096
    data[page:page + 4096] = b"\xff" * 4096
    db.write_bytes(bytes(data))
    out = tmp_path / "o"
    code, _, err = run_cli(monkeypatch, capsys, "run", folder, "--out", out, "--no-progress")
    assert_one_line_error(code, err, f"cannot read bag {folder} after", "rows written so far")
    poses = check_outputs(out)
    assert len(poses) >= 1
    assert len(read_ply_points(out / "map.ply")) > 0


def test_missing_and_ambiguous_topics(monkeypatch, capsys, tmp_path, rig):
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--lidar-topic", "/nope")
    assert_one_line_error(code, err, "topic /nope is not in", "/points", "--lidar-topic")
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--imu-topic", "/points")
    assert_one_line_error(code, err, "/points", "is sensor_msgs/msg/PointCloud2, not "
                          "sensor_msgs/Imu; sensor_msgs/Imu topics in the bag: /imu")
    # info lists the topics, and refuses a named one as run does
    code, out, err = run_cli(monkeypatch, capsys, "info", rig, "--imu-topic", "/points")
    assert_one_line_error(code, err, "/points", "is sensor_msgs/msg/PointCloud2, not "
                          "sensor_msgs/Imu")
    assert "/points" in out and "/imu" in out
    two = tmp_path / "two.bag"
    pts, t_rel, _ = bf.box_scan(columns=10)
    cols = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "t": t_rel}
    layout = [("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("t", 12, "u4")]
    with BagWriter(two) as w:
        w.add_cloud("/a", bf.T0_NS, cols, layout, 16)
        w.add_cloud("/b", bf.T0_NS, cols, layout, 16)
    code, _, err = run_cli(monkeypatch, capsys, "run", two)
    assert_one_line_error(code, err, "several sensor_msgs/PointCloud2 or Livox CustomMsg topics (/a, /b)",
                          "--lidar-topic")
    code, _, err = run_cli(monkeypatch, capsys, "run", two, "--lidar-topic", "/a")
    assert_one_line_error(code, err, "has no sensor_msgs/Imu topic")


def test_cloud_without_xyz(monkeypatch, capsys, tmp_path):
    layout = [("x", 0, "f4"), ("y", 4, "f4"), ("intensity", 8, "f4"), ("t", 12, "u4")]
    path = bf.write_static_rig(tmp_path / "noz.bag", duration_s=0.5, columns=30, layout=layout,
                               point_step=16)
    for cmd in ("run", "info"):
        out = ("--out", tmp_path / "o") if cmd == "run" else ()
        code, _, err = run_cli(monkeypatch, capsys, cmd, path, *out)
        assert_one_line_error(code, err, "PointCloud2 on /points has no z field",
                              "fields: x, y, intensity, t")


def test_imu_not_covering_scans(monkeypatch, capsys, tmp_path):
    path = bf.write_static_rig(tmp_path / "late_imu.bag", duration_s=0.5, columns=30,
                               imu_offset_s=100.0)
    code, _, err = run_cli(monkeypatch, capsys, "run", path, "--out", tmp_path / "o")
    assert_one_line_error(code, err, "IMU on /imu", "does not cover any scan on /points")


@pytest.mark.parametrize("n_back", [1, 3])
def test_non_monotonic_imu_stamps(monkeypatch, capsys, tmp_path, n_back):
    """IMU samples stamped 3 s back: one is a stamp glitch, dropped with a warning, and the run
    completes; three in a row are the clock going back, one error line (no glitch warning)."""
    path = tmp_path / "backwards.bag"
    pts, t_rel, _ = bf.box_scan(columns=30)
    cols = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "t": t_rel}
    layout = [("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("t", 12, "u4")]
    with BagWriter(path) as w:
        for k in range(1000):
            t = bf.T0_NS + k * 5_000_000
            stamp = t - 3_000_000_000 if 800 <= k < 800 + n_back else t
            w.add_imu("/imu", stamp, [0, 0, 0], [0, 0, 9.81], t_recv_ns=t)
            if k % 20 == 0 and k:
                w.add_cloud("/points", t - 100_000_000, cols, layout, 16, t_recv_ns=t + 1)
    code, _, err = run_cli(monkeypatch, capsys, "run", path, "--out", tmp_path / "o",
                           "--no-progress")
    if n_back == 1:
        assert code == 0, err
        assert "IMU sample on /imu stamped 1700000001.000000000 s, 2.800 s before samples " \
               "already used (a stamp glitch?)" in err
        assert "dropped 1 IMU samples on /imu stamped before samples already used" in err
    else:
        assert_one_line_error(code, err, "IMU stamps on /imu go backwards: 1700000001.00",
                              "over 3 samples in a row", "re-stamp")


def test_non_monotonic_scan_stamps(monkeypatch, capsys, tmp_path):
    path = tmp_path / "scans_back.bag"
    pts, t_rel, _ = bf.box_scan(columns=30)
    cols = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "t": t_rel}
    layout = [("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("t", 12, "u4")]
    with BagWriter(path) as w:
        for k in range(600):
            t = bf.T0_NS + k * 5_000_000
            w.add_imu("/imu", t, [0, 0, 0], [0, 0, 9.81])
            if k % 20 == 0 and k:
                stamp = t - 100_000_000 - (2_500_000_000 if k == 400 else 0)
                w.add_cloud("/points", stamp, cols, layout, 16, t_recv_ns=t + 1)
    code, _, err = run_cli(monkeypatch, capsys, "run", path, "--out", tmp_path / "o",
                           "--no-progress")
    assert_one_line_error(code, err, "scan end times on /points go backwards",
                          "sensor.point_time_*")
    assert (tmp_path / "o" / "trajectory.tum").is_file()


@pytest.mark.parametrize("args,frag", [
    (["--extrinsic", "0 0 0 0.5 0.5 0.5 0.1"], "is not a rotation"),
    (["--extrinsic", "0 0 0 1 0"], "must be 7 numbers"),
    (["--mode", "fast"], "adaptive.mode must be one of"),
])
def test_bad_flags(monkeypatch, capsys, rig, args, frag):
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, *args)
    assert_one_line_error(code, err, frag)


def test_run_set_overrides_the_preset_and_the_config_file(monkeypatch, capsys, tmp_path, rig):
    """``run --set KEY=VALUE`` (as ``compare`` and ``batch`` take it) over the preset and
    ``--config``; the run's config.yaml has the values. A malformed item, an unknown key and a
    flag that says otherwise are one error line each."""
    f = tmp_path / "c.yaml"
    f.write_text("imu:\n  accel_bias_cov: 2.0e-5\n")
    out = tmp_path / "set"
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--config", f, "--out", out,
                           "--no-progress", "--max-scans", "8", "--set", "imu.accel_bias_cov=3e-5",
                           "--set", "map.map_leaf_m=0.3", "--set", "adaptive.mode=fixed",
                           "--mode", "fixed")
    assert code == 0, err
    written = load_config(config_file=out / "config.yaml")
    assert written.imu.accel_bias_cov == 3e-5 and written.map.map_leaf_m == 0.3
    assert written.adaptive.mode == "fixed"
    for args, frag in ((["--set", "imu.accel_bias_cov"], "--set expects KEY=VALUE"),
                       (["--set", "imu.acel_bias_cov=1"], "imu.accel_bias_cov"),
                       (["--set", "adaptive.mode=fixed", "--mode", "adaptive"],
                        "--mode adaptive and --set adaptive.mode=fixed disagree"),
                       (["--set", "imu.accel_bias_cov=-1"], "imu.accel_bias_cov")):
        code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--out", tmp_path / "x", *args)
        assert_one_line_error(code, err, frag)
        assert not (tmp_path / "x").exists()


def test_config_extrinsic_not_rotation(monkeypatch, capsys, tmp_path, rig):
    f = tmp_path / "c.yaml"
    f.write_text("sensor:\n  T_imu_lidar: [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]\n")
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--config", f)
    assert_one_line_error(code, err, "sensor.T_imu_lidar is not a rigid transform")


# ------------------------------------------------------------------ info / config
def test_info_reports_topics_and_time_format(monkeypatch, capsys, rig):
    code, out, err = run_cli(monkeypatch, capsys, "info", rig)
    assert code == 0, err
    assert "would use: lidar /points, imu /imu" in out
    assert "per-point time: 't' in ns, relative (detected)" in out
    n = 180 * 16
    assert f"min {n}, median {n}, max {n}" in out
    assert "accelerometer in m/s^2" in out
    assert "T_imu_lidar from identity (fallback): t = [0.0, 0.0, 0.0] m" in out
    assert "warning: no extrinsic in the preset, the config or /tf_static" in err


def test_info_samples_each_message_once(monkeypatch, capsys, rig):
    """``--sample`` more than the bag's clouds reports as many as it has (not the same cloud
    over again), the IMU's sampled messages are distinct too, and ``--sample 0`` is refused."""
    from adalio.io.bag import Bag

    with Bag(rig) as b:
        counts = {t.name: t.count for t in b.topics()}
    code, out, err = run_cli(monkeypatch, capsys, "info", rig, "--sample", 1000)
    assert code == 0, err
    assert f"points per scan ({counts['/points']} sampled)" in out
    assert f"over {counts['/imu']} sampled messages" in out
    code, _, err = run_cli(monkeypatch, capsys, "info", rig, "--sample", 0)
    assert_one_line_error(code, err, "--sample must be >= 1 (got 0)")


@pytest.mark.parametrize("ghosts", [0.0, 0.1])
def test_info_reports_the_stray_returns_of_the_sampled_clouds(monkeypatch, capsys, ghosts):
    """``adalio info`` gives the sampled clouds' share of stray returns: a clean simulated walk
    holds a fraction of a percent, the same walk with ghosts on a tenth of its returns about
    what the simulator put there (measured: 0.1 and 8.2 % on the 43 s hall at 512 columns),
    and the share above which a run drops them."""
    import re

    from adalio.sim import cached_sequence

    sim = cached_sequence("hall", seed=0, duration_s=3.0, columns=256, ghosts=ghosts)
    code, out, err = run_cli(monkeypatch, capsys, "info", sim.bag_path, "--config",
                             sim.config_path)
    assert code == 0, err
    m = re.search(r"stray returns \(5 sampled\): mean ([0-9.]+) %, largest ([0-9.]+) % of a "
                  r"scan's points; a run drops them in a scan above 2 %", out)
    assert m, out
    mean, largest = float(m[1]), float(m[2])
    assert mean <= largest
    assert (mean < 1.0) if not ghosts else (0.6 * 100 * ghosts < mean <= 100 * ghosts)


def test_info_rate_is_each_topics_own(monkeypatch, capsys, tmp_path):
    """A topic's rate is its count over its own span: an IMU recorded 3 s before the LiDAR
    starts reads 200 Hz and the LiDAR 10 Hz (over the bag's 5 s they read 80 and 3.6 Hz)."""
    bag = bf.write_static_rig(tmp_path / "late_lidar.bag", duration_s=2.0, imu_rate_hz=200.0,
                              imu_offset_s=-3.0, columns=90)
    code, out, err = run_cli(monkeypatch, capsys, "info", bag)
    assert code == 0, err
    rows = {ln.split()[1]: ln.split() for ln in out.splitlines() if ln.split()[1:2] in
            (["/imu"], ["/points"])}
    assert rows["/imu"][-2] == "200.0" and rows["/points"][-2] == "10.0", out


def test_config_show_roundtrips(monkeypatch, capsys):
    code, out, _ = run_cli(monkeypatch, capsys, "config", "show", "hilti2022")
    assert code == 0
    cfg = config_from_dict(yaml.safe_load(out))
    assert cfg.to_dict() == load_config("hilti2022").to_dict()
    code, _, err = run_cli(monkeypatch, capsys, "config", "show", "hilt2022")
    assert_one_line_error(code, err, "unknown preset 'hilt2022'", "hilti2022")
    code, _, err = run_cli(monkeypatch, capsys, "config", "show", "my_rig.yaml")
    assert_one_line_error(code, err, "'my_rig.yaml' is a file, not a preset name", "--config")


# ------------------------------------------------------------------ runs
def check_outputs(out_dir: Path, map_name: str = "map.ply") -> np.ndarray:
    t_ns, poses = read_tum(out_dir / "trajectory.tum")
    lines = (out_dir / "scans.csv").read_text().splitlines()
    assert lines[0].split(",") == list(SCANS_CSV_COLUMNS)
    assert len(lines) - 1 == len(t_ns)
    csv_t = [ln.split(",")[0] for ln in lines[1:]]
    tum_t = [ln.split()[0] for ln in (out_dir / "trajectory.tum").read_text().splitlines()]
    assert csv_t == tum_t
    assert all(len(s.split(".")[1]) == 9 for s in tum_t)
    assert np.all(np.diff(t_ns) > 0)
    np.testing.assert_allclose(np.linalg.norm(poses[:, 3:], axis=1), 1.0, atol=1e-6)
    config_from_dict(yaml.safe_load((out_dir / "config.yaml").read_text()))
    assert (out_dir / map_name).is_file()
    return poses


@pytest.mark.slow
def test_run_static_rig_stays_at_origin(monkeypatch, capsys, tmp_path, rig):
    out = tmp_path / "run"
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--out", out, "--no-progress",
                           "--profile")
    assert code == 0, err
    assert "per-stage time" in err
    poses = check_outputs(out)
    assert len(poses) >= 10
    assert np.linalg.norm(poses[:, :3], axis=1).max() < 0.01
    pts = read_ply_points(out / "map.ply")
    assert len(pts) > 100
    lo, hi = bf.BOX_LO, bf.BOX_HI
    # every map point lies on a wall of the box room
    d_wall = np.minimum(np.abs(pts - lo), np.abs(pts - hi)).min(axis=1)
    assert np.percentile(d_wall, 99) < 0.05
    header = (out / "map.ply").read_bytes()[:200].decode("ascii", "replace")
    assert header.startswith("ply\nformat binary_little_endian 1.0\n")


@pytest.mark.slow
def test_run_pcd_map_and_empty_scans_counted(monkeypatch, capsys, tmp_path):
    path = bf.write_static_rig(tmp_path / "gaps.bag", duration_s=1.5, columns=120,
                               empty_scans=(6, 8))
    out = tmp_path / "run"
    code, _, err = run_cli(monkeypatch, capsys, "run", path, "--out", out, "--no-progress",
                           "--map-format", "pcd")
    assert code == 0, err
    assert "warning: empty scan on /points" in err
    assert "skipped 2 empty scans" in err
    check_outputs(out, "map.pcd")
    head = (out / "map.pcd").read_bytes()[:300].decode("ascii", "replace")
    assert "FIELDS x y z" in head and "DATA binary" in head


@pytest.mark.slow
def test_ctrl_c_leaves_valid_partial_outputs(monkeypatch, capsys, tmp_path, rig):
    from adalio import pipeline

    class Interrupting(pipeline.Sequencer):
        def __iter__(self):
            n = 0
            for item in super().__iter__():
                if not isinstance(item, pipeline.ImuBatch):
                    n += 1
                    if n > 10:
                        raise KeyboardInterrupt
                yield item

    monkeypatch.setattr(pipeline, "Sequencer", Interrupting)
    out = tmp_path / "run"
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--out", out, "--no-progress")
    assert code == 130, err
    assert "interrupted" in err
    poses = check_outputs(out)
    assert 1 <= len(poses) <= 10
    assert len(read_ply_points(out / "map.ply")) > 0


@pytest.mark.slow
def test_run_bag_api_max_scans_and_hook(tmp_path, rig):
    from adalio.pipeline import run_bag

    seen = []
    res = run_bag(rig, load_config(), tmp_path / "api", progress=False, max_scans=9,
                  on_scan=seen.append)
    assert seen == list(range(1, 10)) and res.n_scans_in == 9
    assert res.n_scans == len(read_tum(res.trajectory_path)[0]) and not res.interrupted
    assert res.map_path.name == "map.ply" and res.config_path.is_file()


@pytest.mark.slow
def test_run_extrinsic_from_tf_static_or_flag(monkeypatch, capsys, tmp_path):
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xyz", [0.1, -0.2, 0.3])
    T = np.eye(4)
    T[:3, :3] = R.as_matrix()
    T[:3, 3] = [0.05, -0.02, 0.1]
    path = bf.write_static_rig(tmp_path / "tf.bag", duration_s=1.0, columns=120,
                               tf_static=[("imu", "lidar", T)])
    out = tmp_path / "a"
    code, _, err = run_cli(monkeypatch, capsys, "run", path, "--out", out, "--no-progress",
                           "--max-scans", "8")
    assert code == 0, err
    assert "extrinsic from tf_static (imu <- lidar)" in err
    used = yaml.safe_load((out / "config.yaml").read_text())["sensor"]["T_imu_lidar"]
    np.testing.assert_allclose(used, T, atol=1e-9)
    q = R.as_quat()
    flag = f"1 2 3 {q[0]} {q[1]} {q[2]} {q[3]}"
    code, _, err = run_cli(monkeypatch, capsys, "run", path, "--out", tmp_path / "b",
                           "--no-progress", "--max-scans", "8", "--extrinsic", flag)
    assert code == 0, err
    used = yaml.safe_load((tmp_path / "b" / "config.yaml").read_text())["sensor"]["T_imu_lidar"]
    np.testing.assert_allclose(np.asarray(used)[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(np.asarray(used)[:3, :3], R.as_matrix(), atol=1e-9)


def test_run_without_a_pose_fails_and_keeps_outputs(monkeypatch, capsys, tmp_path, rig):
    """Three scans end before the 0.5 s still window and the 1 s moving-start timeout: no pose
    is an error naming why, and the outputs written so far stay."""
    out = tmp_path / "none"
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--out", out, "--no-progress",
                           "--max-scans", "3")
    assert_one_line_error(code, err, "no pose from 3 scans", "never initialized",
                          "imu.init_timeout_s", str(out))
    assert check_outputs(out).shape == (0, 7)
    load_config(config_file=out / "config.yaml")


def test_run_writes_the_measured_imu_calibration(monkeypatch, capsys, tmp_path, rig):
    out = tmp_path / "cal"
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--out", out, "--no-progress")
    assert code == 0, err
    assert "initialization: static start" in err
    measured = yaml.safe_load((out / "config.yaml").read_text())["measured"]
    assert measured["init_method"] == "static" and measured["filter_noise"] == "config"
    # the rig's IMU is noise-free, at rest with gravity on +z and zero gyro
    assert measured["gyro_noise_rad_s_sqrt_hz"] == 0.0
    np.testing.assert_allclose(measured["gravity_imu_m_s2"], [0, 0, -9.81], atol=1e-6)
    # a still start's world is the IMU frame: the same gravity, which the report levels by
    np.testing.assert_allclose(measured["gravity_world_m_s2"], [0, 0, -9.81], atol=1e-6)
    np.testing.assert_allclose(measured["gyro_bias_rad_s"], 0.0, atol=1e-12)
    load_config(config_file=out / "config.yaml")  # the measured block reads back


@pytest.mark.slow
def test_real_sigint_in_subprocess(tmp_path):
    import os
    import signal
    import subprocess
    import time

    path = bf.write_static_rig(tmp_path / "long.bag", duration_s=12.0, columns=360)
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "adalio.cli", "run", str(path), "--out",
                             str(out), "--no-progress"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    tum = out / "trajectory.tum"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if tum.is_file() and len(tum.read_text().splitlines()) >= 3:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "run finished before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err
    poses = check_outputs(out)
    assert 3 <= len(poses) < 110
    assert len(read_ply_points(out / "map.ply")) > 0


def test_run_writes_sigma_columns_and_names_risky_stretches(monkeypatch, capsys, tmp_path, rig):
    from adalio.eval.files import read_scans_csv

    out = tmp_path / "sig"
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--out", out, "--no-progress")
    assert code == 0, err
    assert "at risk" not in err  # mm-level sigmas stay under the 0.1 m default
    scans = read_scans_csv(out / "scans.csv")
    cols = ["sigma_x_m", "sigma_y_m", "sigma_z_m", "sigma_roll_deg", "sigma_pitch_deg",
            "sigma_yaw_deg"]
    sig = np.column_stack([scans[c] for c in cols])
    # the first scan of the filter (after the backfilled ones read before the IMU window was
    # full) is its first map: it defines the world
    anchor = int(np.argmax(np.asarray(scans["backfill"]) == 0))
    assert np.all(sig[anchor] == 0.0)
    rest = np.delete(sig, anchor, axis=0)
    assert np.all(np.isfinite(rest)) and np.all(rest > 0.0)
    assert np.all(rest[:, :3] < 0.1)
    # a threshold below every sigma names the whole run after the first scan
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--out", tmp_path / "sig2",
                           "--no-progress", "--sigma-warn-m", "1e-9")
    assert code == 0, err
    n = len(scans["t_s"])
    assert f"in {n - 1}/{n} scans" in err and "at risk" in err
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--out", tmp_path / "sig3",
                           "--no-progress", "--sigma-warn-m", "0")
    assert code != 0 and "--sigma-warn-m" in err


def test_sigma_warn_default_is_the_pipeline_default():
    import inspect

    from adalio.io.cli import run
    from adalio.pipeline import DEFAULT_SIGMA_WARN_M

    assert inspect.signature(run).parameters["sigma_warn_m"].default == DEFAULT_SIGMA_WARN_M


@pytest.mark.parametrize(("method", "refused", "without", "backfilled", "flagged"), [
    ("moving", 272, 282, 0, True),     # refused fits left 282 of 540 scans without a pose
    ("moving", 272, 282, 230, False),  # the backfill reached all but 52 (< 10 %)
    ("moving", 272, 282, 200, True),   # 82 left (15 %)
    ("moving", 3, 40, 0, False),       # 7 % of the scans: under the 10 % line
    ("static", 0, 282, 0, False),      # a still window's scans rest at the first pose
])
def test_summary_flags_a_long_moving_start_wait(tmp_path, summary_text, method, refused, without,
                                                backfilled, flagged):
    """The run summary names the scans a refused moving start left without a pose (those the
    backfill did not reach either), with the count, the wait and the last refusal, once they
    pass 10 % of the scans read."""
    from adalio.pipeline import RunResult
    from adalio.types import InitReport

    rep = InitReport(method=method, t_ns=28_300_000_000, gyro_bias_rad_s=np.zeros(3),
                     gravity_imu_m_s2=np.array([0.0, 0.0, -9.81]), window_s=1.0,
                     wait_s=28.3, scans_without_pose=without, refused_fits=refused,
                     last_refusal="the motion fit over 11 scans leaves 3.1 cm RMS",
                     backfilled=backfilled)
    res = RunResult(out_dir=tmp_path, trajectory_path=tmp_path, scans_csv_path=tmp_path,
                    map_path=tmp_path, config_path=tmp_path, n_scans=540 - without + backfilled,
                    n_degenerate=0, wall_s=1.0, ms_per_scan_median=1.0, stage_ms={},
                    interrupted=False, n_scans_in=540, init_report=rep)
    text = summary_text(res)
    why = (f"; {refused} moving-start fits refused, the last because the motion fit over 11 "
           "scans leaves 3.1 cm RMS" if refused else "")
    assert (f"first filter pose 28.3 s after the first scan ({without} scans read before it, "
            f"{backfilled} of them given a pose by the backfill{why})") in text
    line = (f"at risk: {without - backfilled}/540 scans have no pose: the filter started 28.3 s "
            f"after the first scan ({refused} moving-start")
    assert (line in text) is flagged
    assert text.count("3.1 cm RMS") == (refused > 0) + flagged  # the wait's reason, said once
    # on the initialization line (since session 94) and again on the at-risk line


@pytest.mark.parametrize(("stray", "dropped", "said"), [
    (2_000, False, ""),              # 0.2 %, as on clean simulated walks: nothing said
    (9_900, False, ""),              # 0.99 %: under the note's 1 % line
    (14_000, False, "note"),         # 1.4 % kept (ghosts on 2 % of the returns): noted
    (140_000, False, "note"),        # 14 % kept (stray_drop_share raised): noted
    (140_000, True, "dropped"),      # the option on: how many it dropped, whatever the share
    (2_000, True, "dropped"),
    (0, True, ""),                   # no ring field: none counted, none dropped
])
def test_summary_says_what_the_stray_returns_were(tmp_path, summary_text, stray, dropped, said):
    """With preprocess.drop_stray_returns the summary counts the stray returns dropped; without
    it, it notes those kept, with the setting that drops them, where they reach 1 % of the
    points (half the default stray_drop_share)."""
    from adalio.config import PreprocessConfig
    from adalio.pipeline import STRAY_NOTE_SHARE, RunResult

    assert STRAY_NOTE_SHARE == 0.01 == PreprocessConfig().stray_drop_share / 2
    res = RunResult(out_dir=tmp_path, trajectory_path=tmp_path, scans_csv_path=tmp_path,
                    map_path=tmp_path, config_path=tmp_path, n_scans=100, n_degenerate=0,
                    wall_s=1.0, ms_per_scan_median=1.0, stage_ms={}, interrupted=False,
                    n_scans_in=100, stray_points=(stray, 1_000_000), stray_dropped=dropped,
                    stray_drops=(stray, 100 if stray else 0, 0) if dropped else (0, 0, stray))
    text = summary_text(res)
    share = f"{stray} of 1000000 points"
    assert (f"stray returns (preprocess.drop_stray_returns): {share}" in text) is (
        said == "dropped")
    assert (f"note: {share} ({100 * stray / 1e6:.1f} %) are stray returns" in text) is (
        said == "note")
    assert ("--set preprocess.stray_drop_share=0.01" in text) is (said == "note")


@pytest.mark.parametrize(("dropped", "scans", "share", "note"), [
    (0, 0, 0.02, False),          # no sweep over its share: nothing said (0.5 % kept)
    (180_000, 40, 0.02, False),   # dust in 40 sweeps: dropped there, 0.5 % kept
    (120_000, 30, 0.3, True),     # the share raised: 11 % kept, noted
])
def test_summary_says_where_sweeps_dropped_their_stray_returns(tmp_path, summary_text, dropped,
                                                              scans, share, note):
    """With preprocess.drop_stray_returns off, the summary names the sweeps that dropped their
    stray returns for being more than preprocess.stray_drop_share of their points, with the
    count and where, and notes only the stray returns kept."""
    from adalio.pipeline import RunResult

    res = RunResult(out_dir=tmp_path, trajectory_path=tmp_path, scans_csv_path=tmp_path,
                    map_path=tmp_path, config_path=tmp_path, n_scans=100, n_degenerate=0,
                    wall_s=1.0, ms_per_scan_median=1.0, stage_ms={}, interrupted=False,
                    n_scans_in=100, stray_points=(5_000 + dropped + 105_000 * note, 1_000_000),
                    stray_drops=(dropped, scans, 5_000 + 105_000 * note), stray_drop_share=share,
                    stray_dropped_ranges_s=[(2.0, 5.9)] if scans else [])
    text = summary_text(res)
    line = (f"stray returns (preprocess.stray_drop_share): {scans}/100 scans had more than "
            f"{100 * share:g} % (dust or rain in front of surfaces, ghosts behind them) and "
            f"dropped {dropped} points ({100 * dropped / 1e6:.1f} % of those read)")
    assert (line in text) is bool(dropped)
    assert ("at 2.0-5.9 s" in text) is bool(dropped)
    assert ("note: 110000 of 1000000 points (11.0 %) are stray returns kept" in text) is note
    assert "drop_stray_returns):" not in text


@pytest.mark.parametrize("n_blind", [0, 37])
def test_summary_names_the_height_blind_stretches(tmp_path, summary_text, n_blind):
    """The run summary names the scans whose height the sigmas leave to the IMU (scans.csv
    height_blind), with their count and time ranges, and says nothing when there are none."""
    from adalio.pipeline import RunResult

    res = RunResult(out_dir=tmp_path, trajectory_path=tmp_path, scans_csv_path=tmp_path,
                    map_path=tmp_path, config_path=tmp_path, n_scans=400, n_degenerate=0,
                    wall_s=1.0, ms_per_scan_median=1.0, stage_ms={}, interrupted=False,
                    n_scans_in=400, n_height_blind=n_blind,
                    height_blind_ranges_s=[(3.1, 6.5)] if n_blind else [])
    text = summary_text(res)
    assert ("height left to the IMU" in text) is bool(n_blind)
    if n_blind:
        assert "37/400 scans at 3.1-6.5 s" in text


@pytest.mark.slow
def test_compare_with_a_gt_no_mode_aligns_with_is_an_error(monkeypatch, capsys, tmp_path):
    """`adalio compare --gt` with the GT of another recording (stamps a day later): the mode runs
    and is kept (trajectory, table), but a comparison with no usable row is bad input, one
    'error:' line naming the GT file and exit 2, not a table of aborted rows and exit 0. (With
    the recording's own GT the command exits 0: tests/eval/test_eval_compare.py,
    test_compare_cli_on_simulated_run.)"""
    from adalio.eval.demo import DEMO_FORMAT, DEMO_SCENE, SHORT_COLUMNS, SHORT_DURATION_S
    from adalio.sim import cached_sequence

    sim = cached_sequence(DEMO_SCENE, seed=0, duration_s=SHORT_DURATION_S,
                          columns=SHORT_COLUMNS, fmt=DEMO_FORMAT)
    rows = np.loadtxt(sim.gt_path)
    rows[:, 0] += 1e5
    other = tmp_path / "other_day.tum"
    np.savetxt(other, rows, fmt="%.9f")
    code, _, err = run_cli(monkeypatch, capsys, "compare", sim.bag_path, "--modes", "fixed",
                           "--config", sim.config_path, "--max-scans", "20", "--gt", other,
                           "--out", tmp_path / "a")
    assert_one_line_error(code, err, "--gt", "other_day.tum", "could be aligned")
    assert (tmp_path / "a" / "compare.md").is_file()
    assert (tmp_path / "a" / "fixed" / "trajectory.tum").is_file()


def test_demo_without_a_seed_is_an_error(monkeypatch, capsys, tmp_path):
    """`adalio demo --seeds 0` compares on nothing: one 'error:' line naming the flag, exit 2,
    and nothing simulated."""
    code, _, err = run_cli(monkeypatch, capsys, "demo", "--seeds", "0", "--out", tmp_path / "d")
    assert_one_line_error(code, err, "--seeds must be >= 1 (got 0)")
    assert not (tmp_path / "d" / "seed0").exists()


def test_compare_in_which_no_mode_poses_is_an_error(monkeypatch, capsys, tmp_path):
    """`adalio compare` whose every mode produces no pose (3 scans: the estimator never
    initializes) is one 'error:' line saying so, exit 2, as `run` would; the table is kept, and
    its empty overlay plot warns of nothing (matplotlib's 'no artists' legend warning)."""
    import warnings

    from adalio.eval.demo import DEMO_FORMAT, DEMO_SCENE, SHORT_COLUMNS, SHORT_DURATION_S
    from adalio.sim import cached_sequence

    sim = cached_sequence(DEMO_SCENE, seed=0, duration_s=SHORT_DURATION_S,
                          columns=SHORT_COLUMNS, fmt=DEMO_FORMAT)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, _, err = run_cli(monkeypatch, capsys, "compare", sim.bag_path, "--modes",
                               "fixed,adaptive", "--config", sim.config_path, "--max-scans",
                               "3", "--out", tmp_path / "c")
    assert_one_line_error(code, err, "no mode produced a usable trajectory", "no pose from 3")
    assert not [w for w in caught if "legend" in str(w.message)], [str(w.message) for w in caught]
    assert (tmp_path / "c" / "compare.md").is_file()


def test_no_pose_reasons_name_the_start_beyond_the_bag_and_late_clouds(monkeypatch, capsys,
                                                                       tmp_path, rig):
    """A run with no pose says why when it is neither the topic nor the initialization:
    ``--start-s`` past the bag's end (a run), or clouds whose receive times lag the IMU's by
    more than the sequencer's IMU window, each skipped (the reason's wording)."""
    code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--out", tmp_path / "a",
                           "--start-s", "100")
    assert_one_line_error(code, err, "--start-s 100 is at or beyond the end of the bag",
                          "s long")
    never = SimpleNamespace(initialized=False, init_failure=lambda: "no still window",
                            rest_refuted=None)
    for n_in in (0, 20):
        text = _no_pose_reason(never, n_in, "/points", "/imu", tmp_path, n_late=100)
        assert "100 scans of /points arrived more than 2 s after their IMU samples" in text


def test_simulate_prints_a_run_command_a_shell_can_take(monkeypatch, capsys, tmp_path):
    """The ``run:`` line simulate prints is a command a shell splits into the bag and the config
    it wrote, also where the output folder has a space in its name."""
    import shlex

    out = tmp_path / "my sims" / "hall 1"
    code, stdout, err = run_cli(monkeypatch, capsys, "simulate", "--scene", "hall", "--duration",
                                "1", "--columns", "64", "--out", out)
    assert code == 0, err
    line = next(ln for ln in stdout.splitlines() if ln.startswith("run: "))
    argv = shlex.split(line[len("run: "):])
    assert argv[:2] == ["adalio", "run"] and argv[3] == "--config"
    assert Path(argv[2]).parent == out and Path(argv[2]).exists()
    assert Path(argv[4]) == out / "config.yaml" and Path(argv[4]).exists()


def test_run_with_a_late_gt_prints_the_reports_warning(monkeypatch, capsys, tmp_path):
    """`adalio run --gt` with a ground truth that starts 1 s after the run's first scan: the
    report's warning (its uncertainty figures are aligned on a later scan, so they flatter the
    sigmas) reaches the terminal as a `warning:` line, as `adalio report` prints it."""
    from adalio.eval.demo import DEMO_FORMAT, DEMO_SCENE, SHORT_COLUMNS, SHORT_DURATION_S
    from adalio.sim import cached_sequence

    sim = cached_sequence(DEMO_SCENE, seed=0, duration_s=SHORT_DURATION_S,
                          columns=SHORT_COLUMNS, fmt=DEMO_FORMAT)
    rows = np.loadtxt(sim.gt_path)
    late = tmp_path / "late.tum"
    np.savetxt(late, rows[rows[:, 0] >= rows[0, 0] + 1.0], fmt="%.9f")
    code, _, err = run_cli(monkeypatch, capsys, "run", sim.bag_path, "--config",
                           sim.config_path, "--max-scans", "30", "--gt", late, "--out",
                           tmp_path / "r")
    assert code == 0, err
    warned = [ln for ln in err.splitlines() if ln.startswith("warning: the ground truth starts "
                                                             "after the filter's first scan")]
    assert len(warned) == 1, err


def test_rrd_over_an_input_file_is_refused_and_the_file_kept(monkeypatch, capsys, tmp_path):
    """`--rrd` naming the bag (or the config, or any file not ending in .rrd) is one error line
    before anything is written: the recording used to be written over it, and the bag was
    gone."""
    rig = bf.write_static_rig(tmp_path / "rig.bag", duration_s=0.5, columns=30)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("preset: hilti2022\n")
    before = {f: f.read_bytes() for f in (rig, cfg)}
    for target in (rig, cfg, tmp_path / "new_recording"):
        code, _, err = run_cli(monkeypatch, capsys, "run", rig, "--config", cfg, "--rrd", target,
                               "--out", tmp_path / "o")
        assert_one_line_error(code, err, f"--rrd {target}", "give a name ending in .rrd")
    assert {f: f.read_bytes() for f in before} == before
    assert not (tmp_path / "new_recording").exists() and not (tmp_path / "o").exists()


def test_a_check_unsettled_far_from_the_setting_is_a_warning():
    """A sensor check that closed unsettled with an estimate 5 or more standard deviations from
    the configured value (a rotation 10 deg off gave 6.69 +- 0.36 deg, a gyro read in the wrong
    unit -97 % +- 1.2 %) gives a warning naming the setting; nearer ones, estimates the check
    does not call significant, estimates too vague for the check (a robot's one-axis turns: a
    lever arm of 5 m +- 78 cm) and checks without an estimate give none."""
    from adalio.io.cli import _far_unsettled

    def res(**checks):
        return SimpleNamespace(**{k: SimpleNamespace(estimate=v) for k, v in checks.items()})

    rot = SimpleNamespace(angle_rad=np.radians(6.69), sigma_rad=np.radians(0.36),
                          significant=True)
    texts = _far_unsettled(res(extrinsic_rotation_unsettled=rot))
    assert len(texts) == 1 and texts[0].startswith(
        "the LiDAR-IMU rotation check's estimate, 6.69 deg, is 19 standard deviations")
    assert "check sensor.T_imu_lidar's rotation" in texts[0]
    scale = SimpleNamespace(largest=0.97, sigma=0.012, significant=True, text=lambda: "-97 %")
    assert "check sensor.gyro_unit" in _far_unsettled(res(gyro_scale_unsettled=scale))[0]
    near = SimpleNamespace(offset_s=0.010, sigma_s=0.0025, significant=True)
    weak = SimpleNamespace(offset_s=0.010, sigma_s=0.0015, significant=False)
    assert _far_unsettled(res(time_offset_unsettled=near)) == []
    assert _far_unsettled(res(time_offset_unsettled=weak)) == []
    assert _far_unsettled(res(time_offset_unsettled=None)) == []
    vague = SimpleNamespace(length_m=5.23, sigma_m=0.783, significant=True, text=lambda: "5 m")
    assert _far_unsettled(res(extrinsic_translation_unsettled=vague)) == []  # a robot's
    assert _far_unsettled(SimpleNamespace()) == []


def test_run_names_where_its_extrinsic_came_from(monkeypatch, capsys, tmp_path):
    """The summary names the extrinsic's origin (it said 'config' for all of them), and a run on
    the identity fallback (a generic preset, no config, no --extrinsic, no /tf_static) warns as
    `adalio info` does."""
    rig = bf.write_static_rig(tmp_path / "rig.bag", duration_s=1.5, columns=60)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("sensor:\n  T_imu_lidar: [[1,0,0,0.1],[0,1,0,0],[0,0,1,0],[0,0,0,1]]\n")
    for args, origin in (((), "identity (fallback)"), (("--config", cfg), f"config file {cfg}"),
                         (("--extrinsic", "0 0 0.1 0 0 0 1"), "--extrinsic")):
        code, _, err = run_cli(monkeypatch, capsys, "run", rig, *args, "--out", tmp_path / "o",
                               "--no-progress")
        assert code == 0, err
        assert f"extrinsic from {origin};" in err
        warned = "warning: no extrinsic in the preset, the config, --extrinsic or /tf_static" in err
        assert warned == (origin == "identity (fallback)")


@pytest.mark.parametrize(("max_range_m", "says"), [
    (1.2, ("every scan was empty after preprocessing (no point within preprocess.blind_m .. "
           "max_range_m)")),
    (2.0, ("Check the scans of /hesai/pandar: too few of them keep the 50 points a moving "
           "start needs")),
])
def test_no_pose_from_sparse_scans_points_at_the_scans_not_the_imu(monkeypatch, capsys,
                                                                    tmp_path, max_range_m, says):
    """A hall walk cut 3 s in (a moving start) whose scans lose their points to the config's
    range limit: every point (1.2 m), or all but too few to register (2.0 m). The no-pose error
    names the scans and the settings; it said to check the IMU's rate, units and stamps until
    session 76 (session 75's probes)."""
    import yaml

    from adalio import simulate

    sim = simulate("hall", tmp_path / "sim", duration_s=6, columns=256)
    cfg = yaml.safe_load(sim.config_path.read_text())
    cfg.setdefault("preprocess", {})["max_range_m"] = max_range_m
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(cfg))
    code, _, err = run_cli(monkeypatch, capsys, "run", sim.bag_path, "--config",
                           tmp_path / "c.yaml", "--start-s", "3", "--out", tmp_path / "r")
    assert_one_line_error(code, err, "no pose from 30 scans", says)
    assert "Check /alphasense/imu" not in err


def test_the_summary_and_the_batch_table_say_a_gross_rotation_before_the_fine_one():
    """After a gross rotation error (session 80), the summary's `LiDAR-IMU rotation:` line and
    the batch table's checks cell name it first, then what the fine check found after it."""
    from adalio.batch import checks_text
    from adalio.io.cli import _rotation_text

    gross = SimpleNamespace(text=lambda: "87.6 deg (+-0.8)", span_s=9.9,
                            angle_rad=np.radians(87.6))
    fine = SimpleNamespace(angle_deg=2.97, found_rad=np.radians([2.97, 0.0, 0.0]), n_scans=120,
                           passes=[0, 1, 2], detected_rad=np.radians([2.1, 0.0, 0.0]))
    left = SimpleNamespace(angle_rad=np.radians(0.04), sigma_rad=np.radians(0.05), span_s=19.0,
                           significant=False)
    res = SimpleNamespace(extrinsic_rotation_gross_found=gross, extrinsic_rotation_found=fine,
                          extrinsic_rotation=left, extrinsic_rotation_unsettled=None)
    text = _rotation_text(res)
    assert text.startswith("sensor.T_imu_lidar turned by 87.6 deg (+-0.8), a gross error found "
                           "by a LiDAR registration without the gyro over the first 10 s, the "
                           "run restarted with it; then sensor.T_imu_lidar turned by 2.97 deg"), \
        text
    assert text.endswith("0.04 deg (+-0.05) left against the LiDAR-registered rotation over 19 s")
    assert "rotation 87.6 deg gross, then 2.97 deg found" in checks_text(res)
    res.extrinsic_rotation_found = None  # the gross correction left nothing the passes found
    assert _rotation_text(res).startswith("sensor.T_imu_lidar turned by 87.6 deg")
    assert "rotation 87.6 deg gross, then 0.04 deg" in checks_text(res)
