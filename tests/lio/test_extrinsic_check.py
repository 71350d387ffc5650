"""The LiDAR-IMU rotation check against a constructed truth: a hand's rotation integrated once,
a gyro that samples it with white noise and a bias, and LiDAR-only orientations at the scan
ends mapped into the IMU frame through a configured rotation that is off by a known ``E``."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from adalio.lio.extrinsic_check import (
    GROSS_MIN_RAD,
    MAX_PASSES,
    PASS_TOLERANCE_RAD,
    estimate_rotation,
    next_rotation,
)

IMU_HZ, SCAN_HZ, SPAN_S = 400.0, 10.0, 20.0
GYRO_SIGMA = 0.002  # rad/s per sample, about the BMI085's at 400 Hz


def _hat(v: np.ndarray) -> np.ndarray:
    """(n,3) -> (n,3,3) skew matrices."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


class _Hand:
    """A hand's orientation ``R(t) = Exp(φ(t))``, ``φ`` a sum of sines per axis (scaled by
    ``axes``), and its exact body rate ``ω = J_r(φ) φ̇``."""

    def __init__(self, rng: np.random.Generator, axes=(1.0, 1.0, 1.0), mix=None) -> None:
        self.f = rng.uniform(0.1, 1.0, size=(3, 4))
        self.a = rng.uniform(0.05, 0.3, size=(3, 4)) * np.asarray(axes)[:, None]
        self.ph = rng.uniform(0.0, 2 * np.pi, size=(3, 4))
        self.mix = np.eye(3) if mix is None else np.asarray(mix, dtype=float)
        # the axes' turns correlated through ``mix`` (a hand turning about a tilted axis)

    def phi(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * self.f[None] * t[:, None, None] + self.ph[None]
        return np.sum(self.a[None] * np.sin(arg), axis=2) @ self.mix.T

    def rate(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * self.f[None] * t[:, None, None] + self.ph[None]
        dphi = np.sum(self.a[None] * 2 * np.pi * self.f[None] * np.cos(arg), axis=2) @ self.mix.T
        phi = self.phi(t)
        a = np.linalg.norm(phi, axis=1)[:, None, None]
        K = _hat(phi)
        safe = np.maximum(a, 1e-9)
        Jr = (np.eye(3) - (1 - np.cos(safe)) / safe**2 * K
              + (safe - np.sin(safe)) / safe**3 * K @ K)
        return np.einsum("nij,nj->ni", Jr, dphi)


def _data(rng, E_rotvec, noise_rad=2e-4, bias=(0.01, -0.02, 0.005), axes=(1.0, 1.0, 1.0),
          correlated=False, mix=None, lidar_turns=None):
    """``lidar_turns``: per IMU axis, the share of the hand's turn the LiDAR-only orientations
    follow (a registration that lags the turn about one axis more than about another)."""
    hand = _Hand(rng, axes, mix)
    t_imu = np.arange(0.0, SPAN_S + 0.9, 1.0 / IMU_HZ)
    gyro = hand.rate(t_imu) + np.asarray(bias) + rng.normal(scale=GYRO_SIGMA,
                                                            size=(t_imu.size, 3))
    t_scan = np.arange(0.2, SPAN_S, 1.0 / SCAN_HZ)
    # R_wi E: the IMU's orientation as the LiDAR sees it through the configured rotation
    phi = hand.phi(t_scan) * (1.0 if lidar_turns is None else np.asarray(lidar_turns))
    R_scan = Rotation.from_rotvec(phi) * Rotation.from_rotvec(E_rotvec)
    if correlated:  # registration errors that persist over several scans (a shared map)
        e = np.zeros((t_scan.size, 3))
        for k in range(1, t_scan.size):
            e[k] = 0.8 * e[k - 1] + rng.normal(scale=noise_rad, size=3)
    else:
        e = rng.normal(scale=noise_rad, size=(t_scan.size, 3))
    R_scan = R_scan * Rotation.from_rotvec(e)
    return t_scan, R_scan.as_matrix(), t_imu, gyro


def _estimate(data, offset_s=0.0):
    return estimate_rotation(*data, offset_s, SPAN_S)


@pytest.mark.parametrize("deg", [0.0, 0.5, 2.0, 5.0])
def test_the_rotation_is_recovered_with_its_axis(deg):
    rng = np.random.default_rng(int(deg * 10) + 1)
    axis = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])
    theta = np.deg2rad(deg) * axis
    est = _estimate(_data(rng, theta))
    assert est is not None
    err = Rotation.from_rotvec(est.rotvec_rad) * Rotation.from_rotvec(theta).inv()
    worst_sigma = np.sqrt(np.linalg.eigvalsh(est.cov_rad2)[-1])
    assert err.magnitude() < 4.0 * worst_sigma, (np.degrees(est.rotvec_rad), deg)
    assert np.degrees(err.magnitude()) < 0.1 and np.degrees(worst_sigma) < 0.05
    assert est.significant == (deg >= 0.5)


