"""The reported sigmas discount what the normals' noise fakes (filter.sigmas_discount_normal_noise)."""

from __future__ import annotations

import functools

import numpy as np

from adalio.config import load_config
from adalio.eval.files import read_scans_csv
from adalio.eval.metrics import sigma_consistency
from adalio.io.writers import read_tum
from adalio.lio.ieskf import real_information
from adalio.pipeline import run_bag
from adalio.sim import cached_sequence

SIGMAS = ("sigma_x_m", "sigma_y_m", "sigma_z_m", "sigma_roll_deg", "sigma_pitch_deg",
          "sigma_yaw_deg")


@functools.cache
def _height_evidence(lidar: str) -> tuple[np.ndarray, np.ndarray]:
    """``adalio.sim.evidence.height_evidence`` of the stairwell, seed 0, 512 columns (sweep start
    times in s, their height-evidence returns), ray-cast once for the tests that share it."""
    from adalio.sim.evidence import height_evidence

    t_s, counts, _, _ = height_evidence("stairs_garage", 0, 0.1, 1.0, lidar, 512)
    return t_s, counts


def test_real_information_stays_between_nothing_and_the_claim():
    """Random claims and fakes: the result is PSD, never above the claim (no direction gains
    information), equals the claim without a fake, and is zero where the fake covers it."""
    rng = np.random.default_rng(5)
    for _ in range(300):
        X = rng.normal(size=(6, 4))
        A = X @ X.T  # rank 4: two directions hold nothing
        Y = rng.normal(size=(6, 3))
        B = Y @ Y.T * rng.uniform(0.0, 3.0)
        J = real_information(A, B)
        assert np.linalg.eigvalsh(J).min() > -1e-9
        assert np.linalg.eigvalsh(A - J).min() > -1e-9
        null = np.linalg.svd(X.T)[2][4:]  # directions A holds nothing along
        np.testing.assert_allclose(null @ J @ null.T, 0.0, atol=1e-9)
        np.testing.assert_allclose(real_information(A, np.zeros((6, 6))), A, atol=1e-9)
        np.testing.assert_allclose(real_information(A, 2.0 * A), 0.0, atol=1e-9)


def _off_on(sim, out_dir, key: str, **settings):
    """The sequence run with ``filter.<key>`` off, then on (the other ``filter`` ``settings``
    alike in both); the two trajectories must be bit-identical. Returns the sigma columns off
    and on, their consistency against the ground truth off and on, and the scans' times. The
    extrinsic's own terms are left out of both (``sensor.extrinsic_*_sigma_*`` 0): the
    simulated extrinsic is exact, and these tests weigh the filter's and the map's terms."""
    runs = {}
    for on in (False, True):
        cfg = load_config(None, sim.config_path)
        cfg.sensor.extrinsic_rotation_sigma_deg = 0.0
        cfg.sensor.extrinsic_translation_sigma_m = 0.0
        setattr(cfg.filter, key, on)
        for name, value in settings.items():
            setattr(cfg.filter, name, value)
        out = out_dir / f"{key}_{on}"
        run_bag(sim.bag_path, cfg, out, progress=False)
        scans = read_scans_csv(out / "scans.csv")
        runs[on] = (read_tum(out / "trajectory.tum"), scans,
                    sigma_consistency(out / "trajectory.tum", sim.gt_path, scans))
    ((t_off, T_off), scans_off, cons_off), ((t_on, T_on), scans_on, cons_on) = runs[False], runs[True]
    np.testing.assert_array_equal(t_on, t_off)
    np.testing.assert_array_equal(T_on, T_off)
    return (np.column_stack([scans_off[c] for c in SIGMAS]),
            np.column_stack([scans_on[c] for c in SIGMAS]), cons_off, cons_on, scans_on["t_s"])


