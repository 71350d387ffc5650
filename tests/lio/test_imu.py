import numpy as np
import pytest

from adalio.config import ImuConfig
from adalio.lio import imu, so3
from adalio.lio.state import DIM, State

rng = np.random.default_rng(1)


def _random_state(rng: np.random.Generator = rng) -> State:
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


HILTI_GYRO_DENSITY = 1.9e-4
HILTI_ACCEL_DENSITY = 1.32e-3


def _imu_window(rate_hz: float, noise_scale: float, seed: int,
                duration_s: float = ImuConfig().init_window_s, motion=None):
    """IMU samples at rest (gravity along a tilted axis, a constant bias) plus white noise of
    ``noise_scale`` x the HILTI BMI085 densities, plus ``motion(t) -> (gyro, accel)`` if given."""
    r = np.random.default_rng(seed)
    n = int(duration_s * rate_hz) + 1
    t_ns = np.round(np.arange(n) / rate_hz * 1e9).astype(np.int64)
    up = so3.exp(np.array([0.3, -0.2, 0.0])) @ np.array([0.0, 0.0, 9.81])
    gyro = np.array([2e-3, -1e-3, 5e-4]) + noise_scale * HILTI_GYRO_DENSITY * np.sqrt(rate_hz) \
        * r.normal(size=(n, 3))
    acc = up + noise_scale * HILTI_ACCEL_DENSITY * np.sqrt(rate_hz) * r.normal(size=(n, 3))
    if motion is not None:
        dg, da = motion(t_ns * 1e-9 + r.uniform(0, 1))
        gyro, acc = gyro + dg, acc + da
    return t_ns, gyro, acc


def _slow_walk(t):
    """A slow walk: step bobbing 0.4 m/s^2 at 1.6 Hz, sway 0.15 rad/s at 0.8 Hz, slow turn."""
    gyro = np.column_stack([0.15 * np.sin(2 * np.pi * 0.8 * t), 0.05 * np.sin(2 * np.pi * 1.6 * t),
                            0.1 + 0.0 * t])
    acc = np.column_stack([0.2 * np.sin(2 * np.pi * 1.6 * t), 0.1 * np.cos(2 * np.pi * 0.8 * t),
                           0.4 * np.sin(2 * np.pi * 1.6 * t + 0.3)])
    return gyro, acc


def _tremor(t):
    """Hand tremor at 9-11 Hz: 0.03 rad/s, 0.3 m/s^2."""
    gyro = 0.03 * np.column_stack([np.sin(2 * np.pi * 9.3 * t), np.cos(2 * np.pi * 10.1 * t),
                                   np.sin(2 * np.pi * 11.0 * t)])
    acc = 0.3 * np.column_stack([np.sin(2 * np.pi * 10.4 * t), np.sin(2 * np.pi * 9.7 * t + 1),
                                 np.cos(2 * np.pi * 10.9 * t)])
    return gyro, acc


def _engine(t):
    """A running engine: 2 m/s^2 and 0.05 rad/s at 29 Hz, its harmonic, and broadband shake."""
    s = np.sin(2 * np.pi * 29.0 * t) + 0.5 * np.sin(2 * np.pi * 58.0 * t)
    return 0.05 * np.column_stack([s, s, 0.5 * s]), 2.0 * np.column_stack([0.5 * s, s, s])


