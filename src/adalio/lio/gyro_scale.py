"""The gyro's scale factors against the data: does the gyro read the rates the LiDAR registers?

A MEMS gyro reads ``S ω`` for the true rate ``ω``: scale factors off by up to a few percent on
the diagonal of ``S``, cross-axis sensitivity off it (datasheet tolerances; an IMU intrinsic
calibration, Kalibr's or OpenVINS's, measures ``S``). Uncalibrated, every rotation the gyro
integrates between scans and across a sweep's undistortion is a little off, and the LiDAR does
not take it back: measured on the simulated hall and shaft (XT-32 at 512 columns, HILTI IMU
noise, ``simulate --imu-scale-error-pct 1``), 0.26 -> 0.59 cm and 2.78 -> 5.65 cm ATE, all of it
restored with the true ``S`` in ``sensor.gyro_sensitivity`` and nearly all with its symmetric
part alone (README, "IMU sensitivity").

What measures it: the rotation check's data (:func:`adalio.lio.extrinsic_check.pair_rates`,
the LiDAR-only mean rate ``ω_L`` and the gyro's ``ω_G`` over each scan pair, read through the
configured ``sensor.gyro_sensitivity``). A general linear map, ``ω_G = (I + A) ω_L + b`` with a
constant bias ``b``, fitted by least squares with Huber weights and a Newey-West covariance as
the rotation check's. ``A``'s antisymmetric part is a rotation of the gyro's axes, which the
rotation check takes as the extrinsic's; its symmetric part ``S_err`` is what no rotation
explains: the scale factors and the symmetric cross-axis terms. Like the rotation, the estimate
sees only part of it (the map was built through the same gyro: 0.4-1.0 of each entry on the
hall, measured), so ``pipeline.run_bag`` finds the value by passes (:func:`next_scale`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adalio.lio.extrinsic_check import (
    HUBER_K,
    MIN_PAIRS,
    NEWEY_WEST_LAGS,
    next_rotation,
    pair_rates,
)
from adalio.lio.time_offset import MAX_PAIR_S, MIN_PAIR_S, huber_least_squares

MIN_SCALE_ERROR = 0.006
"""Smaller estimates (largest entry of the symmetric part) are not acted on: the check has an
error of its own, the registration's rotation bias, which at the right scale reached 0.43 %
(+-0.09, 4.8 deviations) on the VLP-16's hall walk and 0.33 % on the XT-32's (session 64; a
restart on the former "found" 0.65 %)."""
SIGNIFICANCE = 4.0
"""... nor are estimates whose largest entry is within this many of its standard deviations."""
SIGMA_DONE = 0.001
"""The check concludes once every entry's standard deviation is at most this (0.1 %)..."""
SIGMA_SIGNIFICANT = 0.0025
"""... or once it is significant with its largest entry's deviation at most this."""
PASS_TOLERANCE = 0.001
"""``run_bag``'s passes go on until the largest entry left is within this or one deviation."""
MAX_PASSES = 4
MAX_ROTATION_SD_RAD = 1.5e-3
"""Scan pairs whose LiDAR-only orientations are known worse than this about their weakest axes
(0.09°; ``Odometry._lidar_rotation_sd``) are left out: there the registration's rotation follows
the map, which turns with the estimate, and reads a scale that is not the gyro's (at the right
scale, 1.5-2.3 % in the simulated spiral shaft, whose scans are known to 4 mrad; the hall's to
0.6 mrad, a corridor's to 2.8 mrad)."""
MIN_EXCITATION = 1e-3
"""No estimate where the rates' information about some entry is below this share of the
best-known one's: a rig turning about one axis (a robot's yaw) tells nothing of the others'
scales, and the fit would read its registration noise as a scale of -100 %."""
PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
"""The symmetric part's six entries, in the order of ``GyroScaleEstimate.s``."""


def scale_text(s: np.ndarray) -> str:
    """'scale factors x +0.52 / y -0.31 / z +1.20 %, largest cross-axis +0.40 %' of the six
    entries ``s`` (:data:`PAIRS`, fractions)."""
    d = 100 * np.asarray(s)[[0, 3, 5]]
    off = 100 * np.asarray(s)[[1, 2, 4]]
    k = int(np.argmax(np.abs(off)))
    return (f"scale factors x {d[0]:+.2f} / y {d[1]:+.2f} / z {d[2]:+.2f} %, largest "
            f"cross-axis {off[k]:+.2f} %")


def sym_from_vector(s: np.ndarray) -> np.ndarray:
    """The symmetric 3x3 matrix of the six entries ``s`` (:data:`PAIRS`)."""
    M = np.zeros((3, 3))
    for v, (i, j) in zip(s, PAIRS, strict=True):
        M[i, j] = M[j, i] = v
    return M


