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

A gross error (tens of degrees: axes mixed up) the filter's map follows so far that the estimate
sees a few degrees of it. :func:`estimate_gross_rotation` measures the whole rotation against a
registration made without the gyro (``Odometry`` runs one over the first ``GROSS_SPAN_S`` after
a still start); ``Odometry`` concludes on it only where the estimate here is significant too,
and ``run_bag`` restarts from the rotation it finds before the passes above (README,
"LiDAR-IMU rotation", *Gross errors*).
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



GROSS_MIN_RAD = np.deg2rad(10.0)
"""The gross check (:func:`estimate_gross_rotation`) acts on rotations of at least this. Smaller
ones are the fine check's: its passes found 5° on both hall walks tried, 10° on one of two and
15° on neither (session 80). With the right extrinsic the gross estimate (at 10 s, with a
deviation within ``GROSS_SIGMA_MAX_RAD``) was up to 12.6° off (the OS1-64's shaft): so the
gross check also asks the fine check's estimate to be significant (``Odometry``), which with
the right extrinsic it was on none of session 80's walks."""
GROSS_SIGNIFICANCE = 5.0
"""... and of at least this many of its largest standard deviations (the fine check asks 4)."""
GROSS_SIGMA_MAX_RAD = np.deg2rad(2.0)
"""... and only with a largest standard deviation of at most this, so that what the correction
leaves (a few of these) is within what the fine check finds. Where the rig hardly turned about
an axis, or the gyro-free registration is poor, the estimate is no estimate, however far its
angle is from zero in deviations (at 10 s, the right extrinsic, session 80: robots turning
about the vertical 59-177° at 4.3-5.0°, the VLP-16's corridor 132-134° at 3.4°, the XT-32's
shaft 14-21° at 2.7-3.6°, the VLP-16's hall 16-17° at 2.9°). The XT-32's and the OS1-64's hand
walks outside the shaft had 0.3-1.6°."""
GROSS_CERTAIN_RAD = np.deg2rad(30.0)
GROSS_CERTAIN_SIGMA_RAD = np.deg2rad(1.0)
"""A gross estimate of at least ``GROSS_CERTAIN_RAD`` with a deviation of at most this is acted
on without the fine check's agreement: where the configured rotation is that far off, the
filter's LiDAR-only rotations are themselves no measure (a quaternion given w first, 120° off:
4.3° ±1.7 from the fine check, not significant, where the gross estimate was 117.6° ±0.7). With
the right extrinsic, 14 of session 80's 42 runs had a gross estimate with a deviation of at
most 1°, and those were at most 3.3°."""
GROSS_MIN_SPAN_S = 5.0
"""The gross check concludes at the end of a recording with at least this many seconds of
gyro-free registrations ..."""
GROSS_SPAN_S = 10.0
"""... and otherwise this many seconds after the still start, when the fine checks may first
conclude (their ``MIN_SPAN_S``; they wait for it). Its estimates over the first 5-7 s were up
to twice as far off with the right extrinsic (11.8° against 5.4° on the XT-32's hall at 2000
columns, session 80)."""
GROSS_LAG_HALF_WIDTH_S = 0.2
GROSS_LAG_STEP_S = 5.0e-3
"""The lag grid of the gross fit: the gyro-free registration follows the turn some 75 ms late
(the best lag -75 ms, session 80), on top of the IMU's own time offset (the fine check's grid
is as wide)."""


@dataclass
class GrossRotation:
    """The LiDAR-IMU rotation from a registration without the gyro
    (:func:`estimate_gross_rotation`)."""

    correction: np.ndarray
    """(3,3) the rotation the configured ``T_imu_lidar`` rotation needs on its left."""
    cov_rad2: np.ndarray
    """(3,3) the covariance of a small rotation on the left of ``correction``."""
    lag_s: float
    """The lag of the gyro's stamps on the registration's that fits best (negative: the
    registration follows the turn late); not the IMU's time offset, the registration has its
    own."""
    span_s: float
    n_pairs: int
    fine_rad: float = float("nan")
    """Where it concluded on a gross error with the fine check's significant estimate: that
    estimate's angle, and its standard deviation ``fine_sigma_rad`` (NaN: it was beyond doubt
    alone, ``certain``)."""
    fine_sigma_rad: float = float("nan")

    @property
    def angle_rad(self) -> float:
        return float(Rotation.from_matrix(self.correction).magnitude())

    @property
    def sigma_rad(self) -> float:
        """The largest standard deviation (the significance is judged on it, whatever the axis)."""
        return largest_sigma(self.cov_rad2)

    @property
    def gross(self) -> bool:
        """A rotation error too large for the fine check: at least ``GROSS_MIN_RAD`` and
        ``GROSS_SIGNIFICANCE`` deviations, with deviations of at most ``GROSS_SIGMA_MAX_RAD``."""
        return (self.sigma_rad <= GROSS_SIGMA_MAX_RAD
                and self.angle_rad >= max(GROSS_MIN_RAD, GROSS_SIGNIFICANCE * self.sigma_rad))

    @property
    def certain(self) -> bool:
        """Gross beyond doubt: ``GROSS_CERTAIN_RAD`` at a deviation of at most
        ``GROSS_CERTAIN_SIGMA_RAD`` (acted on without the fine check's agreement)."""
        return (self.gross and self.sigma_rad <= GROSS_CERTAIN_SIGMA_RAD
                and self.angle_rad >= GROSS_CERTAIN_RAD)

    def text(self) -> str:
        return f"{np.degrees(self.angle_rad):.1f} deg (+-{np.degrees(self.sigma_rad):.1f})"

    def evidence(self) -> str:
        """What said so, for a warning."""
        fine = ("" if not np.isfinite(self.fine_rad) else
                f"the filter's LiDAR-only rotation disagrees with the gyro "
                f"({np.degrees(self.fine_rad):.2f} deg, +-{np.degrees(self.fine_sigma_rad):.2f}), "
                "and ")
        return (f"{fine}a LiDAR registration that never used the gyro turns about other axes "
                f"than the gyro over the first {self.span_s:.0f} s")