@pytest.mark.parametrize("rate_hz", [100.0, 200.0, 400.0])
@pytest.mark.parametrize("noise_scale", [1.0, 10.0, 50.0])
def test_stillness_test_adapts_to_the_imu_noise(rate_hz, noise_scale):
    """At rest the test says still (false alarms near the configured 1e-3 level, whatever the
    noise), a slow walk is motion; the measured densities are the true ones."""
    cfg = ImuConfig()
    verdicts = []
    for seed in range(100):
        t_ns, gyro, acc = _imu_window(rate_hz, noise_scale, seed)
        test = imu.stillness_test(t_ns, gyro, acc, cfg)
        verdicts.append(test.still)
        if seed < 10:
            # a variance with dof degrees of freedom: its square root has a relative standard
            # deviation of about 1 / sqrt(2 dof); allow 4 of those
            rel = 4.0 / np.sqrt(2 * test.noise_dof)
            assert test.gyro_noise_rad_s_sqrt_hz == pytest.approx(
                noise_scale * HILTI_GYRO_DENSITY, rel=rel)
            assert test.accel_noise_m_s2_sqrt_hz == pytest.approx(
                noise_scale * HILTI_ACCEL_DENSITY, rel=rel)
            assert test.rate_hz == pytest.approx(rate_hz, rel=1e-6)
    assert np.mean(verdicts) >= 0.97
    if noise_scale <= 10:
        for seed in range(20):
            t_ns, gyro, acc = _imu_window(rate_hz, noise_scale, seed, motion=_slow_walk)
            assert not imu.stillness_test(t_ns, gyro, acc, cfg).still


@pytest.mark.parametrize("motion", [_tremor, _engine])
def test_tremor_and_engine_vibration_are_rest(motion):
    cfg = ImuConfig()
    for seed in range(20):
        t_ns, gyro, acc = _imu_window(400.0, 1.0, seed, motion=motion)
        test = imu.stillness_test(t_ns, gyro, acc, cfg)
        assert test.still, test.describe()


def test_stillness_test_judges_accel_in_g_alike():
    cfg = ImuConfig()
    t_ns, gyro, acc = _imu_window(400.0, 10.0, 3)
    assert imu.stillness_test(t_ns, gyro, acc / 9.81, cfg).still
    t_ns, gyro, acc = _imu_window(400.0, 10.0, 3, motion=_slow_walk)
    assert not imu.stillness_test(t_ns, gyro, acc / 9.81, cfg).still


def test_stillness_window_waits_for_enough_data():
    cfg = ImuConfig()
    t_ns, gyro, acc = _imu_window(400.0, 1.0, 0, duration_s=2.0)
    win_ns = round(cfg.init_window_s * 1e9)
    assert imu.stillness_window(t_ns, win_ns - 10_000_000, cfg.init_window_s) is None
    w = imu.stillness_window(t_ns, int(1.6e9), cfg.init_window_s)
    assert t_ns[w][0] >= int(1.6e9) - win_ns and t_ns[w][-1] <= int(1.6e9)
    assert imu.stillness_test(t_ns[w], gyro[w], acc[w], cfg).still
    assert not imu.stillness_test(t_ns[w][:5], gyro[w][:5], acc[w][:5], cfg).still


def test_measured_noise_config_matches_the_discretization():
    cfg = ImuConfig(noise_discretization="dt")
    t_ns, gyro, acc = _imu_window(400.0, 10.0, 1)
    test = imu.stillness_test(t_ns, gyro, acc, cfg)
    m = imu.measured_noise_config(cfg, test)
    assert m.gyro_cov == pytest.approx(test.gyro_noise_rad_s_sqrt_hz**2)
    assert m.gyro_bias_cov == cfg.gyro_bias_cov
    m2 = imu.measured_noise_config(ImuConfig(noise_discretization="dt2"), test)
    # dt2 injects Q dt^2 per step: Q = per-sample variance = density^2 * rate
    assert m2.accel_cov == pytest.approx(np.var(acc - acc.mean(axis=0), axis=0).mean(), rel=0.1)


def test_measured_noise_is_the_white_noise_not_a_hands_tremor():
    """Held still by hand (9-11 Hz tremor of 0.03 rad/s and 0.3 m/s², 6x and 30x the BMI085's
    white noise per sample at 400 Hz), the measured densities are still the sensor's own."""
    cfg = ImuConfig()
    for seed in range(10):
        t_ns, gyro, acc = _imu_window(400.0, 1.0, seed, motion=_tremor)
        test = imu.stillness_test(t_ns, gyro, acc, cfg)
        assert test.still
        rel = 4.0 / np.sqrt(2 * test.noise_dof)
        assert test.gyro_noise_rad_s_sqrt_hz == pytest.approx(HILTI_GYRO_DENSITY, rel=rel)
        assert test.accel_noise_m_s2_sqrt_hz == pytest.approx(HILTI_ACCEL_DENSITY, rel=rel)


