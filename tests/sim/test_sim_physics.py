"""Physics of the simulator against independent truth (integration, geometry, finite differences)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from rosbags.highlevel import AnyReader
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp

from adalio.sim import SCENES, simulate
from adalio.sim.generate import T_IMU_LIDAR_HILTI, build_trajectory, mesh_distance_m
from adalio.sim.imu import GRAVITY_M_S2, ImuNoise, sensitivity_errors, synthesize_imu
from adalio.sim.lidar import RayCaster
from adalio.sim.scenes import build_scene


def _read_bag(bag_path, lidar_topic="/hesai/pandar", max_scans=None):
    imu_t, gyro, acc, scans = [], [], [], []
    with AnyReader([bag_path]) as reader:
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == lidar_topic:
                if max_scans is None or len(scans) < max_scans:
                    scans.append(msg)
            else:
                st = msg.header.stamp
                imu_t.append(st.sec * 1_000_000_000 + st.nanosec)
                w, a = msg.angular_velocity, msg.linear_acceleration
                gyro.append([w.x, w.y, w.z])
                acc.append([a.x, a.y, a.z])
    return np.array(imu_t, dtype=np.int64), np.array(gyro), np.array(acc), scans


def _read_tum(path):
    with open(path) as f:
        rows = [line.split() for line in f if not line.startswith("#")]
    t_ns = np.array([int(r[0].replace(".", "")) for r in rows], dtype=np.int64)
    vals = np.array([[float(v) for v in r[1:]] for r in rows])
    return t_ns, vals[:, :3], Rotation.from_quat(vals[:, 3:])


def _cloud_xyzt(msg):
    offs = {f.name: f.offset for f in msg.fields}
    dt = np.dtype({"names": ["x", "y", "z", "timestamp"], "formats": ["<f4", "<f4", "<f4", "<f8"],
                   "offsets": [offs["x"], offs["y"], offs["z"], offs["timestamp"]],
                   "itemsize": msg.point_step})
    arr = np.frombuffer(msg.data.tobytes(), dtype=dt)
    return np.column_stack([arr["x"], arr["y"], arr["z"]]).astype(np.float64), arr["timestamp"]


@pytest.fixture(scope="module")
def perfect_hall(tmp_path_factory):
    out = tmp_path_factory.mktemp("perfect")
    return simulate("hall", out, duration_s=12.6, columns=36, noise_scale=0.0, seed=3)


def test_noise_free_imu_integrates_to_ground_truth(perfect_hall):
    res = perfect_hall
    meta = json.loads(res.meta_path.read_text())
    t_ns, gyro, acc, _ = _read_bag(res.bag_path)
    gt_t, gt_p, gt_R = _read_tum(res.gt_path)
    R0 = np.asarray(meta["T_scene_world"])[:3, :3]
    g_world = R0.T @ np.array([0.0, 0.0, -GRAVITY_M_S2])
    ts = (t_ns - t_ns[0]) * 1e-9
    wf, af = CubicSpline(ts, gyro), CubicSpline(ts, acc)

    def deriv(t, R, v):
        w = wf(t)
        W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return R @ W, R @ af(t) + g_world, v

    R, v, p = np.eye(3), np.zeros(3), np.zeros(3)
    dt = ts[1] - ts[0]
    end = round(12.5 / dt)
    for k in range(end):
        t = ts[k]
        k1 = deriv(t, R, v)
        k2 = deriv(t + dt / 2, R + dt / 2 * k1[0], v + dt / 2 * k1[1])
        k3 = deriv(t + dt / 2, R + dt / 2 * k2[0], v + dt / 2 * k2[1])
        k4 = deriv(t + dt, R + dt * k3[0], v + dt * k3[1])
        R = R + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        p = p + dt / 6 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
        v = v + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        u, _, vt = np.linalg.svd(R)
        R = u @ vt
    i = int(np.searchsorted(gt_t, t_ns[end]))
    assert gt_t[i] == t_ns[end]
    assert np.linalg.norm(gt_p[i]) > 5.0
    pos_err = np.linalg.norm(p - gt_p[i])
    rot_err = np.degrees(np.linalg.norm(
        Rotation.from_matrix(gt_R[i].as_matrix().T @ R).as_rotvec()))
    print(f"\nIMU dead-reckoning over 12.5 s: {pos_err * 1e6:.1f} um, {rot_err:.2e} deg, "
          f"travelled {np.linalg.norm(gt_p[i]):.1f} m")
    assert pos_err < 0.01, pos_err
    assert rot_err < 0.05, rot_err


def test_static_start_is_exactly_static(perfect_hall):
    meta = json.loads(perfect_hall.meta_path.read_text())
    t_ns, gyro, acc, _ = _read_bag(perfect_hall.bag_path)
    static = (t_ns - t_ns[0]) * 1e-9 <= meta["static_s"]
    assert static.sum() >= 2.0 * 400
    assert np.all(gyro[static] == 0.0)
    assert np.all(acc[static] == acc[0])
    assert abs(np.linalg.norm(acc[0]) - GRAVITY_M_S2) < 1e-9
    moving = (t_ns - t_ns[0]) * 1e-9 > meta["static_s"] + 0.5
    assert np.abs(gyro[moving]).max() > 0.05
    gt_t, gt_p, gt_R = _read_tum(perfect_hall.gt_path)
    gs = (gt_t - gt_t[0]) * 1e-9 <= meta["static_s"]
    assert np.all(gt_p[gs] == 0.0)
    assert np.all(gt_R[gs].as_quat()[:, :3] == 0.0)
    traj = build_trajectory(build_scene("hall", 3), np.asarray(T_IMU_LIDAR_HILTI), 3)
    s = traj.sample(np.linspace(0.0, traj.static_s, 50))
    assert np.all(s.v_world_m_s == 0) and np.all(s.a_world_m_s2 == 0)
    assert np.all(s.p_world_imu_m == s.p_world_imu_m[0])
    # C2 at the start of the motion: velocity and acceleration continuous
    s2 = traj.sample(traj.static_s + np.array([1e-4]))
    assert np.linalg.norm(s2.a_world_m_s2) < 0.05


def test_trajectory_derivatives_match_finite_differences():
    traj = build_trajectory(build_scene("corridor", 1), np.asarray(T_IMU_LIDAR_HILTI), 1)
    t = np.array([4.0, 9.37, 20.1, 33.3])
    h = 1e-5
    sp, sm, s0 = traj.sample(t + h), traj.sample(t - h), traj.sample(t)
    np.testing.assert_allclose((sp.p_world_imu_m - sm.p_world_imu_m) / (2 * h), s0.v_world_m_s,
                               atol=1e-6)
    np.testing.assert_allclose((sp.v_world_m_s - sm.v_world_m_s) / (2 * h), s0.a_world_m_s2,
                               atol=1e-5)
    dR = np.einsum("nji,njk->nik", s0.R_world_imu, (sp.R_world_imu - sm.R_world_imu) / (2 * h))
    w = np.column_stack([dR[:, 2, 1], dR[:, 0, 2], dR[:, 1, 0]])
    np.testing.assert_allclose(w, s0.omega_imu_rad_s, atol=1e-6)
    np.testing.assert_allclose((sp.omega_imu_rad_s - sm.omega_imu_rad_s) / (2 * h),
                               s0.alpha_imu_rad_s2, atol=1e-5)


@pytest.mark.parametrize("scene", SCENES)
def test_walk_is_human_and_keeps_clear_of_the_mesh(scene):
    scn = build_scene(scene, 0)
    traj = build_trajectory(scn, np.asarray(T_IMU_LIDAR_HILTI), 0)
    t = np.arange(0.0, traj.duration_s, 0.01)
    s = traj.sample(t)
    speed = np.linalg.norm(s.v_world_m_s, axis=1)
    assert speed.max() < 1.5
    assert np.median(speed[t > traj.static_s + 3]) > 0.4
    up_imu = np.asarray(T_IMU_LIDAR_HILTI)[:3, :3] @ [0.0, 0.0, 1.0]
    yaw_rate = np.abs(s.omega_imu_rad_s @ up_imu)
    assert np.degrees(yaw_rate.max()) < 100.0
    caster = RayCaster(scn.mesh)
    d = mesh_distance_m(caster, s.p_world_imu_m[::10])
    assert d.min() > 0.25, d.min()


def test_points_lie_on_the_mesh_only_with_per_point_poses(tmp_path):
    res = simulate("hall", tmp_path, duration_s=9.0, columns=400, seed=5)
    meta = json.loads(res.meta_path.read_text())
    _, _, _, scans = _read_bag(res.bag_path)
    gt_t, gt_p, gt_R = _read_tum(res.gt_path)
    gt_s = (gt_t - gt_t[0]) * 1e-9
    slerp = Slerp(gt_s, gt_R)
    T_il = np.asarray(meta["T_imu_lidar"])
    T_sw = np.asarray(meta["T_scene_world"])
    mesh = trimesh.load(res.bag_path.parent / "scene.ply")
    caster = RayCaster(mesh)
    msg = scans[70]
    xyz, t_abs = _cloud_xyzt(msg)
    keep = np.linalg.norm(xyz, axis=1) > 0.5
    xyz, t_abs = xyz[keep][::7], t_abs[keep][::7]
    ts = t_abs - gt_t[0] * 1e-9
    assert np.ptp(ts) > 0.09

    def to_scene(R_w_i, p_w_i):
        p_imu = xyz @ T_il[:3, :3].T + T_il[:3, 3]
        p_w = np.einsum("nij,nj->ni", R_w_i, p_imu) + p_w_i
        return p_w @ T_sw[:3, :3].T + T_sw[:3, 3]

    p_i = np.column_stack([np.interp(ts, gt_s, gt_p[:, k]) for k in range(3)])
    per_point = mesh_distance_m(caster, to_scene(slerp(ts).as_matrix(), p_i))
    n = len(ts)
    one = mesh_distance_m(caster, to_scene(np.repeat(slerp([ts.max()]).as_matrix(), n, 0),
                                           np.repeat(p_i[ts.argmax()][None], n, 0)))
    sigma = meta["range_noise_m"]
    assert np.median(per_point) < 1.2 * sigma, np.median(per_point)
    assert np.mean(per_point > 4 * sigma) < 0.01
    assert np.mean(one > 4 * sigma) > 0.15


@pytest.mark.parametrize("fs", [400.0, 100.0])
def test_imu_noise_matches_the_bmi085_densities(tmp_path, fs):
    """At the BMI085's 400 Hz and at an Ouster IMU's 100 Hz (``imu_rate_hz``): the samples are
    ``1/fs`` apart and their white noise is the densities times ``sqrt(fs)`` (the bound widens
    as ``sqrt(400/fs)``: a quarter of the samples in the same 2.4 s rest)."""
    res = simulate("hall", tmp_path, duration_s=2.4, columns=36, seed=8, imu_rate_hz=fs)
    meta = json.loads(res.meta_path.read_text())
    assert meta["imu_rate_hz"] == fs
    t_imu, gyro, acc, _ = _read_bag(res.bag_path)
    assert np.all(np.diff(t_imu) == round(1e9 / fs))
    rtol = 0.08 * np.sqrt(400.0 / fs)
    noise = meta["imu_noise"]
    for x, density, bias0 in ((gyro, noise["gyro_noise_rad_s_sqrt_hz"], meta["gyro_bias0_rad_s"]),
                              (acc, noise["accel_noise_m_s2_sqrt_hz"], None)):
        sigma = np.std(np.diff(x, axis=0), axis=0) / np.sqrt(2.0)
        np.testing.assert_allclose(sigma, density * np.sqrt(fs), rtol=rtol)
        if bias0 is not None:
            err = np.abs(x.mean(axis=0) - np.asarray(bias0))
            assert np.all(err < 4 * density * np.sqrt(fs) / np.sqrt(len(x)) + 8e-4)
            assert np.linalg.norm(bias0) > 1e-4
    assert np.linalg.norm(meta["accel_bias0_m_s2"]) > 1e-3
    g = np.linalg.norm(acc.mean(axis=0))
    assert abs(g - GRAVITY_M_S2) < 0.1


def test_imu_bias_scale_scales_the_biases_alone():
    """``bias_scale`` multiplies the initial biases and bias walks and nothing else: with the
    same draws, the white noise is the same sample by sample, the biases are 0 at scale 0 and
    twice scale 1's at scale 2, and a bias-free IMU reads the true rate and specific force
    up to white noise of the BMI085 densities."""
    traj = build_trajectory(build_scene("hall", 0), np.asarray(T_IMU_LIDAR_HILTI), 0)
    t_ns = np.arange(4000, dtype=np.int64) * 2_500_000
    out = {k: synthesize_imu(traj, t_ns, 0, np.random.default_rng(7), bias_scale=k)
           for k in (0.0, 1.0, 2.0)}
    for name, unit in (("gyro", "rad_s"), ("accel", "m_s2")):
        bias = {k: getattr(o, f"{name}_bias_{unit}") for k, o in out.items()}
        meas = {k: getattr(o, f"{name}_{unit}") for k, o in out.items()}
        true = getattr(out[0.0], f"{name}_true_{unit}")
        assert np.all(bias[0.0] == 0.0) and np.abs(bias[1.0]).max() > 0
        np.testing.assert_allclose(bias[2.0], 2.0 * bias[1.0], rtol=1e-12, atol=0)
        white = {k: meas[k] - true - bias[k] for k in out}
        np.testing.assert_allclose(white[0.0], white[1.0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(white[2.0], white[1.0], rtol=0, atol=1e-12)
    density = ImuNoise().accel_noise_m_s2_sqrt_hz
    np.testing.assert_allclose(np.std(out[0.0].accel_m_s2 - out[0.0].accel_true_m_s2, axis=0),
                               density * np.sqrt(400.0), rtol=0.08)
    assert np.abs(np.mean(out[0.0].accel_m_s2 - out[0.0].accel_true_m_s2, axis=0)).max() < (
        4 * density * np.sqrt(400.0) / np.sqrt(len(t_ns)))


def test_mesh_distance_matches_brute_force():
    scn = build_scene("spiral", 0)
    caster = RayCaster(scn.mesh)
    rng = np.random.default_rng(0)
    lo, hi = scn.mesh.bounds
    pts = rng.uniform(lo, hi, (40, 3))
    tris = scn.mesh.triangles
    brute = np.array([np.linalg.norm(trimesh.triangles.closest_point(
        tris, np.repeat(p[None], len(tris), 0)) - p, axis=1).min() for p in pts])
    np.testing.assert_allclose(mesh_distance_m(caster, pts), brute, atol=1e-9)


def test_imu_sensitivity_errors_are_what_a_regression_on_the_truth_recovers():
    """With sensitivity errors the samples are ``(I + E) x + bias + noise``: a least-squares fit
    of the samples on the true rate and specific force (plus a constant) recovers ``I + E`` for
    each sensor, while the IMU without them fits the identity; the draws are the seed's own
    stream (the white noise and biases do not move) and scale with ``sigma``."""
    traj = build_trajectory(build_scene("hall", 0), np.asarray(T_IMU_LIDAR_HILTI), 0)
    t_ns = 2_500_000_000 + np.arange(12_000, dtype=np.int64) * 2_500_000  # 30 s of the walk
    E = sensitivity_errors(3, 0.01)
    assert np.array_equal(sensitivity_errors(3, 0.02)[0], 2.0 * E[0])
    assert not np.allclose(sensitivity_errors(4, 0.01)[0], E[0])
    assert not np.any(sensitivity_errors(3, 0.0)[0])
    def imu(bias_scale, sensitivity=None):
        return synthesize_imu(traj, t_ns, 0, np.random.default_rng(7), bias_scale=bias_scale,
                              sensitivity=sensitivity)

    plain, off = imu(0.0), imu(0.0, E)  # without bias walks: the fit's constant is exact
    # tolerances: the white noise's share of the fit (the accelerometer sees little but gravity)
    for name, unit, E_s, tol in (("gyro", "rad_s", E[0], 1e-3), ("accel", "m_s2", E[1], 3e-3)):
        true = getattr(off, f"{name}_true_{unit}")
        X = np.column_stack([true, np.ones(len(true))])
        for sample, expected in ((off, np.eye(3) + E_s), (plain, np.eye(3))):
            fit, *_ = np.linalg.lstsq(X, getattr(sample, f"{name}_{unit}"), rcond=None)
            np.testing.assert_allclose(fit[:3].T, expected, rtol=0, atol=tol)
        np.testing.assert_array_equal(getattr(imu(1.0, E), f"{name}_bias_{unit}"),
                                      getattr(imu(1.0), f"{name}_bias_{unit}"))
    assert min(np.abs(E[0]).max(), np.abs(E[1]).max()) > 5 * 3e-3  # errors >> tolerances