def _polar_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation factor of ``M`` (the nearest rotation: ``M = U P``, ``P`` symmetric; its
    sign fixed so that it is a rotation even where ``M`` mirrors)."""
    W, _, Vt = np.linalg.svd(M)
    return W @ np.diag([1.0, 1.0, np.sign(np.linalg.det(W @ Vt))]) @ Vt


def estimate_gross_rotation(t_scan_s: np.ndarray, R_scan: np.ndarray, t_imu_s: np.ndarray,
                            gyro_rad_s: np.ndarray, span_s: float) -> GrossRotation | None:
    """The LiDAR-IMU rotation, however large its error, from orientations ``R_scan`` (N,3,3;
    the IMU's through the configured extrinsic) that a registration made without the gyro
    (``motion_init.MovingInit(use_gyro=False)``), against gyro samples.

    The fine check (:func:`estimate_rotation`) reads the filter's LiDAR-only steps, whose map
    followed the gyro through the configured rotation: it sees a share of a small error, and
    of a gross one almost nothing (a LiDAR 90° off about its axis: 14°, session 80). A
    registration that never used the gyro sees the whole rotation, through its own
    distortion: without the gyro it neither deskews nor predicts a turn, and it follows the
    turn about the axes its scans constrain weakly by less (a VLP-16 by up to a factor 2.7).
    So for each lag on a grid (the registration follows the turn some 75 ms late), the linear
    map ``M`` and bias with ``ω_G = M ω_L + b`` over the scan pairs' mean rates are fitted by
    least squares, and the lag that fits best is taken; the rotation is ``M``'s rotation
    factor (``M = U P``, :func:`_polar_rotation`): a distortion by a symmetric gain ``P`` on the
    LiDAR's side leaves it exact (a closed-form rotation fit of the rates alone, Kabsch's, was
    28° off on the VLP-16's hall over 10 s, this one 16°).

    The covariance takes the gyro as the regressor: its mean rates over a scan pair are
    precise where the gyro-free registration's are not. A small rotation ``δ`` on the left
    moves the prediction by ``−[ω_G − b]× δ``, which holds no information about a turn about
    the axis the gyro turned about; the residuals are the fit's. The sandwich form with
    Newey-West over ``NEWEY_WEST_LAGS`` pairs, or the plain ``spread² A⁻¹``, whichever is
    larger. With the LiDAR's rates as the regressor, their noise about the other axes passed
    for information: a robot turning about the vertical gave 117-175° at 3.5-6.5° deviations.
    None: too few pairs, or no turn about two axes at all."""
    if t_imu_s.size < 4 or t_scan_s.size < 2:
        return None
    dt = np.diff(t_scan_s)
    best: tuple[float, float, np.ndarray, np.ndarray, np.ndarray] | None = None
    for lag in np.arange(-GROSS_LAG_HALF_WIDTH_S, GROSS_LAG_HALF_WIDTH_S + 1e-12,
                         GROSS_LAG_STEP_S):
        a, b = t_scan_s[:-1] + lag, t_scan_s[1:] + lag
        idx = np.flatnonzero((dt > MIN_PAIR_S) & (dt < MAX_PAIR_S) & (a >= t_imu_s[0])
                             & (b <= t_imu_s[-1]))
        if idx.size < MIN_PAIRS:
            continue
        w_lidar, w_gyro = pair_rates(R_scan[idx], R_scan[idx + 1], a[idx], b[idx], dt[idx],
                                     t_imu_s, gyro_rad_s)
        X = np.column_stack([w_lidar, np.ones(idx.size)])
        coef = np.linalg.lstsq(X, w_gyro, rcond=None)[0]
        e = w_gyro - X @ coef
        cost = float(np.mean(np.sum(e * e, axis=1)))
        if best is None or cost < best[1]:
            best = (float(lag), cost, coef[:3].T, e, w_gyro)
    if best is None:
        return None
    lag, _, M, e, w_gyro = best
    g = w_gyro - w_gyro.mean(axis=0)
    A = np.sum(g * g) * np.eye(3) - g.T @ g  # Σ [g]×ᵀ [g]×
    lam = np.linalg.eigvalsh(A)
    if not lam[0] > 1e-12 * max(lam[-1], 1e-300):
        return None
    score = np.cross(g, e)  # [g]×ᵀ e = −g × e, the sign irrelevant to the covariance
    A_inv = np.linalg.inv(A)
    cov = A_inv @ long_run_covariance(score, NEWEY_WEST_LAGS) @ A_inv
    naive = float(np.sum(e * e)) / max(3 * len(e) - 12, 1) * A_inv
    cov = cov if np.trace(cov) >= np.trace(naive) else naive
    return GrossRotation(correction=_polar_rotation(M), cov_rad2=0.5 * (cov + cov.T),
                         lag_s=lag, span_s=float(span_s), n_pairs=len(g))


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
