"""A LiDAR tilted on the handle (``simulate(lidar_tilt_deg=...)``): its spin axis leans by the
tilt against gravity as the IMU measures it, its points lie on the scene through the ground
truth and the unchanged extrinsic, and the operator's body stays upright behind it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from rosbags.highlevel import AnyReader
from scipy.spatial.transform import Rotation, Slerp

from adalio.errors import InputError
from adalio.io.pointcloud2 import CloudLayout, decode_fields
from adalio.sim import simulate
from adalio.sim.generate import START_NS, T_IMU_LIDAR_HILTI, build_trajectory, mesh_distance_m
from adalio.sim.lidar import Occluder, RayCaster, SweepSimulator, lidar_model
from adalio.sim.scenes import build_scene
from adalio.sim.trajectory import tilt_rig_lidar

TILT_DEG = 40.0


def _read(bag_path):
    acc, scans = [], []
    with AnyReader([bag_path]) as reader:
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype.endswith("Imu"):
                a = msg.linear_acceleration
                acc.append([a.x, a.y, a.z])
            else:
                scans.append(msg)
    return np.array(acc), scans


def _xyzt(msg):
    """The cloud's points (LiDAR frame) and absolute times (s), beyond 0.5 m."""
    f = decode_fields(msg.data, CloudLayout.from_msg(msg), ["x", "y", "z", "timestamp"])
    xyz = np.column_stack([f["x"], f["y"], f["z"]]).astype(np.float64)
    keep = np.linalg.norm(xyz, axis=1) > 0.5
    return xyz[keep], f["timestamp"][keep]


@pytest.fixture(scope="module")
def tilted(tmp_path_factory):
    return simulate("hall", tmp_path_factory.mktemp("tilt"), duration_s=5.0, columns=128,
                    noise_scale=0.0, seed=4, lidar_tilt_deg=TILT_DEG)


def test_the_spin_axis_leans_forward_by_the_tilt_against_the_imu_s_gravity(tilted):
    meta = json.loads(tilted.meta_path.read_text())
    assert meta["lidar_tilt_deg"] == TILT_DEG
    acc, _ = _read(tilted.bag_path)
    up = acc[0] / np.linalg.norm(acc[0])  # still: the accelerometer reads gravity's reaction
    R_il = np.asarray(meta["T_imu_lidar"])[:3, :3]
    axis, nose = R_il @ [0.0, 0.0, 1.0], R_il @ [1.0, 0.0, 0.0]
    assert np.degrees(np.arccos(axis @ up)) == pytest.approx(TILT_DEG, abs=1e-6)
    assert np.degrees(np.arcsin(-(nose @ up))) == pytest.approx(TILT_DEG, abs=1e-6)  # nose down


def test_the_points_lie_on_the_scene_through_the_truth_and_the_same_extrinsic(tilted):
    meta = json.loads(tilted.meta_path.read_text())
    _, scans = _read(tilted.bag_path)
    with open(tilted.gt_path) as f:
        rows = np.array([[float(v) for v in ln.split()] for ln in f if not ln.startswith("#")])
    gt_s = rows[:, 0] - rows[0, 0]
    slerp = Slerp(gt_s, Rotation.from_quat(rows[:, 4:]))
    T_il, T_sw = np.asarray(meta["T_imu_lidar"]), np.asarray(meta["T_scene_world"])
    caster = RayCaster(trimesh.load(tilted.bag_path.parent / "scene.ply"))
    for k in (5, 40):  # still, and walking
        xyz, t_abs = _xyzt(scans[k])
        xyz, ts = xyz[::5], t_abs[::5] - rows[0, 0]
        p_imu = xyz @ T_il[:3, :3].T + T_il[:3, 3]
        p_w = np.einsum("nij,nj->ni", slerp(ts).as_matrix(), p_imu) + np.column_stack(
            [np.interp(ts, gt_s, rows[:, 1 + i]) for i in range(3)])
        d = mesh_distance_m(caster, p_w @ T_sw[:3, :3].T + T_sw[:3, 3])
        assert np.median(d) < 1e-3 and np.mean(d > 5e-3) < 0.01, (k, np.median(d))
        # the floor ahead: a level XT-32 (+-16 deg) sees none of it within 3 m
        assert np.mean((xyz[:, 0] > 0) & (np.linalg.norm(xyz, axis=1) < 3.0)) > 0.05


def test_the_operator_s_body_stays_upright_behind_a_tilted_lidar():
    scn = build_scene("hall", 0)
    T = np.asarray(T_IMU_LIDAR_HILTI)
    R_rl = tilt_rig_lidar(TILT_DEG)
    sim = SweepSimulator(RayCaster(scn.mesh), build_trajectory(scn, T, 0, None, TILT_DEG),
                         lidar_model("xt32", 512), T, START_NS, Occluder())
    sw = sim.sweep(START_NS, np.random.default_rng(0), noise_scale=0.0)
    body = sw.valid & (sw.face == -1)
    assert body.sum() > 50
    occ = Occluder()
    lo, hi = np.asarray(occ.lo), np.asarray(occ.hi)

    def on_box(p):
        inside = np.all((p >= lo - 1e-4) & (p <= hi + 1e-4), axis=1)
        face = np.min(np.minimum(np.abs(p - lo), np.abs(p - hi)), axis=1) < 1e-4
        return inside & face

    p_lidar = sw.xyz_lidar_m[body].astype(np.float64)
    assert on_box(p_lidar @ R_rl.T).all()  # the box in the rig frame
    assert on_box(p_lidar).mean() < 0.5  # not turned with the LiDAR


def test_a_tilt_beyond_a_right_angle_is_refused(tmp_path):
    with pytest.raises(InputError, match="--lidar-tilt-deg must be within"):
        simulate("hall", tmp_path, duration_s=1.0, columns=64, lidar_tilt_deg=95.0)
    assert not any(tmp_path.iterdir())
