"""The LiDAR-IMU rotation in the config against the data: does the gyro turn about the axes the
LiDAR turns about?

A rig's extrinsic rotation (``sensor.T_imu_lidar``) taken from a drawing or a datasheet is often
off by a degree. The filter trusts its gyro for the rotation between scans, and a rotation
error turns the gyro's axes against the LiDAR's, so every turn registers a little off and the
map leans: measured on the simulated hall and corridor (XT-32 at 512 columns, HILTI IMU noise),
1° off costs 0.26 -> 0.84 cm and 1.0 -> 3.1 cm ATE, and the reported sigmas then covered 6-9 %
of the scans' errors on one or two axes (README, "LiDAR-IMU rotation"), until they took the
extrinsic's own uncertainty, narrowed by this check's estimate (:mod:`adalio.lio.extrinsic_sigma`).

What measures it (hand-eye calibration of the rotation, as LI-Init does with a LiDAR-only
odometry): the IMU time offset check's data (:class:`adalio.lio.time_offset.TimeOffsetCheck`),
the orientation the LiDAR alone registers at each scan end, mapped into the IMU frame through
the configured extrinsic. Between consecutive scans that is a mean angular rate ``ω_L``; the
gyro gives ``ω_G`` over the same interval (shifted by the time offset found). With the true
extrinsic rotation ``E R_c`` (``R_c`` the configured one), ``ω_G = E ω_L + S ω_L + b``; a small
``E = Exp(θ)``, a symmetric ``S`` and a constant gyro bias ``b`` minimise the difference
(Gauss-Newton, Huber weights). ``S`` is what the LiDAR-only registration leaves of a turn
unregistered, axis by axis. A registration that follows the sensor's turn about one axis less
than about another differs from the gyro by a symmetric map, and where the turns about two axes
are correlated, as a hand's are, a fit of ``E`` alone reads it as an axis rotation. Measured on
the VLP-16 at 5 Hz in the hall with the right extrinsic (session 79): ``S``'s largest entry
0.6-0.8 % over the first 50-70 scan pairs of seed 1, whose ``E``-only first estimate was 0.41°
and whose restarts left the extrinsic 0.71° off; 2 of 3 seeds restarted for a rotation that was
not there (0.46°, 0.71°), none with ``S``. A rotation of the axes is antisymmetric, so it stays
``θ``'s; ``S`` costs it a little precision (1° off, XT-32 at 512 columns, four scenes: 0.21°
left on average over the 14 restarts, against 0.20°). Its covariance is the sandwich form with
the scores' autocorrelation allowed for (Newey-West over ``NEWEY_WEST_LAGS`` pairs): consecutive
orientations share their map.

As with the time offset, the estimate sees only part of a rotation error (0.6-0.8 of it,
measured): the map was built from poses that followed the gyro through the wrong rotation. It
is unbiased at zero, so it tells an error from none; ``pipeline.run_bag`` finds the value by
re-running the first scans with corrected rotations until what is left is within
``PASS_TOLERANCE_RAD`` or one standard deviation (:func:`next_rotation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from adalio.lio.time_offset import MAX_PAIR_S, MIN_PAIR_S, long_run_covariance

MIN_ROTATION_RAD = np.deg2rad(0.2)
"""Smaller estimates are not acted on: the passes leave 0.1-0.3° at best (README, "LiDAR-IMU
rotation"), so a restart for less would not leave the extrinsic measurably better."""
SIGNIFICANCE = 4.0
"""... nor are estimates within this many standard deviations (along their axis) of zero."""
SIGMA_DONE_RAD = np.deg2rad(0.05)
"""The check concludes once the estimate's largest standard deviation is at most this."""
SIGMA_SIGNIFICANT_RAD = np.deg2rad(0.15)
"""... or once its estimate is significant with a standard deviation of at most this."""
SIGMA_LAST_RAD = np.deg2rad(0.3)
"""At its last look (``MAX_SPAN_S`` or the end of the data) a significant estimate concludes with
a standard deviation up to this (``RotationEstimate.conclusive_at_last``): the walks by hand
that turned too little about one axis to settle sooner end at 0.16-0.21° (session 63); a robot,
which turns about one axis only, at 1.2-2.4°, where a 4-deviation excursion is no rotation (one
ended at 11.8° ±2.3)."""
HUBER_K = 2.5
_SYM_ROWS = np.array([0, 1, 2, 0, 0, 1])
_SYM_COLS = np.array([0, 1, 2, 1, 2, 2])
"""``S``'s six parameters (xx, yy, zz, xy, xz, yz): entry ``k`` sits at (row, col) and its
mirror (col, row)."""
SHEAR_PRIOR = 0.01
"""The prior standard deviation of each entry of ``S``, the share of a turn the LiDAR-only
registration leaves (measured on the VLP-16 at 5 Hz: up to 0.8 %). Where the turns excite an
entry, the data decide it; where they do not (a robot turning about one axis, whose axis tilt
``θ`` and a shear ``S`` would fit alike), the prior keeps ``θ`` an estimate, at no better than
about this (0.6°), where a fit of ``θ`` alone would claim the tilt."""
NEWEY_WEST_LAGS = 10
MIN_PAIRS = 50
"""Fewer scan pairs: no estimate."""
PASS_TOLERANCE_RAD = np.deg2rad(0.05)
"""``run_bag``'s passes go on until the rotation left is within this or one standard deviation
(a rotation below significance still costs: 0.12° left gave the hall 0.36 cm for 0.26)."""
MAX_PASSES = 5
"""``run_bag``'s passes over the first scans to find the rotation (two or three suffice)."""
GAIN_RANGE = (0.2, 1.5)
"""The share of a rotation error the estimate sees, as the passes measure it, is clipped here."""
SEEN_SHARE = 2.0 / 3.0
"""The share of a rotation error the estimate sees, without passes to measure it (0.6-0.8 on
the restarts' first estimates; 0.62-0.87 where 1° was never found, session 62): the reported
sigmas read an estimate ``e`` of covariance ``C`` as the rotation ``e / SEEN_SHARE`` of
covariance ``C / SEEN_SHARE²`` (:mod:`adalio.lio.extrinsic_sigma`)."""


def largest_sigma(cov: np.ndarray) -> float:
    """The largest standard deviation of a covariance (its largest eigenvalue's root)."""
    return float(np.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0)))