def test_white_noise_variance_dof_matches_its_spread():
    """The effective degrees of freedom describe the estimator's spread (Monte Carlo)."""
    r = np.random.default_rng(3)
    est = [imu.white_noise_variance(r.normal(size=(200, 3)))[0] for _ in range(4000)]
    _, dof = imu.white_noise_variance(np.zeros((200, 3)))
    assert np.mean(est) == pytest.approx(1.0, abs=0.01)
    assert np.var(est) == pytest.approx(2.0 / dof, rel=0.1)


def test_robust_white_noise_variance_dof_matches_its_spread():
    """The median estimator is unbiased for white noise and its effective degrees of freedom
    (derived from the second differences' correlations) describe its spread (Monte Carlo)."""
    r = np.random.default_rng(5)
    est = [imu.robust_white_noise_variance(r.normal(size=(400, 3)))[0] for _ in range(4000)]
    _, dof = imu.robust_white_noise_variance(np.zeros((400, 3)))
    assert np.mean(est) == pytest.approx(1.0, abs=0.01)
    assert np.var(est) == pytest.approx(2.0 / dof, rel=0.1)


def _jolts(t):
    """A slow walk with a footfall every 0.5 s: a 5 ms jolt of 20 m/s^2 and 1 rad/s."""
    gyro, acc = _slow_walk(t)
    hit = (np.mod(t, 0.5) < 0.005)[:, None]
    return gyro + 1.0 * hit, acc + 20.0 * hit


@pytest.mark.parametrize("noise_scale", [1.0, 10.0])
def test_moving_noise_measures_the_sensor_through_a_walk_and_its_jolts(noise_scale):
    """In a 1 s moving window (a slow walk, footfalls every 0.5 s), the median of the second
    differences gives the sensor's white-noise densities; their mean (the still window's
    estimator) reads the footfalls as several times the noise."""
    for seed in range(10):
        t_ns, gyro, acc = _imu_window(400.0, noise_scale, seed, duration_s=1.0, motion=_jolts)
        m = imu.moving_noise(t_ns, gyro, acc)
        rel = 4.0 / np.sqrt(2 * m.noise_dof)
        assert m.rate_hz == pytest.approx(400.0)
        assert m.gyro_noise_rad_s_sqrt_hz == pytest.approx(noise_scale * HILTI_GYRO_DENSITY,
                                                           rel=rel)
        assert m.accel_noise_m_s2_sqrt_hz == pytest.approx(noise_scale * HILTI_ACCEL_DENSITY,
                                                           rel=rel)
        mean_var, _ = imu.white_noise_variance(acc)
        assert np.sqrt(mean_var / 400.0) > 3.0 * noise_scale * HILTI_ACCEL_DENSITY
    assert imu.moving_noise(t_ns[:50], gyro[:50], acc[:50]) is None


