"""The Livox Mid-360-like LiDAR (``simulate(lidar="mid360")``): Livox ``CustomMsg`` frames whose
points, placed by the ground truth at their own times, lie on the scene; every point at its own
time in firing order over -7..+52 deg; frames that never repeat and fill the view together; its
IMU's accelerometer in g; and adalio's reader taking the sequence with its own config."""

from __future__ import annotations

import hashlib
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from livoxsim import (
    PERIOD_NS,
    az_el_deg,
    custommsg_frames,
    frame_xyz,
    messages,
    noise_free_walk,
)
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp

from adalio.config import load_config
from adalio.io.bag import Bag
from adalio.io.sequencer import Sequencer
from adalio.sim import simulate
from adalio.sim.generate import START_NS, T_IMU_LIDAR_HILTI, mesh_distance_m
from adalio.sim.lidar import RayCaster
from adalio.types import ImuBatch, Scan

FIRING_NS = 5_000
"""200 000 points/s."""
STANDARD_G = 9.80665
MID360_T_IMU_LIDAR = [[1.0, 0.0, 0.0, -0.011], [0.0, 1.0, 0.0, -0.02329],
                      [0.0, 0.0, 1.0, 0.04412], [0.0, 0.0, 0.0, 1.0]]
"""The Mid-360's built-in IMU in its LiDAR's frame (Livox's manual: the IMU at (11.0, 23.29,
-44.12) mm in the LiDAR frame), as the ``livox_mid360`` preset gives it."""
SIM_GRAVITY_M_S2 = 9.81
"""The simulator's gravity (``adalio.sim.imu``): 1.00034 g."""