def test_spiral_sigmas_grow_where_the_walls_fake_height_and_the_trajectory_stays(tmp_path):
    """25 s of the simulated spiral (the shaft from 13 s): with and without the discount the
    trajectory is bit-identical, every reported height sigma from 5 s on is at least the
    filter's own (the discounted report starts at the anchor, the filter's covariance from its
    initial one, so they are not ordered at first: while the start rests both take the same
    zero velocity (``imu.zero_velocity_update``), and the report's height stays below the
    filter's until 1.2 s into the walk, which starts at 2.5 s), and from then on the
    errors against ground truth fall within 3σ in height more often and the mean NEES is lower,
    both for the filter's covariance alone (where it comes closer to 3) and with the map's
    added. The filter runs without its own errors in variables (on by default), which takes
    the same discount into the update: the report's discount is for a filter that follows
    those rows (``filter.errors_in_variables: false``)."""
    sim = cached_sequence("spiral", seed=0, duration_s=25.0, columns=512)
    for with_map in (False, True):
        s_off, s_on, cons_off, cons_on, t_s = _off_on(
            sim, tmp_path / f"map_{with_map}", "sigmas_discount_normal_noise",
            errors_in_variables=False, map_uncertainty=with_map)
        t0 = t_s[0]
        walk = t_s - t0 >= WALK_FROM_S
        assert np.all(s_on[walk, 2] >= s_off[walk, 2] * (1 - 1e-3) - 1e-9)
        within_on, nees_on = _walk_consistency(cons_on, t0)
        within_off, nees_off = _walk_consistency(cons_off, t0)
        print(f"map {with_map}: z within 3 sigma {within_off[2]:.3f} -> {within_on[2]:.3f}, "
              f"mean NEES {nees_off:.2f} -> {nees_on:.2f}")
        assert within_on[2] > within_off[2], (within_on, within_off)
        assert nees_on < nees_off
        if not with_map:  # 3 is honest
            assert abs(np.log(nees_on / 3)) < abs(np.log(nees_off / 3))
        assert s_on[-1, 2] > 2.0 * s_off[-1, 2]  # height, at the end, in the shaft


WALK_FROM_S = 5.0
"""The consistency is judged from here on (s after the first scan): at the start's rest the
report's sigmas are the zero velocity's (0.4 mm after the anchor) while the first registration
after the anchor errs by 3-6 mm in height with or without it (spiral seed 0), so one scan's
NEES (549) would outweigh the 25 s walk's."""


def _walk_consistency(cons, t0_s: float) -> tuple[np.ndarray, float]:
    """(share within 3 sigma per axis, mean NEES) of the scans from ``WALK_FROM_S`` on."""
    m = cons.t_s - t0_s >= WALK_FROM_S
    e, s = cons.errors_world_m[m], cons.sigma_world_m[m]
    return (np.abs(e) <= 3 * s).mean(axis=0), float(np.mean(np.sum((e / s) ** 2, axis=1)))


def test_anchored_covariance_matches_monte_carlo():
    """The covariance at the anchor against sampled errors: the anchor defines the world, so a
    sampled error keeps its roll, pitch, velocity and biases and loses its position and its
    rotation about the world vertical (world rotation ``R δθ``, body-frame ``δθ``)."""
    from scipy.spatial.transform import Rotation

    from adalio.lio.state import DIM, P_, TH, anchored_covariance, world_sigmas

    rng = np.random.default_rng(11)
    A = rng.normal(size=(DIM, DIM)) * 0.03
    P = A @ A.T + np.eye(DIM) * 1e-4
    R = Rotation.from_euler("zyx", [0.7, 0.3, -0.5]).as_matrix()
    d = rng.multivariate_normal(np.zeros(DIM), P, size=60000)
    w = d[:, TH] @ R.T  # world-frame rotation errors
    w[:, 2] = 0.0
    d[:, TH] = w @ R
    d[:, P_] = 0.0
    Pa = anchored_covariance(R, P)
    sd = np.sqrt(np.diag(P))
    np.testing.assert_allclose(Pa / np.outer(sd, sd), np.cov(d.T) / np.outer(sd, sd),
                               atol=0.02)  # sampling noise ~0.004
    sig_p, sig_th_deg = world_sigmas(R, Pa)
    np.testing.assert_allclose(sig_p, 0.0, atol=1e-12)
    assert sig_th_deg[2] < 1e-6
    assert sig_th_deg[:2].min() > 0.5 * world_sigmas(R, P)[1][:2].min()


def test_sigmas_start_at_the_anchor_not_at_the_initial_covariance(tmp_path):
    """The first 8 s of a simulated stairwell (seed 1: the floor is in view until the first
    flight at 7 s, the walls hold the rest). The pose of the filter's first scan defines the
    world, so the reported height sigma there must come from what happened since, not from the
    filter's initial 1 m: against ground truth the height errors stay within 3σ and the sigma
    stays within ten times the largest height error. (Before the anchor was applied, this
    stretch reported σ_z of 0.3-0.6 m against errors of 2-4 cm.)"""
    sim = cached_sequence("stairs_garage", seed=1, duration_s=8.0, columns=512)
    cfg = load_config(None, sim.config_path)
    out = tmp_path / "run"
    run_bag(sim.bag_path, cfg, out, progress=False)
    scans = read_scans_csv(out / "scans.csv")
    cons = sigma_consistency(out / "trajectory.tum", sim.gt_path, scans)
    err_z = np.abs(cons.errors_world_m[:, 2])
    sig_z = cons.sigma_world_m[:, 2]
    assert cons.within_3sigma[2] >= 0.9, cons.within_3sigma
    assert np.median(sig_z) < 10.0 * max(err_z.max(), 0.005), (np.median(sig_z), err_z.max())