def sigma_along(v: np.ndarray, cov: np.ndarray) -> float:
    """The standard deviation of an estimate ``v`` of covariance ``cov`` along its own
    direction (:func:`largest_sigma` at zero): how far it is from zero in its deviations."""
    n = float(np.linalg.norm(v))
    if n == 0.0:
        return largest_sigma(cov)
    u = v / n
    return float(np.sqrt(max(u @ cov @ u, 0.0)))


def pair_rates(R_start: np.ndarray, R_end: np.ndarray, t_start_s: np.ndarray,
               t_end_s: np.ndarray, dt_s: np.ndarray, t_imu_s: np.ndarray,
               gyro_rad_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n,3) mean angular rates over scan pairs ``dt_s`` long: the LiDAR-only one,
    ``Log(R_startᵀ R_end) / dt``, and the gyro's over ``[t_start_s, t_end_s]`` (its own clock;
    the samples trapezoid-integrated, the ends interpolated)."""
    rel = np.einsum("nji,njk->nik", R_start, R_end)
    w_lidar = Rotation.from_matrix(rel).as_rotvec() / dt_s[:, None]
    steps = np.diff(t_imu_s)
    C = np.concatenate([np.zeros((1, 3)),
                        np.cumsum(0.5 * (gyro_rad_s[1:] + gyro_rad_s[:-1]) * steps[:, None],
                                  axis=0)])
    n = len(dt_s)
    ends = np.stack([np.interp(np.r_[t_start_s, t_end_s], t_imu_s, C[:, i])
                     for i in range(3)], 1)
    return w_lidar, (ends[n:] - ends[:n]) / dt_s[:, None]


@dataclass
class RotationEstimate:
    """The residual LiDAR-IMU rotation over the scans checked."""

    rotvec_rad: np.ndarray
    """(3,) ``θ``, the IMU frame's rotation vector of the correction ``Exp(θ)`` that the
    configured ``T_imu_lidar`` rotation needs on its left (``R ← Exp(θ) R``)."""
    cov_rad2: np.ndarray
    """(3,3) its covariance."""
    span_s: float
    n_pairs: int

    @property
    def angle_rad(self) -> float:
        return float(np.linalg.norm(self.rotvec_rad))

    @property
    def sigma_rad(self) -> float:
        """The standard deviation along the estimate's axis (the largest one at zero)."""
        return sigma_along(self.rotvec_rad, self.cov_rad2)

    @property
    def significant(self) -> bool:
        return self.angle_rad >= max(MIN_ROTATION_RAD, SIGNIFICANCE * self.sigma_rad)

    @property
    def settled(self) -> bool:
        """Within ``PASS_TOLERANCE_RAD`` or one standard deviation of zero (passes stop)."""
        return self.angle_rad <= max(PASS_TOLERANCE_RAD, self.sigma_rad)

    @property
    def conclusive(self) -> bool:
        """Precise enough to call the rotation right, or significant at a usable precision."""
        return largest_sigma(self.cov_rad2) <= SIGMA_DONE_RAD or (
            self.significant and self.sigma_rad <= SIGMA_SIGNIFICANT_RAD)

    @property
    def conclusive_at_last(self) -> bool:
        """At the check's last look: conclusive, or significant with a standard deviation up to
        ``SIGMA_LAST_RAD`` (``run_bag`` weighs the value it then finds by its noise)."""
        return self.conclusive or (self.significant and self.sigma_rad <= SIGMA_LAST_RAD)

    def axis_text(self) -> str:
        """The rotation's unit axis in the IMU frame, as '(x, y, z) of the IMU frame'."""
        a = self.angle_rad
        u = self.rotvec_rad / a if a > 0.0 else np.zeros(3)
        return f"({u[0]:+.2f}, {u[1]:+.2f}, {u[2]:+.2f}) of the IMU frame"