@pytest.mark.parametrize("discretization", ["dt", "dt2"])
def test_at_least_config_raises_only_a_sensor_shown_noisier(discretization):
    """'at_least_config': a configured density stays unless the still window shows that sensor
    noisier beyond the false-alarm level; then the measured (true) density is used. The config
    here is the BMI085's gyro and 12x its accelerometer (as ``hilti2022``)."""
    rate = 400.0
    scale = 1.0 if discretization == "dt" else rate
    cfg = ImuConfig(noise_discretization=discretization,
                    gyro_cov=HILTI_GYRO_DENSITY**2 * scale,
                    accel_cov=(12 * HILTI_ACCEL_DENSITY) ** 2 * scale)
    for noise_scale, gyro_raised, accel_raised in ((1.0, False, False), (10.0, True, False),
                                                   (50.0, True, True)):
        kept = []
        for seed in range(200 if noise_scale == 1.0 else 10):
            t_ns, gyro, acc = _imu_window(rate, noise_scale, seed)
            test = imu.stillness_test(t_ns, gyro, acc, cfg)
            m = imu.measured_noise_config(cfg, test, only_if_noisier=True)
            kept.append((m.gyro_cov == cfg.gyro_cov, m.accel_cov == cfg.accel_cov))
            rel = 4.0 / np.sqrt(2 * test.noise_dof) * 2  # of a variance: twice the density's
            if gyro_raised:
                assert m.gyro_cov == pytest.approx((noise_scale * HILTI_GYRO_DENSITY) ** 2 * scale,
                                                   rel=rel)
            if accel_raised:
                assert m.accel_cov == pytest.approx(
                    (noise_scale * HILTI_ACCEL_DENSITY) ** 2 * scale, rel=rel)
            assert m.gyro_bias_cov == cfg.gyro_bias_cov
        kept = np.array(kept)
        for k, raised in enumerate((gyro_raised, accel_raised)):
            # at the true density the configured value stays (false raises near 1e-3)
            assert not kept[:, k].any() if raised else kept[:, k].mean() >= 0.98


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


@pytest.mark.parametrize("measured_accel", [True, False])
def test_block_covariance_propagation_matches_dense(measured_accel: bool) -> None:
    """The block propagation against the dense F P Fᵀ + G Q Gᵀ, for the measured step and for
    the motion model across an IMU gap (measured_accel False)."""
    gen = rng if measured_accel else np.random.default_rng(6)  # the module's stream as before
    for _ in range(5):
        x = _random_state(gen)
        gyro, acc, dt = gen.normal(size=3), gen.normal(size=3) * 3, 0.004
        F, G = imu.jacobians_fg(x.R, x.b_g, x.b_a, x.g, x.g_anchor, gyro, acc, dt,
                                measured_accel)
        A = gen.normal(size=(DIM, DIM))
        P = A @ A.T
        q = imu.process_noise(ImuConfig())
        dense = F @ P @ F.T + G @ np.diag(q) @ G.T
        fast = imu.propagate_covariance_fast(P, x.R, x.b_g, x.b_a, x.g, x.g_anchor, gyro, acc,
                                             dt, q, measured_accel)
        assert np.allclose(fast, dense, atol=1e-12)


@pytest.mark.parametrize("gap_s", [np.inf, 0.002])
def test_covariances_side_by_side_propagate_as_each_alone(gap_s: float) -> None:
    """Two covariances propagated together, (DIM, 2·DIM), give bit for bit what each gives
    alone, with and without a bridged IMU gap; the state and pose records are the same too."""
    rng = np.random.default_rng(21)  # its own draws: the module's stream feeds later tests
    x = _random_state(rng)
    A, B = rng.normal(size=(2, DIM, DIM))
    P1, P2 = A @ A.T, B @ B.T + np.eye(DIM)
    tau = np.array([-0.001, 0.0015, 0.004, 0.0065, 0.009])
    gyro = rng.normal(size=(5, 3))
    acc = rng.normal(size=(5, 3)) * 2
    q = imu.process_noise(ImuConfig())
    q_gap = np.full(12, 0.3)
    y1, out1, rec1 = imu.propagate(x, P1, tau, gyro, acc, 0.0, 0.012, q, "dt2", gap_s, q_gap)
    _, out2, _ = imu.propagate(x, P2, tau, gyro, acc, 0.0, 0.012, q, "dt2", gap_s, q_gap)
    y, both, rec = imu.propagate(x, np.hstack([P1, P2]), tau, gyro, acc, 0.0, 0.012, q, "dt2",
                                 gap_s, q_gap)
    assert both.shape == (DIM, 2 * DIM)
    np.testing.assert_array_equal(both[:, :DIM], out1)
    np.testing.assert_array_equal(both[:, DIM:], out2)
    assert not np.array_equal(out1, out2)
    np.testing.assert_array_equal(y.p, y1.p)
    np.testing.assert_array_equal(y.R, y1.R)
    np.testing.assert_array_equal(rec.p, rec1.p)


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


