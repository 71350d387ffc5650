"""The LiDAR-IMU translation check against a constructed truth: a hand's rotation and a walk's
position with their exact derivatives, an IMU that samples them (white noise, biases), and
LiDAR-only IMU poses at the scan ends seen through a lever arm that is off by a known ``δ``:
``p̂ = p + R δ``."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_extrinsic_check import _Hand

from adalio.lio.lever_arm import MIN_TRANSLATION_M, estimate_translation

IMU_HZ, SCAN_HZ, SPAN_S = 400.0, 10.0, 20.0
G = np.array([0.0, 0.0, -9.81])
ACCEL_SIGMA = 1.32e-3 * np.sqrt(IMU_HZ)  # the BMI085's density, per sample
GYRO_SIGMA = 1.9e-4 * np.sqrt(IMU_HZ)


class _Walk:
    """A position ``p(t) = v t + Σ a sin(2π f t + φ)`` per axis and its acceleration."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.v = np.array([1.0, 0.3, 0.0])
        self.f = rng.uniform(0.3, 2.0, size=(3, 3))
        self.a = rng.uniform(0.005, 0.05, size=(3, 3))
        self.ph = rng.uniform(0.0, 2 * np.pi, size=(3, 3))

    def p(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * self.f[None] * t[:, None, None] + self.ph[None]
        return self.v * t[:, None] + np.sum(self.a[None] * np.sin(arg), axis=2)

    def acc(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * self.f[None] * t[:, None, None] + self.ph[None]
        return -np.sum(self.a[None] * (2 * np.pi * self.f[None]) ** 2 * np.sin(arg), axis=2)


def _data(rng, delta_m, axes=(1.0, 1.0, 1.0), pose_noise_m=1e-3, rot_noise_rad=2e-4):
    hand, walk = _Hand(rng, axes), _Walk(rng)
    t_imu = np.arange(0.0, SPAN_S + 0.9, 1.0 / IMU_HZ)
    R_imu = Rotation.from_rotvec(hand.phi(t_imu)).as_matrix()
    f = np.einsum("nji,nj->ni", R_imu, walk.acc(t_imu) - G)  # specific force, IMU frame
    gyro = hand.rate(t_imu) + [0.002, -0.001, 0.003] + rng.normal(scale=GYRO_SIGMA,
                                                                   size=(t_imu.size, 3))
    accel = f + [0.03, -0.02, 0.05] + rng.normal(scale=ACCEL_SIGMA, size=(t_imu.size, 3))
    t_scan = np.arange(0.2, SPAN_S, 1.0 / SCAN_HZ)
    R = Rotation.from_rotvec(hand.phi(t_scan)) * Rotation.from_rotvec(
        rng.normal(scale=rot_noise_rad, size=(t_scan.size, 3)))
    R_true = Rotation.from_rotvec(hand.phi(t_scan)).as_matrix()
    p = walk.p(t_scan) + R_true @ np.asarray(delta_m) \
        + rng.normal(scale=pose_noise_m, size=(t_scan.size, 3))
    return t_scan, R.as_matrix(), p, t_imu, gyro, accel


@pytest.mark.parametrize("delta_cm", [(0.0, 0.0, 0.0), (2.0, -1.0, 1.5), (-4.0, 3.0, 0.0)])
def test_the_lever_arm_error_is_recovered(delta_cm):
    rng = np.random.default_rng(int(10 * sum(np.abs(delta_cm))) + 3)
    delta = 1e-2 * np.asarray(delta_cm)
    est = estimate_translation(*_data(rng, delta), G, 0.0, SPAN_S)
    assert est is not None
    sigma = np.sqrt(np.diag(est.cov_m2))
    err = est.delta_m - delta
    assert np.all(np.abs(err) < 4 * sigma + 1e-4), (est.delta_m, delta, sigma)
    assert np.all(np.abs(err) < 3e-3), err  # millimetres, from a 20 s hand
    assert np.all(sigma < 2e-3), sigma
    across = (np.eye(3) - np.outer(est.up_imu, est.up_imu)) @ delta  # what the check acts on
    np.testing.assert_allclose(est.horizontal_m, across, atol=3e-3)
    assert est.significant == (np.linalg.norm(across) >= MIN_TRANSLATION_M)


def test_a_rig_turning_about_the_vertical_only_claims_no_vertical():
    """A robot's yaw: a lever arm along the vertical is the same point in every turn."""
    rng = np.random.default_rng(7)
    est = estimate_translation(*_data(rng, [0.0, 0.0, 0.05], axes=(0.0, 0.0, 1.0)), G, 0.0,
                               SPAN_S)
    assert est is None or np.sqrt(est.cov_m2[2, 2]) > 0.01 or not est.significant


def test_the_stamps_offset_is_taken_out():
    """The IMU's stamps 20 ms late, and the check told so: as on time."""
    rng = np.random.default_rng(5)
    t_scan, R, p, t_imu, gyro, accel = _data(rng, [0.03, 0.0, -0.02])
    est = estimate_translation(t_scan, R, p, t_imu + 0.02, gyro, accel, G, 0.02, SPAN_S)
    assert est is not None and np.all(np.abs(est.delta_m - [0.03, 0.0, -0.02]) < 3e-3)


def test_a_rig_at_rest_gives_no_estimate_and_no_error():
    """A minute at rest: every triple the same, the bias and gravity indistinguishable, and
    nothing to tell a lever arm by (a singular system, not an exception)."""
    t_imu = np.arange(0.0, 60.5, 1.0 / IMU_HZ)
    t_scan = np.arange(0.2, 60.0, 1.0 / SCAN_HZ)
    R = np.repeat(np.eye(3)[None], t_scan.size, axis=0)
    p = np.zeros((t_scan.size, 3))
    gyro = np.zeros((t_imu.size, 3))
    accel = np.tile(-G, (t_imu.size, 1))
    assert estimate_translation(t_scan, R, p, t_imu, gyro, accel, G, 0.0, 60.0) is None