def _symmetric(s: np.ndarray) -> np.ndarray:
    """``S`` from its six parameters ``s`` (``_SYM_ROWS``, ``_SYM_COLS``)."""
    S = np.zeros((3, 3))
    S[_SYM_ROWS, _SYM_COLS] = s
    S[_SYM_COLS, _SYM_ROWS] = s
    return S


def estimate_rotation(t_scan_s: np.ndarray, R_scan: np.ndarray, t_imu_s: np.ndarray,
                      gyro_rad_s: np.ndarray, offset_s: float,
                      span_s: float) -> RotationEstimate | None:
    """The correction ``θ`` from orientations ``R_scan`` (N,3,3; the IMU's, LiDAR-only) at
    ``t_scan_s`` and gyro samples whose stamps run ``offset_s`` late: ``mean gyro over
    [t_{k-1} + τ, t_k + τ] = Exp(θ) Log(R_{k-1}ᵀ R_k) / Δt_k + b``. None: too few pairs, or
    too little rotation about two axes to tell an axis. The data as
    :meth:`adalio.lio.time_offset.TimeOffsetCheck.samples` gives them, paired as that check
    pairs them."""
    if t_imu_s.size < 4:
        return None
    dt = np.diff(t_scan_s)
    a, b = t_scan_s[:-1] + offset_s, t_scan_s[1:] + offset_s
    ok = (dt > MIN_PAIR_S) & (dt < MAX_PAIR_S) & (a >= t_imu_s[0]) & (b <= t_imu_s[-1])
    idx = np.flatnonzero(ok)
    if idx.size < MIN_PAIRS:
        return None
    w_lidar, w_gyro = pair_rates(R_scan[idx], R_scan[idx + 1], a[idx], b[idx], dt[idx],
                                 t_imu_s, gyro_rad_s)
    n = idx.size
    theta = np.zeros(3)
    bias = np.median(w_gyro - w_lidar, axis=0)
    weights = np.ones(n)
    # columns: θ (3), the bias (3), S's parameters ``s`` (6), whose prediction S ω_L is linear
    # with these constant columns
    J = np.zeros((n, 3, 12))
    J[:, :, 3:6] = np.eye(3)
    J[:, _SYM_ROWS, 6 + np.arange(6)] = w_lidar[:, _SYM_COLS]
    J[:, _SYM_COLS, 6 + np.arange(6)] = w_lidar[:, _SYM_ROWS]
    s = np.zeros(6)
    for _ in range(10):
        w_rot = Rotation.from_rotvec(theta).apply(w_lidar)
        r = w_gyro - w_rot - w_lidar @ _symmetric(s) - bias  # S symmetric: (S ω)ᵀ = ωᵀ S
        norm = np.linalg.norm(r, axis=1)
        scale = 1.4826 * float(np.median(norm)) / np.sqrt(3.0) + 1e-12
        z = norm / scale
        weights = np.where(z < HUBER_K, 1.0, HUBER_K / np.maximum(z, 1e-12))
        # ∂(Exp(δ) Exp(θ) ω)/∂δ = −[Exp(θ) ω]×
        J[:, 0, 1], J[:, 0, 2] = w_rot[:, 2], -w_rot[:, 1]
        J[:, 1, 0], J[:, 1, 2] = -w_rot[:, 2], w_rot[:, 0]
        J[:, 2, 0], J[:, 2, 1] = w_rot[:, 1], -w_rot[:, 0]
        # S's prior, N(0, SHEAR_PRIOR² I) per entry, as pseudo-rows weighted like the data's
        prior = (scale / SHEAR_PRIOR) ** 2
        A = np.einsum("n,nki,nkj->ij", weights, J, J)
        A[6:, 6:] += prior * np.eye(6)
        g = np.einsum("n,nki,nk->i", weights, J, r)
        g[6:] -= prior * s
        lam = np.linalg.eigvalsh(A[:3, :3] - A[:3, 3:] @ np.linalg.solve(A[3:, 3:], A[3:, :3]))
        if not lam[0] > 1e-9 * max(lam[-1], 1e-300) or not lam[-1] > 0.0:
            return None  # the rotation turned about one axis only (or not at all)
        step = np.linalg.solve(A, g)
        theta = (Rotation.from_rotvec(step[:3]) * Rotation.from_rotvec(theta)).as_rotvec()
        bias = bias + step[3:6]
        s = s + step[6:]
        if np.linalg.norm(step[:3]) < 1e-7:
            break
    w_rot = Rotation.from_rotvec(theta).apply(w_lidar)
    r = w_gyro - w_rot - w_lidar @ _symmetric(s) - bias
    score = weights[:, None] * np.einsum("nki,nk->ni", J, r)
    A_inv = np.linalg.inv(A)
    omega = long_run_covariance(score, NEWEY_WEST_LAGS)
    omega[6:, 6:] += scale**2 * prior * np.eye(6)  # the prior's own share of the scores
    cov = A_inv @ omega @ A_inv
    naive = scale**2 * A_inv
    cov_theta = cov[:3, :3] if np.trace(cov[:3, :3]) >= np.trace(naive[:3, :3]) else naive[:3, :3]
    return RotationEstimate(rotvec_rad=theta, cov_rad2=0.5 * (cov_theta + cov_theta.T),
                            span_s=float(span_s), n_pairs=int(n))



def pass_gain(tried: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """The share of a correction that the rotation left falls by (the estimate's gain), from the
    (correction, rotation left) pairs so far: measured along the last step between two passes
    (a secant, clipped to ``GAIN_RANGE``), 1 before the second pass."""
    if len(tried) < 2:
        return 1.0
    (c0, e0), (c1, e1) = tried[-2], tried[-1]
    d = c1 - c0
    dd = float(d @ d)
    return float(np.clip((e0 - e1) @ d / dd, *GAIN_RANGE)) if dd > 0.0 else 1.0


def next_rotation(tried: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The next correction to try (a rotation vector, rad), from the (correction, rotation
    left) pairs so far, the first at correction zero: the last correction plus the rotation it
    left over the estimate's gain (:func:`pass_gain`)."""
    c1, e1 = tried[-1]
    return c1 + e1 / pass_gain(tried)