def test_rest_mean_variances_match_the_spread_of_window_means():
    """Batch-means variance of a window mean against the variance of many such means."""
    gen = np.random.default_rng(7)
    n, n_block, sig_g, sig_a = 200, 40, 2e-3, 2e-2
    est_g, est_a, means_g, means_a = [], [], [], []
    for _ in range(400):
        g = gen.normal(0.0, sig_g, (n, 3))
        a = gen.normal(0.0, sig_a, (n, 3)) + np.array([0.0, 0.0, 9.81])
        vg, va = imu.rest_mean_variances(g, a, n_block)
        est_g.append(vg)
        est_a.append(va)
        means_g.append(g.mean(axis=0))
        means_a.append(a.mean(axis=0))
    for est, means, sig in ((est_g, means_g, sig_g), (est_a, means_a, sig_a)):
        truth = np.var(np.asarray(means), axis=0).mean()
        assert np.mean(est) == pytest.approx(truth, rel=0.12)
        assert truth == pytest.approx(sig**2 / n, rel=0.12)
    # slow sway within the window (what the stillness test may accept) widens it
    t = np.arange(n) / 400.0
    sway = 0.05 * np.sin(2 * np.pi * 1.5 * t)[:, None] * np.ones(3)
    _, va_sway = imu.rest_mean_variances(g, a + sway, n_block)
    _, va_quiet = imu.rest_mean_variances(g, a, n_block)
    assert va_sway > 3 * va_quiet


def test_condition_on_rest_is_the_information_form_update_with_numerical_jacobian():
    """P after condition_on_rest = (P0^-1 + J^T Rn^-1 J)^-1, with J of the rest measurement
    z = [b_g; -R^T g + b_a] taken by central differences through the state's boxplus."""
    from adalio.lio.state import condition_on_rest, initial_covariance

    x = _random_state()
    P0 = initial_covariance(False) + np.diag(rng.uniform(0, 1e-4, DIM))

    def z(s: State) -> np.ndarray:
        return np.concatenate([s.b_g, -s.R.T @ s.g + s.b_a])

    J = np.zeros((6, DIM))
    h = 1e-6
    for i in range(DIM):
        e = np.zeros(DIM)
        e[i] = h
        J[:, i] = (z(x.boxplus(e)) - z(x.boxplus(-e))) / (2 * h)
    # the attitude is left out on purpose (the world frame is the IMU's at rest)
    J[:, 3:6] = 0.0
    var_g, var_a = 1e-8, 4e-6
    P1 = condition_on_rest(P0, x, var_g, var_a)
    Rn_inv = np.diag([1 / var_g] * 3 + [1 / var_a] * 3)
    expected = np.linalg.inv(np.linalg.inv(P0) + J.T @ Rn_inv @ J)
    assert np.allclose(P1, expected, rtol=1e-5, atol=1e-12)
    # what it means: the predicted specific force is as certain as the window mean, while the
    # accelerometer bias alone stays almost as uncertain as before
    S_a = J[3:6] @ P1 @ J[3:6].T
    assert np.all(np.diag(S_a) < 1.01 * var_a)
    assert np.all(np.diag(P1)[18:21] > 0.25 * np.diag(P0)[18:21])