def test_its_sigma_holds_with_correlated_registration_errors():
    """Over many constructed walks with registration errors that persist over scans (as a
    shared map makes them), the error's size against the claimed covariance (squared
    Mahalanobis, 3 dof: mean 3 when honest; measured 3.0) is neither far above
    (over-confident) nor far below."""
    d2 = []
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        theta = np.deg2rad(1.0) * rng.normal(size=3) / np.sqrt(3.0)
        est = _estimate(_data(rng, theta, noise_rad=1e-3, correlated=True))
        err = (Rotation.from_rotvec(est.rotvec_rad) * Rotation.from_rotvec(theta).inv()
               ).as_rotvec()
        d2.append(float(err @ np.linalg.solve(est.cov_rad2, err)))
    assert 1.5 < np.mean(d2) < 5.0, np.mean(d2)


def _rotation_only(data) -> np.ndarray:
    """The least-squares ``θ`` of ``ω_G = Exp(θ) ω_L + b`` alone, linearised at zero (the
    model without the symmetric part), for the test below to show what its data do to it."""
    from adalio.lio.extrinsic_check import pair_rates

    t_scan, R_scan, t_imu, gyro = data
    dt = np.diff(t_scan)
    w_l, w_g = pair_rates(R_scan[:-1], R_scan[1:], t_scan[:-1], t_scan[1:], dt, t_imu, gyro)
    # ω_G − ω_L ≈ −[ω_L]× θ + b
    A = np.concatenate([-_hat(w_l), np.broadcast_to(np.eye(3), (len(w_l), 3, 3))], 2)
    x = np.linalg.lstsq(A.reshape(-1, 6), (w_g - w_l).reshape(-1), rcond=None)[0]
    return x[:3]


@pytest.mark.parametrize("deg", [0.0, 1.0])
def test_a_registration_that_lags_the_turn_about_one_axis_is_no_rotation(deg):
    """LiDAR-only orientations that follow the hand's turn about y by 1 % less than about x
    and z, with the turns about x and y correlated: a fit of the rotation alone reads that as
    an axis rotation (0.25-0.26° here; the check before session 79 was that fit and failed
    both cases), the check's symmetric part takes it, and the rotation found is the one the
    extrinsic has (none, or 1°: 0.10 and 0.005° off, at 2.2 and 0.1 of its sigma)."""
    rng = np.random.default_rng(21 + int(deg))
    axis = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])
    theta = np.deg2rad(deg) * axis
    mix = [[1.0, 0.6, 0.0], [0.6, 1.0, 0.0], [0.0, 0.0, 1.0]]
    data = _data(rng, theta, mix=mix, lidar_turns=(1.0, 0.99, 1.0))
    off = _rotation_only(data) - theta
    assert np.degrees(np.linalg.norm(off)) > 0.15, np.degrees(off)
    est = _estimate(data)
    err = Rotation.from_rotvec(est.rotvec_rad) * Rotation.from_rotvec(theta).inv()
    worst_sigma = np.sqrt(np.linalg.eigvalsh(est.cov_rad2)[-1])
    assert err.magnitude() < 4.0 * worst_sigma, (np.degrees(est.rotvec_rad), deg)
    assert np.degrees(err.magnitude()) < 0.15  # the fit of θ alone: 0.25-0.26° off
    assert est.significant == (deg > 0.0)