def test_height_blind_against_the_generalized_eigenproblem():
    """``height_blind`` against scipy's generalized eigensolver (``fake v = m claimed v``,
    ``vᵀ claimed v = 1``, so ``claimed = Σ (claimed v)(claimed v)ᵀ``): the directions with
    ``m >= 1`` hold more than half of the claim's height entry ``eᵀ claimed e``, ``e = [up,
    0]``, along the world's z and along a random up. And the two cases it is for:
    a floor in view (height claimed far above its fake) and walls only (their fitted normals'
    noise fakes more height than they claim)."""
    from scipy.linalg import eigh

    from adalio.lio.ieskf import height_blind

    rng = np.random.default_rng(11)
    checked = 0
    for _ in range(400):
        X = rng.normal(size=(6, 6)) * rng.uniform(0.1, 3.0, size=6)
        A = X @ X.T
        Y = rng.normal(size=(6, 6)) * rng.uniform(0.0, 3.0, size=6)
        F = Y @ Y.T
        m, V = eigh(F, A)
        up = rng.normal(size=3)
        up /= np.linalg.norm(up)
        # the world's z (the default), and any up (the world is the IMU frame at the start)
        for e, given in ((np.eye(6)[2], None), (np.r_[up, np.zeros(3)], up)):
            part = (e @ A @ V) ** 2
            share = part[m >= 1.0].sum() / part.sum()
            if abs(share - 0.5) < 1e-6:
                continue
            assert height_blind(A, F, given) == (share > 0.5)
            checked += 1
    assert checked > 790
    floor = np.diag([1e4, 1e4, 1e5, 1e3, 1e3, 1e3])
    assert not height_blind(floor, np.diag([1e2, 1e2, 4e4, 10.0, 10.0, 10.0]))
    walls = np.diag([1e4, 1e4, 5e3, 1e3, 1e3, 1e3])
    assert height_blind(walls, np.diag([1e2, 1e2, 4e4, 10.0, 10.0, 10.0]))


def test_height_blind_takes_the_height_along_the_worlds_up():
    """The world is the IMU frame at the start, so its up is wherever the IMU's mounting puts
    it: a scene turned with the world (both information matrices as ``T A Tᵀ``, ``T = diag(Q,
    Q)``) gives the same answer along the turned up, where the world's z would not: walls
    turned onto their side claim their height along y. (Any up against scipy's generalized
    eigensolver: the test above.)"""
    from scipy.spatial.transform import Rotation

    from adalio.lio.ieskf import height_blind

    walls = np.diag([1e4, 1e4, 5e3, 1e3, 1e3, 1e3])
    fake = np.diag([1e2, 1e2, 4e4, 10.0, 10.0, 10.0])
    Q = Rotation.from_euler("x", 90, degrees=True).as_matrix()  # the up, z, turned to -y
    T = np.kron(np.eye(2), Q)
    side_walls, side_fake = T @ walls @ T.T, T @ fake @ T.T
    assert height_blind(side_walls, side_fake, Q @ np.array([0.0, 0.0, 1.0]))
    assert not height_blind(side_walls, side_fake)  # the world's z is horizontal there


def test_without_direction_is_the_marginal_information():
    """``J`` with the height marginalised out holds nothing along it, and on the other five
    coordinates it is the marginal information ``((J⁻¹)_rr)⁻¹`` (brute force)."""
    from adalio.lio.ieskf import without_direction

    rng = np.random.default_rng(12)
    e = np.eye(6)[2]
    rest = [0, 1, 3, 4, 5]
    for _ in range(100):
        X = rng.normal(size=(6, 8))
        J = X @ X.T
        Jm = without_direction(J, e)
        np.testing.assert_allclose(Jm @ e, 0.0, atol=1e-9 * np.abs(J).max())
        marginal = np.linalg.inv(np.linalg.inv(J)[np.ix_(rest, rest)])
        np.testing.assert_allclose(Jm[np.ix_(rest, rest)], marginal, rtol=1e-8,
                                   atol=1e-9 * np.abs(J).max())
    np.testing.assert_array_equal(without_direction(np.diag([1.0, 1, 0, 1, 1, 1]), e),
                                  np.diag([1.0, 1, 0, 1, 1, 1]))