@dataclass
class GyroScaleEstimate:
    """The symmetric part of the gyro's sensitivity error left after
    ``sensor.gyro_sensitivity``, over the scans checked."""

    s: np.ndarray
    """(6,) its entries xx, xy, xz, yy, yz, zz (fractions: 0.01 = 1 %)."""
    cov: np.ndarray
    """(6,6) their covariance."""
    span_s: float
    n_pairs: int

    @property
    def matrix(self) -> np.ndarray:
        return sym_from_vector(self.s)

    @property
    def _largest(self) -> int:
        return int(np.argmax(np.abs(self.s)))

    @property
    def largest(self) -> float:
        """The largest entry's size (a fraction)."""
        return float(np.abs(self.s).max())

    @property
    def sigma(self) -> float:
        """The largest entry's standard deviation."""
        k = self._largest
        return float(np.sqrt(max(self.cov[k, k], 0.0)))

    @property
    def significant(self) -> bool:
        return self.largest >= max(MIN_SCALE_ERROR, SIGNIFICANCE * self.sigma)

    @property
    def settled(self) -> bool:
        """Within ``PASS_TOLERANCE`` or one standard deviation of zero (passes stop)."""
        return self.largest <= max(PASS_TOLERANCE, self.sigma)

    @property
    def conclusive(self) -> bool:
        """Precise enough to call the scale right, or significant at a usable precision."""
        sd = np.sqrt(np.clip(np.diag(self.cov), 0.0, None))
        return bool(sd.max() <= SIGMA_DONE
                    or (self.significant and self.sigma <= SIGMA_SIGNIFICANT))

    def text(self) -> str:
        """:func:`scale_text` with the largest entry's deviation: '... +0.40 % (+-0.05)'."""
        return f"{scale_text(self.s)} (+-{100 * self.sigma:.2f})"


def estimate_gyro_scale(t_scan_s: np.ndarray, R_scan: np.ndarray, t_imu_s: np.ndarray,
                        gyro_rad_s: np.ndarray, offset_s: float, span_s: float,
                        rot_sd_rad: np.ndarray | None = None) -> GyroScaleEstimate | None:
    """The symmetric part of ``A`` in ``ω_G = (I + A) ω_L + b`` over consecutive scan pairs (the
    data and pairing of :func:`adalio.lio.extrinsic_check.estimate_rotation`), those whose two
    LiDAR-only orientations are known to ``MAX_ROTATION_SD_RAD`` about their weakest axes
    (``rot_sd_rad`` per scan; None: all). None: too few pairs, or too little rotation about
    some axis to tell its scale."""
    if t_imu_s.size < 4:
        return None
    dt = np.diff(t_scan_s)
    a, b = t_scan_s[:-1] + offset_s, t_scan_s[1:] + offset_s
    ok = (dt > MIN_PAIR_S) & (dt < MAX_PAIR_S) & (a >= t_imu_s[0]) & (b <= t_imu_s[-1])
    if rot_sd_rad is not None:
        known = np.asarray(rot_sd_rad) <= MAX_ROTATION_SD_RAD  # NaN: not known
        ok &= known[:-1] & known[1:]
    idx = np.flatnonzero(ok)
    if idx.size < MIN_PAIRS:
        return None
    w_lidar, w_gyro = pair_rates(R_scan[idx], R_scan[idx + 1], a[idx], b[idx], dt[idx],
                                 t_imu_s, gyro_rad_s)
    n = idx.size
    X = np.zeros((n, 3, 12))  # unknowns: A row by row, then b
    for i in range(3):
        X[:, i, 3 * i:3 * i + 3] = w_lidar
        X[:, i, 9 + i] = 1.0
    fit = huber_least_squares(w_gyro - w_lidar, X, 9, iterations=8,
                              min_excitation=MIN_EXCITATION, lags=NEWEY_WEST_LAGS,
                              huber_k=HUBER_K)
    if fit is None:
        return None  # too little rotation about some axis
    beta, cov = fit
    P = np.zeros((6, 9))  # the symmetric part's entries from A's nine
    for k, (i, j) in enumerate(PAIRS):
        P[k, 3 * i + j] += 0.5
        P[k, 3 * j + i] += 0.5
    C = P @ cov @ P.T
    return GyroScaleEstimate(s=P @ beta[:9], cov=0.5 * (C + C.T), span_s=float(span_s),
                             n_pairs=int(n))


def next_scale(tried: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The next correction to try (the six entries), from the (correction, scale left) pairs so
    far: the rotation's secant (:func:`adalio.lio.extrinsic_check.next_rotation`) on these."""
    return next_rotation(tried)


def corrected_sensitivity(configured: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``sensor.gyro_sensitivity`` after a correction ``s``: the gyro read through the
    configured matrix still reads ``(I + S) ω``, so it reads ``configured (I + S) ω``."""
    return np.asarray(configured, dtype=np.float64) @ (np.eye(3) + sym_from_vector(s))
