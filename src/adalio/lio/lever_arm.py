"""The LiDAR-IMU translation in the config against the data: does the accelerometer feel the
motion the LiDAR registers, through the configured lever arm?

A rig's lever arm (``sensor.T_imu_lidar``'s translation) taken from a drawing can be off by
centimetres. The LiDAR registers its own origin; the filter reports the IMU through the
configured lever arm, so a translation error ``δ`` puts every reported IMU position off by
``R(t) δ``, which turns with the rig: measured on the simulated hall (XT-32 at 512 columns,
HILTI IMU noise), 3 cm off costs the IMU's trajectory 0.26 -> 1.31 cm and the LiDAR's (the
map's) 0.26 -> 0.48 cm (README, "LiDAR-IMU lever arm"). A significant correction is said in
the run's summary, a hint only (no warning, no restart): it is good to a centimetre or two,
and short recordings flag right lever arms now and then (measured, README).

What measures it: the updates' LiDAR-only poses (the IMU time offset check's data,
:class:`adalio.lio.time_offset.TimeOffsetCheck`), the IMU's position the LiDAR alone registers
through the configured extrinsic, ``p̂(t) = p(t) + R(t) δ``, against the accelerometer. Over
three scans ``a < b < c`` (``STRIDE_S`` apart) the velocity at ``a`` drops out of

    (p̂_c - p̂_a - D_ac)/(t_c - t_a) - (p̂_b - p̂_a - D_ab)/(t_b - t_a)
        = [(R_c - R_a)/(t_c - t_a) - (R_b - R_a)/(t_b - t_a)] δ + (bias, gravity terms),

``D`` the accelerometer integrated twice from rest at ``a`` (in the world, through the
LiDAR-only orientation at ``a`` and the gyro after it), with ``½ g t²``. Least squares with
Huber weights for ``δ``, a constant accelerometer bias and a gravity correction; the covariance
is the sandwich form with Newey-West over the overlapping triples.

A translation error is seen only when the rig turns, and a walk or a robot turns mostly about
the vertical: the part of ``δ`` along the rig's mean vertical is barely seen, and measured
biased by up to 3 cm (the x10 corridor, seed 1, right extrinsic: (-0.9, +2.3, +3.3) cm, the
vertical the largest) where the part across it held to 1-2 cm. The check judges the part
across the vertical only (:attr:`TranslationEstimate.horizontal_m`); the vertical is left as
configured.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from adalio.lio.extrinsic_check import largest_sigma, pair_rates, sigma_along
from adalio.lio.time_offset import MAX_PAIR_S, MIN_PAIR_S, huber_least_squares

STRIDE_S = 0.3
"""Time between the three scans of a triple: the accelerometer's noise, integrated twice, grows
with it and the registration's noise falls (the hall's whole walk, least squares without
Newey-West, scratch: largest deviations 0.74, 0.24, 0.19, 0.41 cm at 0.1, 0.2, 0.3, 0.5 s;
beyond, the vertical drifts by centimetres)."""
MIN_TRANSLATION_M = 0.02
"""Smaller corrections are not flagged: with the right lever arm the estimate keeps 0.3-1.5 cm
across the vertical (the registration's own error, shared by overlapping triples; README,
"LiDAR-IMU lever arm")."""
SIGNIFICANCE = 4.0
"""... nor are estimates within this many standard deviations (along their direction) of zero."""
SIGMA_DONE_M = 0.005
"""The check concludes once the estimate's largest standard deviation is at most this."""
SIGMA_SIGNIFICANT_M = 0.01
"""... or once its estimate is significant with a standard deviation of at most this."""
HUBER_K = 2.5
NEWEY_WEST_LAGS = 10
MIN_TRIPLES = 50
"""Fewer triples: no estimate."""


