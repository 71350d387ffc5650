"""The extrinsic rotation's share of the reported sigmas against brute force: poses composed
exactly through a turned map (Monte Carlo), and the Bayesian posterior in its other form."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from adalio.lio.extrinsic_sigma import (
    error_second_moment,
    extrinsic_rotation_covariance,
    extrinsic_translation_covariance,
    posterior,
    prior_scale,
)


def _poses(rng, n):
    R = Rotation.random(n, random_state=rng).as_matrix()
    p = rng.uniform(-20.0, 20.0, size=(n, 3))
    return R, p


def test_the_covariance_is_that_of_poses_through_a_turned_map():
    """Draw the extrinsic's error, turn the map about the first pose by R0 theta and compose
    each pose exactly (the LiDAR's pose follows the map, the IMU's is it through the used
    rotation); the errors' covariance is G M G^T to Monte Carlo precision."""
    rng = np.random.default_rng(0)
    R_all, p_all = _poses(rng, 4)
    R0, p0 = R_all[0], p_all[0]
    sigma = np.radians([0.3, 0.1, 0.2])
    A = Rotation.random(random_state=1).as_matrix()
    M = A @ np.diag(sigma**2) @ A.T
    thetas = rng.multivariate_normal(np.zeros(3), M, size=20000)
    for R, p in zip(R_all[1:], p_all[1:], strict=True):
        errs = np.empty((len(thetas), 6))
        for i, th in enumerate(thetas):
            turn = Rotation.from_rotvec(R0 @ th).as_matrix()  # the map turned about p0
            p_est = p0 + turn @ (p - p0)
            R_est = turn @ R @ Rotation.from_rotvec(-th).as_matrix()
            errs[i, :3] = p_est - p
            errs[i, 3:] = Rotation.from_matrix(R_est @ R.T).as_rotvec()
        W = extrinsic_rotation_covariance(M, R0, R, p - p0)
        emp = np.cov(errs.T)
        scale = np.sqrt(np.outer(np.diag(W), np.diag(W)))
        assert np.max(np.abs(emp - W) / scale) < 0.05, (emp, W)


def test_the_translation_covariance_is_that_of_poses_through_a_shifted_map():
    """A lever arm off by delta: the first scan's points land shifted by R0 delta, the LiDAR's
    later positions follow that map, and the IMU's are the LiDAR's less the used lever arm
    turned by the attitude; their errors' covariance is G M G^T, exactly (it is linear)."""
    rng = np.random.default_rng(5)
    R_all, p_all = _poses(rng, 4)
    R0 = R_all[0]
    t_true = np.array([-0.01, -0.0085, 0.055])
    M = np.diag([0.02, 0.01, 0.005]) ** 2
    deltas = rng.multivariate_normal(np.zeros(3), M, size=20000)
    for R, p in zip(R_all[1:], p_all[1:], strict=True):
        lidar_true = p + R @ t_true
        lidar_est = lidar_true + deltas @ R0.T  # the map, and the LiDAR on it, shifted by R0 delta
        imu_est = lidar_est - (t_true + deltas) @ R.T
        W = extrinsic_translation_covariance(M, R0, R)
        np.testing.assert_allclose(np.cov((imu_est - p).T), W[:3, :3],
                                   atol=0.05 * np.max(np.diag(W[:3, :3])))
        assert not W[3:].any()


def test_the_first_pose_has_none():
    R = Rotation.random(random_state=2).as_matrix()
    W = extrinsic_rotation_covariance(np.eye(3) * 1e-4, R, R, np.zeros(3))
    assert np.allclose(W, 0.0)


def test_the_second_moment_is_the_posterior_variance_plus_its_mean_squared():
    rng = np.random.default_rng(3)
    s = np.radians(0.1)
    B = rng.normal(size=(3, 3))
    C = B @ B.T * np.radians(0.08) ** 2
    e = np.radians([0.2, -0.1, 0.05])
    M = error_second_moment(s, e, C)
    P = np.eye(3) * s**2 * prior_scale(s**2, e, C)  # the gain form of the same posterior
    K = P @ np.linalg.inv(P + C)
    m = K @ e
    V = P - K @ P
    np.testing.assert_allclose(M, V + np.outer(m, m), atol=1e-14)
    # by sampling: the prior's thetas, weighted by the estimate's likelihood
    th = rng.normal(scale=np.sqrt(P[0, 0]), size=(400000, 3))
    r = e - th
    w = np.exp(-0.5 * np.einsum("ni,ij,nj->n", r, np.linalg.inv(C), r))
    w /= w.sum()
    np.testing.assert_allclose(np.einsum("n,ni,nj->ij", w, th, th), M, rtol=0.05,
                               atol=0.02 * P[0, 0])


def test_the_prior_is_widened_to_what_makes_the_estimate_most_likely():
    s2 = np.radians(0.1) ** 2
    rng = np.random.default_rng(4)
    B = rng.normal(size=(3, 3))
    C = B @ B.T * np.radians(0.1) ** 2
    grid = np.exp(np.linspace(0.0, np.log(1e4), 20001))
    for e_deg in ([0.05, 0.0, 0.02], [1.0, 0.2, -0.3], [0.0, 0.6, 0.0]):
        e = np.radians(e_deg)

        def nll(scale, e=e):
            S = scale * s2 * np.eye(3) + C
            return np.linalg.slogdet(S)[1] + e @ np.linalg.solve(S, e)

        brute = grid[np.argmin([nll(g) for g in grid])]
        assert np.isclose(prior_scale(s2, e, C), brute, rtol=2e-3), (e_deg, brute)
    # a rotation 1 deg off in a config that claims 0.1: the second moment reaches the estimate
    e = np.radians([1.0, 0.0, 0.0])
    C = np.diag(np.radians([0.15, 0.5, 0.5]) ** 2)
    M = error_second_moment(np.radians(0.1), e, C)
    assert np.sqrt(M[0, 0]) > np.radians(0.9)
    # one within the claim leaves the prior as it is
    assert prior_scale(s2, np.radians([0.05, 0.0, 0.0]), C) == 1.0


