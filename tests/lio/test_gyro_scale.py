"""The gyro scale check against a constructed truth: a hand's orientation, a gyro that reads its
body rate (by finite differences of the orientation) through ``I + E`` with a bias and white
noise, and LiDAR-only orientations at the scan ends with registration noise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from adalio.lio.gyro_scale import (
    MAX_ROTATION_SD_RAD,
    PAIRS,
    corrected_sensitivity,
    estimate_gyro_scale,
    sym_from_vector,
)

IMU_HZ, SCAN_HZ, SPAN_S = 400.0, 10.0, 30.0
GYRO_SIGMA = 0.002  # rad/s per sample, about the BMI085's at 400 Hz


def _orientation(t: np.ndarray, f: np.ndarray, a: np.ndarray, ph: np.ndarray) -> Rotation:
    """A hand's orientation ``Exp(φ(t))``, each axis of ``φ`` a sum of sines."""
    arg = 2 * np.pi * f[None] * t[:, None, None] + ph[None]
    return Rotation.from_rotvec(np.sum(a[None] * np.sin(arg), axis=2))


def _data(rng: np.random.Generator, E: np.ndarray, noise_rad: float = 2e-4,
          axes=(1.0, 1.0, 1.0)):
    f = rng.uniform(0.1, 1.0, size=(3, 4))
    a = rng.uniform(0.05, 0.3, size=(3, 4)) * np.asarray(axes)[:, None]
    ph = rng.uniform(0.0, 2 * np.pi, size=(3, 4))
    t_imu = np.arange(0.0, SPAN_S + 0.9, 1.0 / IMU_HZ)
    h = 1e-5  # the body rate by a central difference of the orientation
    rate = (_orientation(t_imu - h, f, a, ph).inv() * _orientation(t_imu + h, f, a, ph)
            ).as_rotvec() / (2 * h)
    gyro = rate @ (np.eye(3) + E).T + np.array([0.01, -0.02, 0.005]) + rng.normal(
        scale=GYRO_SIGMA, size=rate.shape)
    t_scan = np.arange(0.2, SPAN_S, 1.0 / SCAN_HZ)
    R_scan = _orientation(t_scan, f, a, ph) * Rotation.from_rotvec(
        rng.normal(scale=noise_rad, size=(t_scan.size, 3)))
    return t_scan, R_scan.as_matrix(), t_imu, gyro


def _sym(E: np.ndarray) -> np.ndarray:
    S = 0.5 * (E + E.T)
    return np.array([S[i, j] for i, j in PAIRS])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_symmetric_part_is_recovered_and_a_rotation_is_not_taken_for_it(seed):
    """A 1 % sensitivity error (scale factors, cross-axis and a skew part, a rotation of the
    gyro's axes) is recovered in its symmetric part within 4 deviations; the same data without
    it reads no significant scale, and a pure rotation of the axes (skew ``E``) none either."""
    rng = np.random.default_rng(seed)
    E = 0.01 * rng.standard_normal((3, 3))
    est = estimate_gyro_scale(*_data(rng, E), 0.0, SPAN_S)
    assert est is not None and est.significant
    sd = np.sqrt(np.diag(est.cov))
    assert np.all(np.abs(est.s - _sym(E)) <= 4 * sd + 1e-4), (est.s, _sym(E), sd)
    assert sd.max() < 0.0015  # precise against 1 %
    rng = np.random.default_rng(seed + 10)
    none = estimate_gyro_scale(*_data(rng, np.zeros((3, 3))), 0.0, SPAN_S)
    assert none is not None and not none.significant
    skew = np.deg2rad(1.0) * np.array([[0, -1, 0.5], [1, 0, -0.3], [-0.5, 0.3, 0]])
    turned = estimate_gyro_scale(*_data(rng, skew), 0.0, SPAN_S)
    assert turned is not None and not turned.significant


def test_a_rig_turning_about_one_axis_gives_no_estimate():
    """Rotation about one axis only cannot tell the other axes' scales: no estimate."""
    rng = np.random.default_rng(5)
    assert estimate_gyro_scale(*_data(rng, np.zeros((3, 3)), axes=(0.0, 0.0, 1.0)), 0.0,
                               SPAN_S) is None


def test_the_corrected_sensitivity_reads_the_error_left_as_zero():
    """A gyro reading ``S_true ω``, read through ``corrected_sensitivity(S_cfg, s)`` with ``s``
    the symmetric error the check sees through ``S_cfg``, reads ``ω`` back exactly when
    ``S_true`` is ``S_cfg (I + sym(s))``: brute force on random rates."""
    rng = np.random.default_rng(3)
    S_cfg = np.eye(3) + 0.01 * rng.standard_normal((3, 3))
    s = 0.01 * rng.standard_normal(6)
    S_true = S_cfg @ (np.eye(3) + sym_from_vector(s))
    w = rng.standard_normal((100, 3))
    read = w @ S_true.T
    back = read @ np.linalg.inv(corrected_sensitivity(S_cfg, s)).T
    np.testing.assert_allclose(back, w, rtol=0, atol=1e-12)
    assert np.abs(read @ np.linalg.inv(S_cfg).T - w).max() > 1e-3


def test_pairs_the_lidar_registers_weakly_are_left_out():
    """Scans whose LiDAR-only rotation over-reads by 5 % (a map that turns with the estimate),
    flagged with deviations beyond ``MAX_ROTATION_SD_RAD``, would read a scale error of -5 % where
    there is none: with their deviations given the estimate leaves them out and reads none."""
    rng = np.random.default_rng(7)
    t_scan, R, t_imu, gyro = _data(rng, np.zeros((3, 3)))
    weak = (t_scan > 8.0) & (t_scan < 22.0)
    R_bad = R.copy()
    for k in range(1, len(R)):
        if weak[k]:
            step = Rotation.from_matrix(R[k - 1].T @ R[k]).as_rotvec()
            R_bad[k] = R_bad[k - 1] @ Rotation.from_rotvec(1.05 * step).as_matrix()
        else:
            R_bad[k] = R_bad[k - 1] @ (R[k - 1].T @ R[k])
    sd = np.where(weak, 10 * MAX_ROTATION_SD_RAD, 0.1 * MAX_ROTATION_SD_RAD)
    fooled = estimate_gyro_scale(t_scan, R_bad, t_imu, gyro, 0.0, SPAN_S)
    assert fooled is not None and fooled.significant and fooled.largest > 0.02
    gated = estimate_gyro_scale(t_scan, R_bad, t_imu, gyro, 0.0, SPAN_S, rot_sd_rad=sd)
    assert gated is not None and not gated.significant
    assert gated.n_pairs < 0.6 * fooled.n_pairs
    assert estimate_gyro_scale(t_scan, R_bad, t_imu, gyro, 0.0, SPAN_S,
                               rot_sd_rad=np.full(len(t_scan), np.nan)) is None  # none known