def test_height_blind_sigmas_leave_the_trajectory_and_grow_on_the_flights(tmp_path):
    """20 s of the simulated stairwell (a still start on the landing, then down the flights,
    the XT-32's ±16° seeing no tread for stretches): with ``filter.sigmas_height_blind`` (on by
    default) the trajectory is bit-identical, no reported sigma is smaller (the map's term off,
    so the sigmas are the covariance's own plus the deskew term), and the height sigma at the
    end is larger, with the height error within 3σ on at least as many scans."""
    sim = cached_sequence("stairs_garage", seed=1, duration_s=20.0, columns=512)
    s_off, s_on, cons_off, cons_on, _ = _off_on(sim, tmp_path, "sigmas_height_blind",
                                                map_uncertainty=False)
    assert np.all(s_on >= s_off * (1 - 1e-6) - 1e-12)
    print(f"sigma_z at the end {s_off[-1, 2]:.3f} -> {s_on[-1, 2]:.3f} m; z within 3 sigma "
          f"{cons_off.within_3sigma[2]:.3f} -> {cons_on.within_3sigma[2]:.3f}")
    assert s_on[-1, 2] > 2.0 * s_off[-1, 2]
    assert cons_on.within_3sigma[2] >= cons_off.within_3sigma[2]


def test_height_blind_column_flags_every_sweep_without_height_evidence(tmp_path):
    """40 s of the simulated stairwell, seed 0 (the landing, the flights, then the garage floor):
    ``scans.csv``'s ``height_blind`` against the ray-cast truth (``adalio.sim.evidence``: a
    noise-free sweep's returns on horizontal faces beyond 1 m). Every sweep with fewer than 20
    such returns is flagged, so the sigmas take no height from it; of the sweeps with 300 or
    more (the garage floor in view), at most one in ten is. In between the flag is
    conservative (it also takes sweeps whose few treads the normals' noise outweighs)."""
    from adalio.sim.generate import START_NS

    sim = cached_sequence("stairs_garage", seed=0, duration_s=40.0, columns=512)
    out = tmp_path / "run"
    run_bag(sim.bag_path, load_config(None, sim.config_path), out, progress=False)
    scans = read_scans_csv(out / "scans.csv")
    t_sweep_s = np.asarray(scans["t_s"], dtype=np.float64) - START_NS * 1e-9 - 0.1
    flagged = np.asarray(scans["height_blind"]) == 1
    t_s, counts = _height_evidence("xt32")
    k = np.round(t_sweep_s / 0.1).astype(int)
    ok = (k >= 5) & (k < len(t_s)) & (np.abs(t_sweep_s - 0.1 * k) < 0.01)  # from 0.5 s on
    flagged, evidence = flagged[ok], counts[k[ok]]
    none, floor = evidence < 20, evidence >= 300
    print(f"{ok.sum()} sweeps: without evidence {none.sum()}, flagged {flagged[none].mean():.3f}; "
          f"floor in view {floor.sum()}, flagged {flagged[floor].mean():.3f}; "
          f"in between {flagged[~none & ~floor].mean():.3f}")
    assert none.sum() > 100 and floor.sum() > 20
    assert flagged[none].all()
    assert flagged[floor].mean() <= 0.1


def test_a_wide_field_of_view_gives_the_flights_their_height(tmp_path):
    """The same 40 s of the stairwell (seed 0) seen by an OS0-128-like head (``simulate --lidar
    ouster128``: ±45°) instead of the XT-32 (±16°). The ray-cast truth (``adalio.sim.evidence``)
    puts 300 or more returns on horizontal faces in every one of its sweeps, where more than
    half of the XT-32's have fewer than 20. So the height is the LiDAR's, not the IMU's: few
    of its scans are flagged height-blind, and its trajectory is an order of magnitude closer
    to the truth. This is the field-of-view account of the stairwell (README, *Where adalio
    stands*) measured on one walk."""
    from adalio.eval.metrics import ate

    runs = {}
    for lidar in ("xt32", "ouster128"):
        t_s, counts = _height_evidence(lidar)
        walk = (t_s >= 0.5) & (t_s < 39.9)
        sim = cached_sequence("stairs_garage", seed=0, duration_s=40.0, columns=512,
                              lidar=lidar)
        out = tmp_path / lidar
        res = run_bag(sim.bag_path, load_config(None, sim.config_path), out, progress=False)
        flagged = np.asarray(read_scans_csv(out / "scans.csv")["height_blind"]) == 1
        runs[lidar] = (counts[walk], flagged.mean(), float(ate(res.trajectory_path,
                                                               sim.gt_path)["rmse_m"]))
        print(f"{lidar}: sweeps with < 20 height returns {np.mean(counts[walk] < 20):.2f}, "
              f"flagged {flagged.mean():.3f}, ATE {runs[lidar][2] * 100:.2f} cm")
    (narrow, flagged_narrow, ate_narrow), (wide, flagged_wide, ate_wide) = runs.values()
    assert np.mean(narrow < 20) > 0.5  # measured 0.55
    assert np.all(wide >= 300)
    assert flagged_narrow > 0.8  # measured 0.87
    assert flagged_wide < 0.25  # measured 0.12
    assert ate_wide < 0.02 and ate_wide < 0.1 * ate_narrow  # measured 0.18 cm against 19.1 cm