def test_rest_velocity_update_is_the_kalman_update_of_a_zero_velocity_and_gates_motion():
    """rest_velocity_update against the textbook Kalman update with an explicit H (taken by
    central differences of the state's velocity through boxplus): the same correction and
    posterior; its NIS is the innovation's Mahalanobis length; a velocity many sigmas from
    zero is refused."""
    from adalio.lio.state import rest_velocity_covariance, rest_velocity_update

    x = _random_state()
    x.v = np.array([0.02, -0.01, 0.03])
    A = rng.normal(size=(DIM, DIM))
    P = A @ A.T * 1e-3 + np.eye(DIM) * 1e-5
    H = np.zeros((3, DIM))
    for i in range(DIM):
        e = np.zeros(DIM)
        e[i] = 1e-6
        H[:, i] = (x.boxplus(e).v - x.boxplus(-e).v) / 2e-6
    var_v = 2.5e-5
    S = H @ P @ H.T + var_v * np.eye(3)
    K = P @ H.T @ np.linalg.inv(S)
    out = rest_velocity_update(P, x.v, var_v, gate=1e9)
    assert out is not None
    dx, P1, nis = out
    assert np.allclose(dx, K @ (0.0 - x.v), rtol=1e-6, atol=1e-12)
    assert np.allclose(P1, P - K @ S @ K.T, rtol=1e-6, atol=1e-12)
    assert np.allclose(rest_velocity_covariance(P, var_v), P1, rtol=1e-9, atol=1e-15)
    assert nis == pytest.approx(float(x.v @ np.linalg.solve(S, x.v)), rel=1e-9)
    # the posterior velocity is nearer zero than both the prior and the measurement's spread
    assert np.linalg.norm(x.boxplus(dx).v) < np.linalg.norm(x.v)
    assert np.all(np.diag(P1)[12:15] < var_v)
    # a velocity the filter is sure of is no rest: refused at the gate
    assert rest_velocity_update(P, x.v, var_v, gate=0.5 * nis) is None
    assert rest_velocity_update(P, x.v, var_v, gate=2.0 * nis) is not None
    # the gate may ask another covariance (the discounted one): a wider velocity spread there
    # lets through what P alone refuses, and the correction is still P's
    wide = P.copy()
    wide[12:15, 12:15] += 10 * S
    out_wide = rest_velocity_update(P, x.v, var_v, gate=0.5 * nis, P_gate=wide)
    assert out_wide is not None
    S_wide = wide[12:15, 12:15] + var_v * np.eye(3)
    assert out_wide[2] == pytest.approx(float(x.v @ np.linalg.solve(S_wide, x.v)), rel=1e-9)
    assert np.allclose(out_wide[0], dx) and np.allclose(out_wide[1], P1)


def test_chi2_quantile_is_scipy_stats_to_the_bit():
    """The stillness test's chi-square quantile equals ``scipy.stats.chi2.ppf`` bit for bit
    (the window sizes it sees, and the false-alarm levels a config may give)."""
    from scipy.stats import chi2

    for q in (0.5, 0.9, 0.99, 0.997, 1 - 1e-6, 0.01):
        for dof in (*range(1, 40), 199, 200, 399, 1200, 2999):
            assert imu.chi2_quantile(q, dof) == float(chi2.ppf(q, dof)), (q, dof)


def test_a_run_starts_without_importing_scipy_stats(tmp_path):
    """A run through the initialization and its stillness tests imports no scipy.stats (0.35-0.5
    s of every run's start before session 73), in a fresh interpreter."""
    import subprocess
    import sys

    from adalio.sim import cached_sequence

    sim = cached_sequence("hall", seed=1, duration_s=6.0, columns=500)
    code = f"""
import sys
from adalio import Bag, ImuBatch, Odometry, Sequencer, load_config
cfg = load_config(config_file={str(sim.config_path)!r})
odom = Odometry(cfg)
n = 0
with Bag({str(sim.bag_path)!r}) as bag:
    for item in Sequencer(bag, cfg.sensor.lidar_topic, cfg.sensor.imu_topic, cfg.sensor):
        if isinstance(item, ImuBatch):
            odom.add_imu(item.t_ns, item.gyro_rad_s, item.accel_m_s2)
        else:
            n += odom.add_scan(item.points_lidar, item.t_ns) is not None
            if n >= 5:
                break
print(n, odom.init_report is not None, "scipy.stats" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True,
                         text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    n, initialized, imported = out.stdout.split()
    assert int(n) >= 5 and initialized == "True"
    assert imported == "False"