def _az_el_deg360(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    az, el = az_el_deg(points)
    return az % 360.0, el


def _sha1(path: Path) -> str:
    h = hashlib.sha1()
    for f in sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]:
        h.update(f.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """4 s in the hall without sensor noise: still for 2.5 s, then walking off (1 m/s at 4 s)."""
    return noise_free_walk(tmp_path_factory.mktemp("mid360"), "mid360")


def test_frames_are_livox_custom_msgs_with_every_point_at_its_own_time(walk):
    res, meta, msgs = walk
    frames = custommsg_frames(res, meta, msgs)
    for cloud in frames:
        p = cloud.points
        assert 0.9 * 20_000 < len(p) <= 20_000  # a closed hall: nearly every ray returns
        off = p["offset_time"].astype(np.int64)
        assert off.min() >= 0 and off.max() < PERIOD_NS and np.all(np.diff(off) > 0)
        assert np.all(off % FIRING_NS == 0)  # its own firing slot, 5 us apart
        assert np.array_equal(p["line"], (off // FIRING_NS) % 4)  # the 4 lasers in turn
        assert np.all(p["tag"] == 0) and p["reflectivity"].max() > 100
        az, el = _az_el_deg360(frame_xyz(cloud))
        assert el.min() >= -7.0 - 1e-3 and el.max() <= 52.0 + 1e-3
        assert el.min() < -6.9 and el.max() > 51.9
        # the azimuth turns clockwise once a frame at a constant rate, firing by firing
        turned = (az + 360.0 * off / PERIOD_NS - az[0] + 180.0) % 360.0 - 180.0
        assert np.abs(turned).max() < 0.05
    lines = np.bincount(np.concatenate([c.points["line"] for c in frames]))
    assert len(lines) == 4 and lines.min() > 0.24 * lines.sum()


def test_points_lie_on_the_scene_at_their_own_firing_times(walk):
    """Each point through the ground-truth IMU pose at its own time (``timebase +
    offset_time``) and the extrinsic lies on the mesh; through the frame's first pose instead,
    the walking frame's points do not (the motion distortion is there, per point)."""
    res, meta, msgs = walk
    rows = np.loadtxt(res.gt_path)
    gt_s = rows[:, 0] - rows[0, 0]
    slerp = Slerp(gt_s, Rotation.from_quat(rows[:, 4:]))
    T_il, T_sw = np.asarray(meta["T_imu_lidar"]), np.asarray(meta["T_scene_world"])
    caster = RayCaster(trimesh.load(res.bag_path.parent / "scene.ply"))

    def off_scene_m(xyz: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        p_imu = xyz @ T_il[:3, :3].T + T_il[:3, 3]
        p_w = np.einsum("nij,nj->ni", slerp(t_s).as_matrix(), p_imu) + np.column_stack(
            [np.interp(t_s, gt_s, rows[:, 1 + i]) for i in range(3)])
        return mesh_distance_m(caster, p_w @ T_sw[:3, :3].T + T_sw[:3, 3])

    for k in (5, 38):  # still, and walking at about 1 m/s
        cloud = msgs["/livox/lidar"][k][1]
        xyz = frame_xyz(cloud)
        keep = np.flatnonzero(np.linalg.norm(xyz, axis=1) > 0.5)[::60]  # not the operator
        t_s = (cloud.timebase_ns - START_NS
               + cloud.points["offset_time"][keep].astype(np.int64)) * 1e-9
        d = off_scene_m(xyz[keep], t_s)
        assert np.median(d) < 1e-3 and np.mean(d > 5e-3) < 0.01, (k, np.median(d))
        if k == 38:
            d_first = off_scene_m(xyz[keep], np.full(len(keep), t_s.min()))
            assert np.median(d_first) > 0.005  # 5x the bound above


def test_frames_never_repeat_and_together_fill_the_view(walk):
    """Still frames (the same pose): consecutive frames' directions differ, and ten frames cover
    the field of view far more fully than one (0.5 deg cells hit; the largest elevation gap)."""
    _, _, msgs = walk
    still = [frame_xyz(c) for _, c in msgs["/livox/lidar"][2:22]]  # 0.2-2.2 s: at rest
    dirs = [x / np.linalg.norm(x, axis=1, keepdims=True) for x in still]
    for a, b in itertools.pairwise(dirs):
        near, _ = cKDTree(a).query(b)
        assert np.mean(near < np.radians(0.01)) < 0.01

    def cells_hit(xyz: np.ndarray) -> int:
        az, el = _az_el_deg360(xyz)
        return len(np.unique(np.floor(az / 0.5) * 1000 + np.floor((el + 7.0) / 0.5)))

    def largest_elevation_gap_deg(xyz: np.ndarray) -> float:
        _, el = _az_el_deg360(xyz)
        return float(np.diff(np.sort(np.r_[-7.0, el, 52.0])).max())

    cells = 720 * 118
    one, ten, twenty = (np.concatenate(still[:n]) for n in (1, 10, 20))
    assert cells_hit(one) < 0.3 * cells
    assert cells_hit(ten) > 3.0 * cells_hit(one) and cells_hit(ten) > 0.8 * cells
    assert cells_hit(twenty) > cells_hit(ten)
    assert largest_elevation_gap_deg(ten) < largest_elevation_gap_deg(one) / 3.0


@pytest.fixture(scope="module")
def short(tmp_path_factory):
    """1 s sequences with sensor noise: the Mid-360 twice with one seed and once with another
    (ROS1 and ROS2 sqlite3), and the XT-32 with the same seed."""
    root = tmp_path_factory.mktemp("mid360_short")
    kw = {"duration_s": 1.0, "seed": 5}
    return {"a": simulate("hall", root / "a", lidar="mid360", **kw),
            "b": simulate("hall", root / "b", lidar="mid360", **kw),
            "c": simulate("hall", root / "c", lidar="mid360", duration_s=1.0, seed=6),
            "ros2": simulate("hall", root / "ros2", lidar="mid360", fmt="ros2", **kw),
            "xt32": simulate("hall", root / "xt32", lidar="xt32", columns=16,
                             T_imu_lidar=MID360_T_IMU_LIDAR, **kw),
            "hilti": simulate("hall", root / "hilti", lidar="mid360",
                              T_imu_lidar=T_IMU_LIDAR_HILTI, **kw)}


def test_its_imu_is_its_own_where_the_preset_puts_it(short):
    """By default the Mid-360's IMU is its built-in one: the sequence's config and meta give the
    ``livox_mid360`` preset's extrinsic (identity rotation, the manual's offset), so
    ``--preset livox_mid360`` alone reads the sequence with the true mounting. At rest the
    accelerometer then reads gravity's reaction along the level LiDAR's +z (about +1 g), where
    the HILTI rig's mounting (asked for explicitly) holds the IMU upside down (about -1 g)."""
    preset_T = np.asarray(load_config(preset="livox_mid360").sensor.T_imu_lidar)
    np.testing.assert_array_equal(preset_T, MID360_T_IMU_LIDAR)
    res = short["a"]
    np.testing.assert_array_equal(json.loads(res.meta_path.read_text())["T_imu_lidar"], preset_T)
    np.testing.assert_array_equal(load_config(config_file=res.config_path).sensor.T_imu_lidar,
                                  preset_T)
    np.testing.assert_array_equal(json.loads(short["hilti"].meta_path.read_text())["T_imu_lidar"],
                                  T_IMU_LIDAR_HILTI)

    def still_z_g(r) -> float:
        return float(np.mean([m.linear_acceleration.z
                              for _, m in messages(r.bag_path)["/livox/imu"]][:100]))

    assert still_z_g(res) == pytest.approx(1.0, abs=0.02)
    assert still_z_g(short["hilti"]) == pytest.approx(-1.0, abs=0.02)


def test_same_seed_same_bytes_other_seed_other_bytes(short):
    a, b, c = short["a"], short["b"], short["c"]
    assert _sha1(a.bag_path) == _sha1(b.bag_path)
    assert a.meta_path.read_bytes() == b.meta_path.read_bytes()
    assert _sha1(a.bag_path) != _sha1(c.bag_path)


def test_its_imu_publishes_the_accelerometer_in_g(short):
    """``/livox/imu`` in ``livox_frame``: the same samples as the XT-32 rig's IMU (same seed,
    same mounting) divided by the standard g, so about 1 at rest."""
    imu = [m for _, m in messages(short["a"].bag_path)["/livox/imu"]]
    ref = [m for _, m in messages(short["xt32"].bag_path)["/alphasense/imu"]]
    assert {m.header.frame_id for m in imu} == {"livox_frame"}

    def acc(msgs):
        return np.array([[m.linear_acceleration.x, m.linear_acceleration.y,
                          m.linear_acceleration.z] for m in msgs])

    def gyro(msgs):
        return np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z]
                         for m in msgs])

    np.testing.assert_allclose(acc(imu) * STANDARD_G, acc(ref), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(gyro(imu), gyro(ref))  # rad/s
    # at rest (the walk starts at 2.5 s): gravity's reaction, plus the BMI085's initial bias
    assert np.linalg.norm(acc(imu).mean(axis=0)) == pytest.approx(SIM_GRAVITY_M_S2 / STANDARD_G,
                                                                  abs=0.01)


@pytest.mark.parametrize("which", ["a", "ros2"])
def test_adalio_reads_the_sequence_with_its_own_config(short, which):
    """The sequence's ``config.yaml`` (``accel_unit`` left to ``auto``) through adalio's reader:
    every frame a scan of its points at ``timebase + offset_time`` (no rings: a laser of the
    pattern is none), and
    the IMU found in g and read in m/s^2 as the XT-32 rig's (same seed and mounting) is."""

    def read(res):
        cfg = load_config(config_file=res.config_path)
        with Bag(res.bag_path) as bag:
            lidar, imu = bag.select_topics(cfg.sensor)
            items = list(Sequencer(bag, lidar, imu, cfg.sensor))
        acc = np.concatenate([i.accel_m_s2 for i in items if isinstance(i, ImuBatch)])
        return cfg, (lidar, imu), [i for i in items if isinstance(i, Scan)], acc

    res = short[which]
    meta = json.loads(res.meta_path.read_text())
    with pytest.warns(UserWarning, match="reports in g"):
        cfg, topics, scans, acc = read(res)
    assert cfg.sensor.accel_unit == "auto" and topics == ("/livox/lidar", "/livox/imu")
    assert len(scans) == meta["n_scans"] == 10 and len(acc) == meta["n_imu"]
    assert sum(len(s.t_ns) for s in scans) == meta["n_points"]
    for k, s in enumerate(scans):
        start = START_NS + k * PERIOD_NS
        assert s.stamp_ns == start and s.t_ns.min() >= start and s.t_ns.max() < start + PERIOD_NS
        assert s.ring is None
    np.testing.assert_allclose(acc, read(short["xt32"])[3], rtol=1e-12, atol=1e-12)


def test_columns_and_rate_set_the_frame(tmp_path):
    """``columns``: firing cycles of the 4 lasers a frame; ``lidar_rate_hz``: frames a second,
    each frame's firings spread over its period."""
    res = simulate("hall", tmp_path, duration_s=1.0, lidar="mid360", columns=300,
                   lidar_rate_hz=20.0, noise_scale=0.0, seed=1)
    frames = messages(res.bag_path)["/livox/lidar"]
    assert len(frames) == 20
    for _, cloud in frames:
        off = cloud.points["offset_time"].astype(np.int64)
        slot = 50_000_000 // 1200
        assert 0.9 * 1200 < len(off) <= 1200 and off.max() < 50_000_000
        assert np.array_equal(cloud.points["line"], (off // slot) % 4)
