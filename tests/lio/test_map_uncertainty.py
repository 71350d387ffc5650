"""Map uncertainty (lio/map_uncertainty.py): the lever-arm transport against Monte Carlo rigid
perturbations of a map, cell ownership and the matched-point average against brute force, the
correlated combination against sampled correlated errors and a chain of map extensions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from adalio.lio.map_uncertainty import MapProvenance, transport, world_covariance


def _random_covariance(rng: np.random.Generator, pos_m: float, rot_rad: float) -> np.ndarray:
    A = rng.normal(size=(6, 6)) * np.r_[[pos_m] * 3, [rot_rad] * 3][:, None]
    return A @ A.T / 6


def test_transport_matches_monte_carlo_of_a_rigidly_displaced_map():
    """A map placed by a pose with error (δp, δφ) ~ N(0, W) moves as x -> p_j + δp +
    Exp(δφ)(x - p_j); a pose at p_k that follows it has the error transport(W, p_k - p_j)."""
    rng = np.random.default_rng(3)
    W = _random_covariance(rng, 0.02, np.radians(0.5))
    p_j = np.array([1.0, -2.0, 0.5])
    p_k = np.array([7.0, 3.0, -4.0])
    R_k = Rotation.from_euler("zyx", [40, -10, 5], degrees=True).as_matrix()
    n = 40000
    e = rng.multivariate_normal(np.zeros(6), W, size=n)
    R_d = Rotation.from_rotvec(e[:, 3:]).as_matrix()
    p_moved = p_j + e[:, :3] + np.einsum("nij,j->ni", R_d, p_k - p_j)
    R_moved = R_d @ R_k
    dphi = Rotation.from_matrix(R_moved @ R_k.T).as_rotvec()  # world-frame small rotation
    err = np.column_stack([p_moved - p_k, dphi])
    C = np.cov(err.T)
    expected = transport(W, p_k - p_j)
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
    np.testing.assert_allclose(C / scale, expected / scale, atol=0.03)
    # the lever arm matters: 10 m at 0.5° is far more than the 2 cm position term
    assert expected[0, 0] > 5 * W[0, 0]


def test_owners_are_the_first_scan_to_fill_each_cell():
    rng = np.random.default_rng(5)
    prov = MapProvenance(cell_m=0.5)
    scans = [rng.uniform(-3, 3, size=(300, 3)) + 0.7 * k for k in range(6)]
    first: dict[tuple[int, int, int], int] = {}
    for k, pts in enumerate(scans):
        assert prov.add_scan(np.zeros(3), np.eye(6) * k, pts) == k
        for cell in map(tuple, np.floor(pts / 0.5).astype(int)):
            first.setdefault(cell, k)
    queries = np.vstack([rng.uniform(-4, 8, size=(2000, 3)), *scans])
    expected = [first.get(tuple(c), -1) for c in np.floor(queries / 0.5).astype(int)]
    np.testing.assert_array_equal(prov.owners(queries), expected)
    assert len(prov) == len(first)
    assert (prov.owners(queries) == -1).any() and (prov.owners(queries) == 5).any()


def test_map_covariance_is_the_matched_points_mean_of_transported_owner_covariances():
    rng = np.random.default_rng(8)
    prov = MapProvenance(cell_m=1.0)
    positions = [rng.normal(size=3) * 4 for _ in range(4)]
    covs = [_random_covariance(rng, 0.01 * (k + 1), 0.002 * (k + 1)) for k in range(4)]
    blocks = [np.array([[4.0 * k + 0.5, 0.5, 0.5]]) + rng.uniform(0, 3, size=(50, 3))
              for k in range(4)]
    for p, W, pts in zip(positions, covs, blocks, strict=True):
        prov.add_scan(p, W, pts)
    matched = np.vstack([blocks[0][:5], blocks[2][:30], blocks[3][:1],
                         np.array([[100.0, 100.0, 100.0]])])  # the last one owns no cell
    p_now = np.array([2.0, 1.0, -1.0])
    owners = prov.owners(matched)
    brute = np.mean([transport(covs[j], p_now - positions[j]) for j in owners if j >= 0], axis=0)
    np.testing.assert_allclose(prov.map_covariance(p_now, matched), brute, rtol=1e-12,
                               atol=1e-18)
    # rows without a neighbour (NaN) are left out, wherever they sit
    with_nan = np.insert(matched, [0, 7, len(matched)], np.nan, axis=0)
    np.testing.assert_array_equal(prov.map_covariance(p_now, with_nan),
                                  prov.map_covariance(p_now, matched))
    np.testing.assert_array_equal(prov.map_covariance(p_now, matched[-1:]), np.zeros((6, 6)))


def test_world_covariance_bounds_the_sum_of_two_errors_whatever_their_correlation():
    """For joint covariances of (a, b) with random cross-covariances, from none to (nearly)
    full, the sampled covariance of a + b stays below the bound in the PSD order, while the
    independent sum is exceeded when the two errors are positively correlated; the bound is
    exact when b is a positive multiple of a."""
    rng = np.random.default_rng(11)
    n = 200000
    exceeded = 0
    for trial in range(12):
        A_half = rng.normal(size=(6, 6)) * np.r_[[0.02] * 3, [0.004] * 3][:, None]
        B_half = rng.normal(size=(6, 6)) * np.r_[[0.05] * 3, [0.002] * 3][:, None]
        shared = trial / 11  # 0: independent ... 1: a and b driven by one noise
        u = rng.normal(size=(n, 6))
        v = np.sqrt(shared) * u + np.sqrt(1 - shared) * rng.normal(size=(n, 6))
        a, b = u @ A_half.T, v @ B_half.T
        W_rel, W_map = np.cov(a.T), np.cov(b.T)
        C = np.cov((a + b).T)
        bound = world_covariance(W_rel, W_map, correlated=True)
        assert np.linalg.eigvalsh(bound - C).min() > -1e-3 * np.linalg.eigvalsh(C).max()
        independent = world_covariance(W_rel, W_map, correlated=False)
        np.testing.assert_allclose(independent, W_rel + W_map)
        exceeded += np.trace(C[:3, :3]) > 1.05 * np.trace(independent[:3, :3])
    assert exceeded >= 4
    W = np.cov(rng.normal(size=(1000, 6)).T)
    np.testing.assert_allclose(world_covariance(W, 4.0 * W, correlated=True), 9.0 * W,
                               rtol=1e-12)
    np.testing.assert_array_equal(world_covariance(W, np.zeros((6, 6)), correlated=True), W)


def test_world_covariance_inflates_no_axis_without_limit():
    """Over covariances whose axes differ by up to eight orders of magnitude (a map of rotation
    and hardly any position, as near the anchor), no axis of the bound exceeds 12 times that
    axis's own smallest bound ``(sqrt(W_rel,aa) + sqrt(W_map,aa))²``; choosing α from the
    position traces alone (before session 45) exceeded it by orders of magnitude there."""
    rng = np.random.default_rng(17)
    worst, worst_old = 0.0, 0.0
    for _ in range(300):
        W_rel = _random_covariance(rng, 10.0 ** rng.uniform(-5, -1), 10.0 ** rng.uniform(-5, -1))
        W_map = _random_covariance(rng, 10.0 ** rng.uniform(-7, -1), 10.0 ** rng.uniform(-5, -1))
        own = (np.sqrt(np.diag(W_rel)) + np.sqrt(np.diag(W_map))) ** 2
        W = world_covariance(W_rel, W_map, correlated=True)
        worst = max(worst, np.max(np.diag(W) / own))
        alpha = np.sqrt(np.trace(W_map[:3, :3]) / np.trace(W_rel[:3, :3]))
        old = (1 + alpha) * W_rel + (1 + 1 / alpha) * W_map
        worst_old = max(worst_old, np.max(np.diag(old) / own))
    assert 1.0 <= worst <= 12.0
    assert worst_old > 100.0


def test_a_chain_of_map_extensions_adds_standard_deviations_not_variances():
    """Scan k registers against the cells scan k-1 filled (no lever arm) with its own position
    covariance σ² I: with the correlated combination the k-th scan's sigma is (k+1) σ, as for a
    bias repeated at every extension; as independent errors it is sqrt(k+1) σ."""
    sigma = 0.01
    W_rel = np.diag([sigma**2] * 3 + [0.0] * 3)
    for correlated, expected in ((True, lambda k: (k + 1) * sigma),
                                 (False, lambda k: np.sqrt(k + 1) * sigma)):
        prov = MapProvenance(cell_m=1.0)
        block = np.array([[0.5, 0.5, 0.5]])
        W_map = np.zeros((6, 6))
        for k in range(8):
            if k:
                W_map = prov.map_covariance(np.zeros(3), block + [3.0 * (k - 1), 0, 0])
            W = world_covariance(W_rel, W_map, correlated)
            np.testing.assert_allclose(np.sqrt(np.diag(W)[:3]), expected(k), rtol=1e-12)
            prov.add_scan(np.zeros(3), W, block + [3.0 * k, 0, 0])


def test_odometry_sigmas_add_the_map_and_leave_the_trajectory_alone(tmp_path):
    """On a simulated corridor walk, ``filter.map_uncertainty`` changes only the reported sigmas:
    the trajectory is bit-identical, every sigma is at least the filter's own, the filter's first
    scan (which defines the world) has none, and by the end, with the map extended along the walk,
    they are larger than the filter's alone; the errors against ground truth fall within 3σ
    more often."""
    from adalio.config import load_config
    from adalio.eval.files import read_scans_csv
    from adalio.eval.metrics import sigma_consistency
    from adalio.io.writers import read_tum
    from adalio.pipeline import run_bag
    from adalio.sim import cached_sequence

    sim = cached_sequence("corridor", seed=0, duration_s=4.0, columns=512)
    runs = {}
    for on in (False, True):
        cfg = load_config(None, sim.config_path)
        cfg.filter.map_uncertainty = on
        out = tmp_path / f"map_uncertainty_{on}"
        run_bag(sim.bag_path, cfg, out, progress=False)
        runs[on] = (read_tum(out / "trajectory.tum"), read_scans_csv(out / "scans.csv"),
                    sigma_consistency(out / "trajectory.tum", sim.gt_path,
                                      read_scans_csv(out / "scans.csv")))
    (t_off, T_off), scans_off, cons_off = runs[False]
    (t_on, T_on), scans_on, cons_on = runs[True]
    np.testing.assert_array_equal(t_on, t_off)
    np.testing.assert_array_equal(T_on, T_off)
    cols = ("sigma_x_m", "sigma_y_m", "sigma_z_m", "sigma_roll_deg", "sigma_pitch_deg",
            "sigma_yaw_deg")
    s_off = np.column_stack([scans_off[c] for c in cols])
    s_on = np.column_stack([scans_on[c] for c in cols])
    assert len(s_on) > 30
    anchor = int(np.argmax(scans_on["backfill"] == 0))  # after the backfilled first scans
    np.testing.assert_array_equal(s_on[anchor], 0.0)
    assert np.all(s_on >= s_off * (1 - 1e-9))
    # 4 s into the walk the map's share of the position variance is about a quarter
    var_on, var_off = np.sum(s_on[-1, :3] ** 2), np.sum(s_off[-1, :3] ** 2)
    assert var_on > 1.15 * var_off, (s_on[-1], s_off[-1])
    assert cons_on.mean_nees < cons_off.mean_nees


def test_deskew_covariance_against_monte_carlo():
    """The rotation a sweep's undistortion takes from the gyro's white noise, brute force: 400 Hz
    gyro samples of density² q, each of 200 points evenly over 0.1 s moved to the sweep's end by
    the noise integrated from its time to the end, the registration's rotation their mean. Its
    variance per axis over many sweeps is ``deskew_covariance``'s, the axes uncorrelated, no
    position."""
    from adalio.lio.map_uncertainty import deskew_covariance

    rng = np.random.default_rng(3)
    q, span, rate = 3.6e-6, 0.1, 400.0
    n_samples = int(span * rate)
    t_pts = np.linspace(0.0, span, 200, endpoint=False)  # time before the end
    # sample j covers [j, j+1) / rate before the end; a point integrates the samples it has passed
    steps = rng.normal(0.0, np.sqrt(q * rate), (20000, n_samples, 3)) / rate
    cum = np.concatenate([np.zeros((20000, 1, 3)), np.cumsum(steps, axis=1)], axis=1)
    k = t_pts * rate
    lo = np.floor(k).astype(int)
    frac = (k - lo)[None, :, None]
    walk = cum[:, lo] * (1 - frac) + cum[:, np.minimum(lo + 1, n_samples)] * frac
    mean_rot = walk.mean(axis=1)  # (trials, 3)
    W = deskew_covariance(q, span)
    np.testing.assert_array_equal(W[:3], 0.0)
    np.testing.assert_allclose(np.cov(mean_rot.T), W[3:, 3:], rtol=0.05, atol=0.03 * W[3, 3])
    assert not deskew_covariance(0.0, span).any() and not deskew_covariance(q, 0.0).any()


def _deskew_off_on(tmp_path, **imu_settings):
    """The simulated 4 s corridor run twice, the map's term off (so the sigmas' sum is plain),
    with ``imu_settings`` and ``filter.sigmas_deskew_noise`` off, then on: (the estimates off,
    the estimates on, the second run's initialization report)."""
    from adalio.config import load_config
    from adalio.pipeline import run_bag
    from adalio.sim import cached_sequence

    sim = cached_sequence("corridor", seed=0, duration_s=4.0, columns=512)
    runs = []
    for on in (False, True):
        cfg = load_config(None, sim.config_path)
        for key, value in imu_settings.items():
            setattr(cfg.imu, key, value)
        cfg.filter.map_uncertainty = False
        cfg.filter.sigmas_deskew_noise = on
        ests = []
        res = run_bag(sim.bag_path, cfg, tmp_path / f"deskew_{on}", progress=False,
                      on_estimate=ests.append)
        runs.append((ests, res.init_report))
    (off, _), (on, report) = runs
    return off, on, report


def _attitude_variance(e) -> np.ndarray:
    return np.radians(np.asarray(e.stats.sigma_rot_world_deg)) ** 2


def _extra_attitude_variance(off, on) -> np.ndarray:
    """Per scan whose attitude sigma off is not zero: the attitude variance (rad²) on adds."""
    return np.array([_attitude_variance(b) - _attitude_variance(a)
                     for a, b in zip(off, on, strict=True) if np.any(_attitude_variance(a) > 0)])


@pytest.mark.parametrize("form", ["dt", "dt2"])
def test_odometry_sigmas_hold_the_deskew_noise_and_leave_the_trajectory_alone(tmp_path, form):
    """``filter.sigmas_deskew_noise`` adds ``q T / 3`` per axis to every reported attitude
    variance (the map's term off, so the sum is plain; the gyro noise as configured: in the
    'dt2' form a per-sample value, ``q`` times the 400 Hz IMU's rate) and changes nothing else:
    the trajectory is bit-identical and the anchor has no sigma."""
    q = 3.6e-6  # rad²/s, the x10 BMI085's
    off, on, _ = _deskew_off_on(tmp_path, noise_source="config", noise_discretization=form,
                                gyro_cov=q if form == "dt" else q * 400.0)
    assert len(on) == len(off) > 30
    for a, b in zip(off, on, strict=True):
        assert a.t_ns == b.t_ns
        np.testing.assert_array_equal(a.T_world_imu, b.T_world_imu)
    extra = _extra_attitude_variance(off, on)
    assert len(extra) > 30
    assert any(not np.any(_attitude_variance(b)) for b in on)  # the anchor
    # the simulated sweeps' points span 0.1 s less one column
    assert np.all(extra > q * 0.099 / 3 * (1 - 1e-6)) and np.all(extra < q * 0.1 / 3 * (1 + 1e-6))


def test_deskew_noise_is_the_measured_gyro_noise_not_a_generic_config(tmp_path):
    """With a generic process noise (FAST-LIO's gyro_cov 0.1 in the dt2 form, the ``ouster``
    preset's) and the default ``imu.noise_source: at_least_config``, the term takes the gyro
    density the still start measured, which is the simulated BMI085's (1.9e-4 rad/s/sqrt(Hz)),
    not the configured floor (80 times larger in sigma)."""
    off, on, report = _deskew_off_on(tmp_path, noise_discretization="dt2", gyro_cov=0.1,
                                     accel_cov=0.1)
    q = report.gyro_noise_rad_s_sqrt_hz ** 2
    assert 0.5 * 1.9e-4**2 < q < 2.0 * 1.9e-4**2
    extra = _extra_attitude_variance(off, on)
    assert len(extra) > 30
    np.testing.assert_allclose(extra, q * 0.0995 / 3, rtol=0.01)