def test_an_axis_the_check_cannot_see_keeps_the_prior():
    s = np.radians(0.2)
    for blind in (1e6, 0.0, 1e-22):  # a huge variance, or a degenerate one (rounding left over
        # from a projection, as the lever arm check's across the vertical): no information
        C = np.diag([np.radians(0.05) ** 2, np.radians(0.05) ** 2, blind])
        M = error_second_moment(s, np.zeros(3), C)
        assert np.isclose(M[2, 2], s**2, rtol=1e-6) and M[0, 0] < 0.1 * s**2


def test_no_estimate_is_the_prior_and_zero_is_exact():
    s = np.radians(0.1)
    np.testing.assert_allclose(error_second_moment(s), np.eye(3) * s**2)
    assert not error_second_moment(0.0, np.ones(3), np.eye(3)).any()


def test_a_projected_estimate_never_breaks_the_second_moment():
    """The lever arm check's covariance across the vertical is singular up to rounding along
    it (a run once stopped on a singular matrix here): any scale, any vertical, finite and
    positive definite."""
    rng = np.random.default_rng(6)
    for _ in range(2000):
        up = rng.normal(size=3)
        up /= np.linalg.norm(up)
        P = np.eye(3) - np.outer(up, up)
        B = rng.normal(size=(3, 3)) * 10 ** rng.uniform(-4, -1)
        e = P @ rng.normal(size=3) * 10 ** rng.uniform(-4, -1)
        M = error_second_moment(10 ** rng.uniform(-4, -1), e, P @ (B @ B.T) @ P)
        assert np.all(np.isfinite(M)) and np.linalg.eigvalsh(M).min() > 0


def test_the_posterior_mean_corrects_better_than_the_value_found():
    """The restart applies the posterior mean of the passes' value (``run_bag``): drawn true
    rotations of several sizes, values found with an anisotropic noise of 0.1-0.25 deg, prior
    0.1 deg. Where the rotation is comparable to the noise the posterior mean leaves less than
    the value itself (which a noisy excursion carries whole), a clear rotation is corrected as
    well as by the value, and the rotation left is within the value's largest deviation per axis
    (the restarted run's configured deviation)."""
    rng = np.random.default_rng(3)
    prior = np.radians(0.1)
    for mag_deg in (0.0, 0.3, 0.5, 2.0):
        raw, post, ratio = [], [], []
        for _ in range(600):
            A = Rotation.random(random_state=rng).as_matrix()
            S = A @ np.diag(np.radians([0.1, 0.15, 0.25]) ** 2) @ A.T
            u = rng.standard_normal(3)
            theta = np.radians(mag_deg) * u / np.linalg.norm(u)
            found = rng.multivariate_normal(theta, S)
            m, _ = posterior(prior, found, S)
            raw.append(np.sum((theta - found) ** 2))
            post.append(np.sum((theta - m) ** 2))
            ratio.append(np.linalg.norm(m) / np.linalg.norm(found))
        rms_raw, rms_post = np.sqrt(np.mean(raw)), np.sqrt(np.mean(post))
        if mag_deg <= 0.3:
            assert rms_post < 0.9 * rms_raw, (mag_deg, rms_post, rms_raw)
        elif mag_deg <= 0.5:
            assert rms_post < rms_raw, (rms_post, rms_raw)
        else:
            assert rms_post < 1.05 * rms_raw and np.mean(ratio) > 0.97, (rms_post, rms_raw)
        assert rms_post / np.sqrt(3.0) < np.radians(0.25)


def test_the_run_end_variance_is_each_scans_own_at_the_final_estimates():
    """Odometry.extrinsic_variance (the share run_bag widens scans.csv's rows to) is, pose by
    pose, the diagonal of the G M G^T each scan's own sigmas add (``_extrinsic_covariance``,
    built on the functions above) with the same estimates; zero at the anchor and before it."""
    from adalio.config import Config
    from adalio.lio import Odometry
    from adalio.lio.state import State

    rng = np.random.default_rng(11)
    odom = Odometry(Config())
    R_all, p_all = _poses(rng, 6)
    assert np.all(odom.extrinsic_variance(np.eye(4)[None].repeat(2, axis=0)) == 0.0)
    odom._anchor_state = State(p=p_all[0], R=R_all[0])
    for attr, scale in (("_rotation_M", 1e-2), ("_gyro_axes_M", 3e-3), ("_translation_M", 2e-2)):
        A = rng.normal(size=(3, 3)) * scale
        setattr(odom, attr, A @ A.T)
    T = np.stack([State(p=p, R=R).T_world_imu() for R, p in zip(R_all, p_all, strict=True)])
    got = odom.extrinsic_variance(T)
    assert np.all(got[0] == 0.0)
    for k in range(1, len(T)):
        odom._state = State(p=p_all[k], R=R_all[k])
        want = np.diag(odom._extrinsic_covariance())
        np.testing.assert_allclose(got[k], want, rtol=1e-12, atol=1e-18)
        assert np.all(want > 0.0)
