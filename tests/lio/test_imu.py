import numpy as np
import pytest

from adalio.config import ImuConfig
from adalio.lio import imu, so3
from adalio.lio.state import DIM, State

rng = np.random.default_rng(1)


def _random_state() -> State:
    g = so3.exp(rng.normal(size=3) * 0.3) @ np.array([0.0, 0.0, -9.81])
    return State(p=rng.normal(size=3), R=so3.exp(rng.normal(size=3)),
                 R_LI=so3.exp(rng.normal(size=3) * 0.1), t_LI=rng.normal(size=3) * 0.1,
                 v=rng.normal(size=3), b_g=rng.normal(size=3) * 0.05,
                 b_a=rng.normal(size=3) * 0.2, g=g, g_anchor=so3.anchor_frame(g))


def _step(x: State, gyro, acc, dt, noise=None) -> State:
    """The discrete step of §3.1 with the additive noise of §3.2 injected."""
    noise = np.zeros(12) if noise is None else noise
    p, R, v = imu.discrete_step(x.p, x.R, x.v, x.b_g, x.b_a, x.g, gyro - noise[0:3],
                                acc - noise[3:6], dt)
    y = x.copy()
    y.p, y.R, y.v = p, R, v
    y.b_g = x.b_g + noise[6:9] * dt
    y.b_a = x.b_a + noise[9:12] * dt
    return y


@pytest.mark.parametrize("accel_in_g", [False, True])
def test_static_init_recovers_gravity_and_gyro_bias(accel_in_g):
    cfg = ImuConfig()
    R_wi = so3.exp(np.array([0.2, -0.1, 0.7]))
    up_world = np.array([0.0, 0.0, 1.0])
    specific_force = R_wi.T @ (9.81 * up_world)
    if accel_in_g:
        specific_force = specific_force / 9.81
    bias = np.array([0.01, -0.02, 0.005])
    n = 200
    gyro = np.tile(bias, (n, 1))
    acc = np.tile(specific_force, (n, 1))
    out = imu.static_init(gyro, acc, cfg)
    assert np.allclose(out.gyro_bias_rad_s, bias, atol=1e-15)
    assert np.allclose(out.gravity_world_m_s2, -9.81 * (R_wi.T @ up_world), atol=1e-12)
    assert np.allclose(out.R_world_imu, np.eye(3))
    assert np.isclose(out.accel_scale * np.linalg.norm(specific_force), 9.81)

    cfg.gravity_align_world = True
    out = imu.static_init(gyro, acc, cfg)
    assert np.allclose(out.gravity_world_m_s2, [0.0, 0.0, -9.81], atol=1e-12)
    R = out.R_world_imu
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.allclose(R @ (specific_force * out.accel_scale), [0, 0, 9.81], atol=1e-12)


def test_stillness_check_rejects_motion_and_waits_for_window():
    cfg = ImuConfig()
    t_ns = np.arange(0, 2_000_000_000, 2_500_000, dtype=np.int64)
    t_s = t_ns * 1e-9
    n = t_ns.size
    gyro = 0.002 * rng.normal(size=(n, 3))
    acc = np.array([0.0, 0.0, 9.81]) + 0.02 * rng.normal(size=(n, 3))
    moving = t_s < 1.0
    gyro[moving, 2] += 0.5 * np.sin(2 * np.pi * 1.5 * t_s[moving])
    acc[moving, 0] += 1.0 * np.sin(2 * np.pi * 2.0 * t_s[moving])

    assert imu.stillness_window(t_ns, int(0.3e9), cfg.init_window_s) is None
    w = imu.stillness_window(t_ns, int(0.9e9), cfg.init_window_s)
    assert not imu.is_still(gyro[w], acc[w], cfg)
    w = imu.stillness_window(t_ns, int(1.2e9), cfg.init_window_s)
    assert not imu.is_still(gyro[w], acc[w], cfg)
    w = imu.stillness_window(t_ns, int(1.6e9), cfg.init_window_s)
    assert t_ns[w][0] >= int(1.1e9) and t_ns[w][-1] <= int(1.6e9)
    assert imu.is_still(gyro[w], acc[w], cfg)
    assert not imu.is_still(gyro[w][:5], acc[w][:5], cfg)