@dataclass
class TranslationEstimate:
    """The residual LiDAR-IMU translation over the scans checked."""

    delta_m: np.ndarray
    """(3,) ``δ`` in the IMU frame: the correction the configured ``T_imu_lidar`` translation
    needs added (``t ← t + δ``)."""
    cov_m2: np.ndarray
    """(3,3) its covariance."""
    span_s: float
    n_triples: int
    up_imu: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    """(3,) the rig's mean vertical in the IMU frame over the scans checked."""

    @property
    def _across(self) -> np.ndarray:
        """Projector onto the plane across the vertical (IMU frame)."""
        return np.eye(3) - np.outer(self.up_imu, self.up_imu)

    @property
    def horizontal_m(self) -> np.ndarray:
        """(3,) the part of ``δ`` across the rig's vertical: the correction the check acts on."""
        return self._across @ self.delta_m

    @property
    def horizontal_cov_m2(self) -> np.ndarray:
        P = self._across
        return P @ self.cov_m2 @ P

    @property
    def length_m(self) -> float:
        """The length of :attr:`horizontal_m`."""
        return float(np.linalg.norm(self.horizontal_m))

    @property
    def sigma_m(self) -> float:
        """The standard deviation of :attr:`horizontal_m` along its direction (the largest one
        across the vertical at zero)."""
        return sigma_along(self.horizontal_m, self.horizontal_cov_m2)

    @property
    def significant(self) -> bool:
        return self.length_m >= max(MIN_TRANSLATION_M, SIGNIFICANCE * self.sigma_m)

    @property
    def conclusive(self) -> bool:
        """Precise enough to call the translation right, or significant at a usable precision."""
        return largest_sigma(self.horizontal_cov_m2) <= SIGMA_DONE_M or (
            self.significant and self.sigma_m <= SIGMA_SIGNIFICANT_M)

    def text(self) -> str:
        """'(+1.4, -2.1, +0.7) cm (+-0.3)': :attr:`horizontal_m` in the IMU frame."""
        d = 100.0 * self.horizontal_m
        return f"({d[0]:+.1f}, {d[1]:+.1f}, {d[2]:+.1f}) cm (+-{100.0 * self.sigma_m:.1f})"


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products of (n,4) scalar-last quaternions."""
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=1)


def _prefix_rotations(steps: np.ndarray) -> np.ndarray:
    """Inclusive prefix products ``s_0 s_1 ... s_k`` of (n,4) quaternions (Hillis-Steele:
    log2(n) batched steps instead of n sequential ones)."""
    q = steps.copy()
    shift = 1
    while shift < len(q):
        q[shift:] = _quat_mul(q[:-shift], q[shift:])
        shift *= 2
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _cumulative(t: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Trapezoid cumulative integral of samples ``f`` (n, ...) at ``t`` (n,), 0 at ``t[0]``."""
    h = np.diff(t).reshape((-1,) + (1,) * (f.ndim - 1))
    return np.concatenate([np.zeros((1,) + f.shape[1:]),
                           np.cumsum(0.5 * (f[1:] + f[:-1]) * h, axis=0)])