def test_outlier_registrations_do_not_move_it():
    rng = np.random.default_rng(7)
    theta = np.deg2rad([0.6, -0.4, 0.2])
    t_scan, R_scan, t_imu, gyro = _data(rng, theta)
    bad = rng.choice(t_scan.size, size=t_scan.size // 20, replace=False)
    R_scan[bad] = R_scan[bad] @ Rotation.from_rotvec(
        rng.normal(scale=np.deg2rad(3.0), size=(bad.size, 3))).as_matrix()
    est = _estimate((t_scan, R_scan, t_imu, gyro))
    err = Rotation.from_rotvec(est.rotvec_rad) * Rotation.from_rotvec(theta).inv()
    assert err.magnitude() < 4.0 * np.sqrt(np.linalg.eigvalsh(est.cov_rad2)[-1])
    assert np.degrees(err.magnitude()) < 0.1


def test_a_turn_about_one_axis_cannot_tell_an_axis():
    """Rotating about one axis only, a rotation error about that axis changes nothing:
    no estimate rather than a confident one."""
    rng = np.random.default_rng(3)
    est = _estimate(_data(rng, np.deg2rad([0.0, 0.0, 1.0]), axes=(0.0, 0.0, 1.0),
                          noise_rad=0.0))
    assert est is None or not est.significant


def test_the_gyro_running_late_is_allowed_for():
    rng = np.random.default_rng(9)
    theta = np.deg2rad([0.5, 0.5, -0.5])
    t_scan, R_scan, t_imu, gyro = _data(rng, theta)
    late = 0.03
    est = _estimate((t_scan, R_scan, t_imu + late, gyro), offset_s=late)
    err = Rotation.from_rotvec(est.rotvec_rad) * Rotation.from_rotvec(theta).inv()
    assert err.magnitude() < 4.0 * np.sqrt(np.linalg.eigvalsh(est.cov_rad2)[-1])
    assert np.degrees(err.magnitude()) < 0.1


@pytest.mark.parametrize("gains", [(0.8, 0.7, 0.6), (0.3, 0.9, 0.5), (1.0, 1.0, 1.0)])
def test_the_passes_converge_when_each_sees_only_part_of_what_is_left(gains):
    """``run_bag``'s search: each pass's estimate is a share (different per axis, in a turned
    basis) of the rotation left; the passes reach the tolerance within MAX_PASSES."""
    rng = np.random.default_rng(11)
    B = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    G = B @ np.diag(gains) @ B.T
    truth = np.deg2rad([1.5, -0.8, 0.6])
    tried = [(np.zeros(3), G @ truth)]
    for _ in range(MAX_PASSES):
        c = next_rotation(tried)
        left = G @ (truth - c)
        tried.append((c, left))
        if np.linalg.norm(left) <= PASS_TOLERANCE_RAD:
            break
    assert np.linalg.norm(tried[-1][1]) <= PASS_TOLERANCE_RAD, [np.degrees(t[1]) for t in tried]


def _gross(data, lag_s=0.0):
    """The gross check on ``data``, its LiDAR-only orientations stamped ``lag_s`` late (the
    gyro-free registration follows the turn late)."""
    from adalio.lio.extrinsic_check import estimate_gross_rotation

    t_scan, R_scan, t_imu, gyro = data
    return estimate_gross_rotation(t_scan + lag_s, R_scan, t_imu, gyro, SPAN_S)


@pytest.mark.parametrize(("deg", "lag_s"), [(0.0, 0.0), (3.0, 0.07), (12.0, 0.0),
                                            (90.0, 0.07), (179.0, -0.05)])
def test_a_gross_rotation_is_found_whole_whatever_its_size(deg, lag_s):
    """The gross check (a registration without the gyro against the gyro: the rotation factor
    of the linear map between their rates, on a lag grid): the whole rotation, however large,
    from noisier orientations than the fine check's (errors of about 0.1° that persist over
    scans), with the registration's own lag; a gross error from 10° and 5 deviations."""
    rng = np.random.default_rng(40 + int(deg))
    axis = np.array([-0.5, 0.2, 0.85]) / np.linalg.norm([-0.5, 0.2, 0.85])
    theta = np.deg2rad(deg) * axis
    est = _gross(_data(rng, theta, noise_rad=2e-3, correlated=True), lag_s)
    assert est is not None
    err = Rotation.from_matrix(est.correction) * Rotation.from_rotvec(theta).inv()
    assert err.magnitude() < 4.0 * est.sigma_rad, (np.degrees(err.magnitude()), est.text())
    assert np.degrees(err.magnitude()) < 0.5 and np.degrees(est.sigma_rad) < 0.5
    assert abs(est.lag_s + lag_s) <= 0.01, est.lag_s  # the gyro, against them, is early
    assert est.gross == (deg >= np.degrees(GROSS_MIN_RAD)), est.text()


def test_a_robot_turning_about_one_axis_raises_no_gross_rotation():
    """Turning about one axis with a little wobble (a robot), the rotation about the others is
    hardly seen: the gross check must not claim an error where there is none."""
    for seed in range(4):
        rng = np.random.default_rng(60 + seed)
        est = _gross(_data(rng, np.zeros(3), noise_rad=2e-3, correlated=True,
                           axes=(0.01, 0.01, 1.0)))
        assert est is None or not est.gross, est.text()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_gross_rotation_survives_a_registration_that_lags_about_one_axis(seed):
    """A registration without the gyro follows the turn about the axes its scans constrain
    weakly by less (the VLP-16's by up to a factor 2.7, session 80). Here it follows the turn
    about y by 15 % less, with the turns about x and y correlated, 90° off: the rotation factor
    of the rates' linear map is 1.1-2.5° off, where the closed-form rotation fit of the rates
    alone (Kabsch's) is 4.2-4.3° off."""
    rng = np.random.default_rng(80 + seed)
    axis = np.array([-0.5, 0.2, 0.85]) / np.linalg.norm([-0.5, 0.2, 0.85])
    theta = np.deg2rad(90.0) * axis
    mix = [[1.0, 0.6, 0.0], [0.6, 1.0, 0.0], [0.0, 0.0, 1.0]]
    est = _gross(_data(rng, theta, noise_rad=2e-3, correlated=True, mix=mix,
                       lidar_turns=(1.0, 0.85, 1.0)))
    err = Rotation.from_matrix(est.correction) * Rotation.from_rotvec(theta).inv()
    assert np.degrees(err.magnitude()) < 3.0, (np.degrees(err.magnitude()), est.text())
    assert est.gross