def test_F_and_G_match_numerical_differentiation():
    for _ in range(5):
        x = _random_state()
        gyro = rng.normal(size=3)
        acc = rng.normal(size=3) * 3
        dt = 0.01
        F, G = imu.jacobians_fg(x.R, x.b_g, x.b_a, x.g, x.g_anchor, gyro, acc, dt)
        y0 = _step(x, gyro, acc, dt)
        eps = 1e-6
        F_num = np.empty((DIM, DIM))
        for i in range(DIM):
            e = np.zeros(DIM)
            e[i] = eps
            F_num[:, i] = (_step(x.boxplus(e), gyro, acc, dt).boxminus(y0)
                           - _step(x.boxplus(-e), gyro, acc, dt).boxminus(y0)) / (2 * eps)
        assert np.allclose(F, F_num, atol=1e-7), np.abs(F - F_num).max()
        G_num = np.empty((DIM, 12))
        for i in range(12):
            e = np.zeros(12)
            e[i] = eps
            G_num[:, i] = (_step(x, gyro, acc, dt, e).boxminus(y0)
                           - _step(x, gyro, acc, dt, -e).boxminus(y0)) / (2 * eps)
        assert np.allclose(G, G_num, atol=1e-7), np.abs(G - G_num).max()


def test_sparse_covariance_propagation_matches_dense():
    x = _random_state()
    F, G = imu.jacobians_fg(x.R, x.b_g, x.b_a, x.g, x.g_anchor, rng.normal(size=3),
                            rng.normal(size=3), 0.005)
    A = rng.normal(size=(DIM, DIM))
    P = A @ A.T
    q = imu.process_noise(ImuConfig())
    dense = F @ P @ F.T + G @ np.diag(q) @ G.T
    assert np.allclose(imu.propagate_covariance(P, F, G, q), dense, atol=1e-12)


def test_block_covariance_propagation_matches_dense():
    for _ in range(5):
        x = _random_state()
        gyro, acc, dt = rng.normal(size=3), rng.normal(size=3) * 3, 0.004
        F, G = imu.jacobians_fg(x.R, x.b_g, x.b_a, x.g, x.g_anchor, gyro, acc, dt)
        A = rng.normal(size=(DIM, DIM))
        P = A @ A.T
        q = imu.process_noise(ImuConfig())
        dense = F @ P @ F.T + G @ np.diag(q) @ G.T
        fast = imu.propagate_covariance_fast(P, x.R, x.b_g, x.b_a, x.g, x.g_anchor, gyro, acc,
                                             dt, q)
        assert np.allclose(fast, dense, atol=1e-12)


def test_propagate_scan_equals_stepwise_midpoint_integration():
    x = _random_state()
    P = np.eye(DIM)
    tau = np.array([-0.001, 0.0015, 0.004, 0.0065, 0.009])
    gyro = rng.normal(size=(5, 3))
    acc = rng.normal(size=(5, 3)) * 2
    q = imu.process_noise(ImuConfig())
    y, P_out, rec = imu.propagate(x, P, tau, gyro, acc, 0.0, 0.01, q)
    ref = x.copy()
    P_ref = P.copy()
    times = [0.0, 0.0015, 0.004, 0.0065, 0.009]
    for k in range(4):
        g_mid = 0.5 * (gyro[k] + gyro[k + 1])
        a_mid = 0.5 * (acc[k] + acc[k + 1])
        dt = times[k + 1] - times[k]
        assert np.isclose(rec.tau_s[k], times[k])
        assert np.allclose(rec.R[k], ref.R) and np.allclose(rec.p[k], ref.p)
        F, G = imu.jacobians_fg(ref.R, ref.b_g, ref.b_a, ref.g, ref.g_anchor, g_mid, a_mid, dt)
        P_ref = F @ P_ref @ F.T + G @ np.diag(q) @ G.T
        ref = _step(ref, g_mid, a_mid, dt)
    F, G = imu.jacobians_fg(ref.R, ref.b_g, ref.b_a, ref.g, ref.g_anchor, g_mid, a_mid, 0.001)
    P_ref = F @ P_ref @ F.T + G @ np.diag(q) @ G.T
    ref = _step(ref, g_mid, a_mid, 0.001)
    assert rec.tau_s.shape[0] == 5
    assert np.allclose(y.R, ref.R) and np.allclose(y.p, ref.p) and np.allclose(y.v, ref.v)
    assert np.allclose(P_out, P_ref)