def _interp(t_query: np.ndarray, t: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Linear interpolation of (n, ...) samples along the first axis."""
    flat = f.reshape(len(t), -1)
    out = np.stack([np.interp(t_query, t, flat[:, i]) for i in range(flat.shape[1])], axis=1)
    return out.reshape((len(t_query),) + f.shape[1:])


def estimate_translation(t_scan_s: np.ndarray, R_scan: np.ndarray, p_scan: np.ndarray,
                         t_imu_s: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                         gravity_world_m_s2: np.ndarray, offset_s: float,
                         span_s: float) -> TranslationEstimate | None:
    """``δ`` from the IMU's LiDAR-only orientations ``R_scan`` (N,3,3) and positions ``p_scan``
    (N,3) at ``t_scan_s``, the gyro and accelerometer samples (stamps running ``offset_s``
    late) and the world's gravity vector. None: too few triples, or too little rotation to
    tell a translation."""
    t_imu = np.asarray(t_imu_s, dtype=np.float64) - offset_s
    if t_imu.size < 4 or len(t_scan_s) < 3:
        return None
    dt = np.diff(t_scan_s)
    good = (dt > MIN_PAIR_S) & (dt < MAX_PAIR_S)
    if not np.any(good):
        return None
    m = max(1, round(STRIDE_S / float(np.median(dt[good]))))
    bad_before = np.concatenate([[0], np.cumsum(~good)])
    a = np.arange(len(t_scan_s) - 2 * m)
    c = a + 2 * m
    ok = (bad_before[c] == bad_before[a]) & (t_scan_s[a] >= t_imu[0]) & (t_scan_s[c] <= t_imu[-1])
    a = a[ok]
    if a.size < MIN_TRIPLES:
        return None
    b, c = a + m, a + 2 * m
    # the gyro's bias: the median difference to the LiDAR-only rate between consecutive scans
    k = np.flatnonzero(good & (t_scan_s[:-1] >= t_imu[0]) & (t_scan_s[1:] <= t_imu[-1]))
    w_lidar, w_gyro = pair_rates(R_scan[k], R_scan[k + 1], t_scan_s[k], t_scan_s[k + 1], dt[k],
                                 t_imu, gyro_rad_s)
    b_g = np.median(w_gyro - w_lidar, axis=0)
    # the gyro's orientation track Q (from the first sample) and the accelerometer through it
    w_mid = 0.5 * (gyro_rad_s[1:] + gyro_rad_s[:-1]) - b_g
    steps = Rotation.from_rotvec(w_mid * np.diff(t_imu)[:, None]).as_quat()
    Q = np.concatenate([[[0.0, 0.0, 0.0, 1.0]], _prefix_rotations(steps)])
    Qm = Rotation.from_quat(Q).as_matrix()
    F = np.einsum("nij,nj->ni", Qm, accel_m_s2)
    F1, K1 = _cumulative(t_imu, F), _cumulative(t_imu, Qm)
    F2, K2 = _cumulative(t_imu, F1), _cumulative(t_imu, K1)

    def Q_at(t: np.ndarray) -> np.ndarray:
        """The track at scan times: its sample before, turned on at that interval's rate."""
        j = np.clip(np.searchsorted(t_imu, t, side="right") - 1, 0, len(w_mid) - 1)
        turn = Rotation.from_rotvec(w_mid[j] * (t - t_imu[j])[:, None])
        return (Rotation.from_quat(Q[j]) * turn).as_matrix()

    def double_integral(i: np.ndarray, j: np.ndarray):
        """World-frame accelerometer integrated twice from rest at scans i to scans j, and its
        derivative against the accelerometer's bias (negated)."""
        ti, tj = t_scan_s[i], t_scan_s[j]
        A = np.einsum("nij,nkj->nik", R_scan[i], Q_at(ti))  # R_i Q(t_i)ᵀ
        dF = _interp(tj, t_imu, F2) - _interp(ti, t_imu, F2) \
            - _interp(ti, t_imu, F1) * (tj - ti)[:, None]
        dK = _interp(tj, t_imu, K2) - _interp(ti, t_imu, K2) \
            - _interp(ti, t_imu, K1) * (tj - ti)[:, None, None]
        return np.einsum("nij,nj->ni", A, dF), np.einsum("nij,njk->nik", A, dK)

    D_ab, J_ab = double_integral(a, b)
    D_ac, J_ac = double_integral(a, c)
    d1 = (t_scan_s[b] - t_scan_s[a])[:, None]
    d2 = (t_scan_s[c] - t_scan_s[a])[:, None]
    g = np.asarray(gravity_world_m_s2, dtype=np.float64)
    r = ((p_scan[c] - p_scan[a] - D_ac - 0.5 * g * d2**2) / d2
         - (p_scan[b] - p_scan[a] - D_ab - 0.5 * g * d1**2) / d1)
    n = a.size
    H = np.zeros((n, 3, 9))
    H[:, :, :3] = (R_scan[c] - R_scan[a]) / d2[:, :, None] - (R_scan[b] - R_scan[a]) / d1[:, :, None]
    H[:, :, 3:6] = -(J_ac / d2[:, :, None] - J_ab / d1[:, :, None])  # the bias, subtracted
    H[:, :, 6:] = 0.5 * (d2 - d1)[:, :, None] * np.eye(3)            # a gravity correction
    up = np.einsum("nji,j->ni", R_scan[a], -g / np.linalg.norm(g)).mean(axis=0)
    try:
        return _fit(r, H, m, span_s, up / np.linalg.norm(up))
    except np.linalg.LinAlgError:  # no motion to tell the bias from gravity, or no rotation
        return None


def _fit(r: np.ndarray, H: np.ndarray, m: int, span_s: float,
         up_imu: np.ndarray) -> TranslationEstimate | None:
    """Huber-weighted least squares of the triples' residuals ``r`` (n,3) on ``H`` (n,3,9)
    [lever arm, accelerometer bias, gravity] (``m`` scans apart, the rig's vertical
    ``up_imu``); None without the rotation to tell a lever arm."""
    fit = huber_least_squares(r, H, 3, iterations=5, min_excitation=1e-9,
                              lags=NEWEY_WEST_LAGS + 2 * m, huber_k=HUBER_K)
    if fit is None:
        return None  # the rig did not turn enough to tell a translation
    x, cov_d = fit
    n = len(r)
    return TranslationEstimate(delta_m=x[:3], cov_m2=0.5 * (cov_d + cov_d.T),
                               span_s=float(span_s), n_triples=int(n), up_imu=up_imu)

