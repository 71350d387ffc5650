"""Initialization in motion: LiDAR-registered scans aligned against the IMU (moving start).

When no still window appears within ``imu.init_timeout_s`` (a robot already driving, a recording
started late, a hand that never rests), the static initialization of lio-design.md §4 cannot
run. Instead, as in LiDAR-inertial initializers such as LI-Init and the visual-inertial alignment
of VINS-Mono:

1. **Register** each incoming scan against a small local map (one point per
   ``imu.moving_init_map_leaf_m`` cell), LiDAR only: every point is
   deskewed with the raw gyro rotation and a constant-velocity translation (from the previous
   two registrations), then the pose is refined point-to-plane by the iterated update of
   ``ieskf.py`` under a loose prior (the constant-velocity prediction). World = the IMU frame at
   the start of the first scan.
2. **Gyro bias**: the gyro rotation from the window's first scan to each later one,
   ``ΔR_j(b)``, must equal the registered ``R_0ᵀ R_j``; one Gauss-Newton step on
   ``Log(ΔR_j(0)ᵀ R_0ᵀ R_j) = −J_j b`` (J by finite differences of the preintegration).
   A fitted bias beyond 3σ of the prior the filter holds it to after the hand-over (its P₀,
   chi-square at 99.73 %) is refused: it is the registrations' rotation error, not the gyro's
   (a VLP-16 slipping in yaw in a spiral shaft gave fits 0.1-0.17 rad/s off a 0.002 rad/s
   bias, whose hand-overs left the track by 1.3-3.2 m).
3. **Gravity and velocity**: with the bias-corrected preintegration ``Δp_j``, ``Δv_j`` (in the
   first scan's IMU frame), ``p_j = p_0 + v_0 t_j + ½ g t_j² + R_0 Δp_j`` is linear in
   ``(p_0, v_0, g)``; least squares over the window, then ``g`` is scaled to ``|g|`` and
   ``(p_0, v_0)`` solved again. The fit is accepted when its RMS position residual is below
   ``imu.moving_init_max_residual_m``, the unconstrained ``|g|`` is within 10 % of
   ``imu.gravity_m_s2``, and the window's registrations can vouch for the velocity: re-searched
   ``adaptive.probe_step_m`` either way along its weakest translation, a registration restores a
   share of the information it claims there (``odometry.restoring_ratios``, degeneracy.py §4),
   and the median share must reach ``imu.moving_init_min_restoring_ratio``. A registration stuck
   to its map's viewpoint in a corridor passes the first two (the IMU does not see a constant
   velocity) with the velocity along the corridor metres per second off.
3b. **First map**: the last scan, which becomes the filter's first map, is deskewed again with
   the fitted motion (velocity, gravity, gyro bias) instead of the registration's
   finite-difference velocity.
3c. **Nested windows**: the fit is accepted only once the registrations span twice the window
   and the fit over both windows passes the same residual and ``|g|`` tests and agrees with it:
   gravity direction and end velocity within 3σ of the short fit's covariance (chi-square at
   99.73 %; Hausman's test of nested estimators). Over one second a registration that slides
   smoothly along a weak direction (a corridor's axis seen by a 16-ring LiDAR) passes for a
   quadratic, and the fit takes it into gravity and velocity: the VLP-16's corridor walks were
   accepted with gravity 3-4° and velocity 0.4 m/s off at a 3 cm residual, and slid 0.7-0.9 m.
   Over two seconds the slide no longer fits, and the two fits disagree.
3d. **A map the registrations could not vouch for is restarted**: when a full window of
   registrations fails the restoring test, the registration map restarts from the window's last
   scan alone (at its registered pose, so the world frame stays), the next scan is predicted at
   zero velocity (the velocity along the weak direction was not measured), and the fits use
   only the registrations made against the new map. A registration that cannot restore its
   weak direction moves along it with its constant-velocity prediction, and the map it builds
   is stretched or compressed there; once the geometry offers that direction again, the
   registrations lock onto the misplaced copies, restore what they claim, and pass every test
   with the velocity along the weak direction wrong (a Mid-360 walking a corridor at 1.05 m/s
   slid 1.5 times too fast for 10 s, then locked at -0.06 m/s; the filter, handed that velocity
   with a claimed deviation of 0.055 m/s, lost 17.7 m).
4. **Hand-over covariance**: the filter starts from the fit's own uncertainty, not the static
   start's generic one. Position and attitude: the RMS residuals of the two fits (the hand-over
   pose anchors the new map, so it is known to the registration's scatter); velocity at the
   window's end: the least-squares covariance ``σ² (AᵀA)⁻¹`` of the motion fit, ``σ²`` its
   residual variance, through ``v_end = v_0 + g t`` (so gravity's share is in it); gravity
   and velocity also carry the accelerometer bias the fit does not model, at its P₀ (as a
   tilt of ``σ_ba/|g|``, 0.18°, the still start's P₀ for gravity; as a velocity error of
   ``σ_ba`` times the window). The gyro bias
   keeps the static start's P₀: the rotation residuals accumulate the gyro's noise from the
   window's first scan on, so they are correlated and their least-squares covariance is several
   times too small (measured: the bias error is 6-11 of its sigmas on the test walk).

Limits: the accelerometer bias is not separated from gravity (as in the static case); a window
whose registration is degenerate along a direction (a featureless corridor) is refused by the
restoring test, so the start waits for the geometry (the backfill gives the scans before it
their poses); a window too short for the fit to pass waits for more scans.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import pairwise

import numpy as np

from adalio.config import Config, ImuConfig
from adalio.jit import kernel
from adalio.lio import imu, so3
from adalio.lio.ieskf import iterated_update
from adalio.lio.ivox import IVox
from adalio.lio.measurement import points_to_world
from adalio.lio.state import BA, BG, DIM, P_, TH, G, State, V, initial_covariance
from adalio.lio.voxel import voxel_downsample

MIN_SCANS = 5
"""Fewest registered scans a moving-start fit uses."""
MIN_POINTS = 50
"""Scans with fewer downsampled points are not registered."""
PRIOR_SIGMA_P_M = 0.5
PRIOR_SIGMA_TH_RAD = 0.1
"""Loose prior of the LiDAR-only registration around the constant-velocity prediction."""
GRAVITY_NORM_TOLERANCE = 0.1
CHI2_2DOF_3SIGMA = 11.829
CHI2_3DOF_3SIGMA = 14.156
"""Chi-square quantiles at 99.73 % (the 3σ of a normal) with 2 and 3 degrees of freedom: the
nested-window agreement test of a moving start's gravity direction and velocity (step 3c), and
the fitted gyro bias against the filter's prior (step 2)."""


@kernel()
def preintegrate(imu_tau, gyro, accel, b_g, query_tau):
    """Rotation, velocity and position increments from ``query_tau[0]`` to each query time.

    Inputs piecewise constant over each sample interval (mid-point of its two samples, as in
    ``imu.propagate_scan``), no gravity, no accel bias; increments in the frame at
    ``query_tau[0]``. Times in seconds, ascending, within the samples' span.
    """
    m = query_tau.shape[0]
    out_R = np.empty((m, 3, 3))
    out_v = np.empty((m, 3))
    out_p = np.empty((m, 3))
    R = np.eye(3)
    v = np.zeros(3)
    p = np.zeros(3)
    tau = query_tau[0]
    q = 0
    n = imu_tau.shape[0]
    k = 0
    while k < n - 2 and imu_tau[k + 1] <= tau:
        k += 1
    while q < m:
        if query_tau[q] <= tau:
            for i in range(3):
                out_v[q, i] = v[i]
                out_p[q, i] = p[i]
                for j in range(3):
                    out_R[q, i, j] = R[i, j]
            q += 1
            continue
        w = 0.5 * (gyro[k] + gyro[k + 1]) - b_g
        a = 0.5 * (accel[k] + accel[k + 1])
        t_next = query_tau[q]
        if k < n - 2 and imu_tau[k + 1] < t_next:
            t_next = imu_tau[k + 1]
        dt = t_next - tau
        Ra = so3.mul_vec(R, a)
        p = p + v * dt + 0.5 * Ra * dt * dt
        v = v + Ra * dt
        R = so3.mul(R, so3.exp(w * dt))
        tau = t_next
        if k < n - 2 and imu_tau[k + 1] <= tau:
            k += 1
    return out_R, out_v, out_p


@dataclass
class MovingInitResult:
    """State at the end of the last scan of the fitted window (world = IMU at the first scan)."""

    t_ns: int
    R_world_imu: np.ndarray
    p_world_imu_m: np.ndarray
    v_world_m_s: np.ndarray
    gyro_bias_rad_s: np.ndarray
    gravity_world_m_s2: np.ndarray
    residual_m: float
    gravity_norm_fit_m_s2: float
    n_scans: int
    window_s: float
    points_lidar_end: np.ndarray
    """The last scan, deskewed to its end (LiDAR frame) with the fitted velocity, gravity and
    gyro bias (:meth:`MovingInit._deskew_last`), for the first map."""
    rotation_residual_rad: float
    """RMS of the gyro-bias fit's rotation residuals."""
    velocity_cov_m2_s2: np.ndarray
    """(3,3) covariance of ``v_world_m_s``: least squares of the motion fit, plus the
    accelerometer bias's P₀ variance times the window squared (the fit does not model it)."""
    gravity_cov_m2_s4: np.ndarray
    """(3,3) covariance of the unconstrained gravity of the motion fit: least squares, plus the
    accelerometer bias's P₀ variance (it passes for a tilt, as in a still start)."""


@dataclass
class _Registered:
    t_ns: int
    R: np.ndarray
    p: np.ndarray
    restoring: float = float("nan")
    """Restoring ratio of the registration along its weakest translation (NaN: not
    registered, or not probed)."""
    weakest: np.ndarray | None = None
    """That translation's unit direction (world; None: not probed)."""


REST_CHECK_MIN_SCANS = 3
"""Fewest LiDAR-only registrations the rest check (:func:`lidar_rest_check`) judges from: a
line through two points has no residual to measure the registration's scatter with."""


@dataclass
class RestCheck:
    """What LiDAR-only registrations say about a rest the IMU's stillness test claims
    (:func:`lidar_rest_check`)."""

    speed_m_s: float
    """Speed of the straight-line fit of the registered positions."""
    rate_rad_s: float
    """Rotation rate of the straight-line fit of the registered rotations."""
    statistic: float
    """Both rates squared over their variances under rest, summed."""
    limit: float
    """The statistic's quantile under rest at ``imu.still_false_alarm``: 6 times the F
    distribution's with (6, 3(n - 2)) degrees of freedom (the same with ``held_out``)."""
    n_scans: int
    span_s: float
    t_ns: int
    """End of the last registration judged."""
    held_out: np.ndarray | None = None
    """The direction (world, unit) left out of the speed: the registrations' weakest
    translation, where they restore less than ``imu.moving_init_min_restoring_ratio`` of the
    information they claim (None: every direction judged)."""
    restoring: float = float("nan")
    """The registrations' median restoring ratio along their weakest translation (NaN: none
    probed)."""

    @property
    def refuted(self) -> bool:
        """The registrations moved beyond what rest allows: a constant motion the IMU cannot
        tell from rest."""
        return self.statistic > self.limit

    def describe(self) -> str:
        held = ("" if self.held_out is None else
                f"; not along their weakest translation, where they restore "
                f"{self.restoring:.2f} of the information they claim")
        return (f"{self.speed_m_s:.2f} m/s and {np.degrees(self.rate_rad_s):.1f} deg/s over "
                f"{self.n_scans} LiDAR-only registrations in {self.span_s:.2f} s{held} (rest "
                f"allows a statistic of {self.limit:.1f}, got {self.statistic:.1f})")

    def verdict(self) -> str:
        """The initialization report's words for it (``InitReport.lidar_rest``)."""
        if self.refuted:
            return ("a still window was refused: the IMU rested by its test while the LiDAR "
                    "registered " + self.describe())
        return "the LiDAR agrees: " + self.describe()


def lidar_rest_check(scans: list[_Registered], cfg: ImuConfig) -> RestCheck | None:
    """Does a LiDAR-only registration refute the rest an IMU window claims?

    An IMU cannot tell rest from a constant velocity and rotation rate (a robot already
    cruising when its recording starts): both read gravity and the gyro bias alone. The scene
    can: a straight line through the registered positions and rotation vectors against time
    gives the speed ``v`` and rate ``w``, their standard errors ``se`` from the line's
    residuals (pooled over the three axes). Rest as the stillness test defines it moves at most
    ``imu.still_accel_floor_m_s2 x imu.still_block_s`` (the zero-velocity update's 5 mm/s) and
    turns at most ``imu.still_gyro_floor_rad_s``; rest is refuted when
    ``|v|²/(σ_v² + se_v²) + |w|²/(σ_w² + se_w²)`` exceeds its quantile under rest at
    ``imu.still_false_alarm``. With the floors alone it would be chi-square with 6 degrees of
    freedom; with the standard errors, estimated from 3(n - 2) residual degrees of freedom
    each, it is at most 6 F(6, 3(n - 2)) (Student's correction: a chi-square limit refuted
    the rest of three registrations with a 2 mm scatter in 2.4 % of draws, not 0.1 %), whose
    quantile is taken. None with fewer than ``REST_CHECK_MIN_SCANS`` registrations.

    A registration vouches for no motion along a translation whose information it only claims:
    where the scene fixes nothing along it (a corridor seen only by its floor and ceiling, a
    LiDAR tilted on its handle), a registration started from the last two's velocity keeps
    sliding at that velocity, rest or not (2.3 m/s in a still corridor, session 81). So where
    the registrations' median restoring ratio along their weakest translation is below
    ``imu.moving_init_min_restoring_ratio`` (the moving start's test for vouching for a
    velocity), the positions are judged across that direction only (``held_out``, the mean of
    the registrations' own weakest translations), with the limit and the residual degrees of
    freedom as before: one component fewer and a scatter pooled over two axes but divided as
    over three make the test stricter than rest needs (at most 0.5 % false alarms at rest in
    ``tests/lio/test_motion_init.py``), never more lenient than the check without it. Taking
    the exact F(5, 2(n - 2)) instead let a robot driving up the stairwell's flights pass for
    at rest (0.78 m/s across that direction, a statistic of 90.7 against 104.0; session 81),
    where the check without it refused the window."""
    if len(scans) < REST_CHECK_MIN_SCANS:
        return None
    t = np.array([(s.t_ns - scans[0].t_ns) * 1e-9 for s in scans])
    spread = float(((t - t.mean()) ** 2).sum())
    if not spread > 0.0:
        return None
    A = np.column_stack([np.ones_like(t), t])
    R0t = scans[0].R.T
    positions = np.array([s.p for s in scans])
    probed = [s for s in scans if np.isfinite(s.restoring) and s.weakest is not None]
    restoring = float(np.median([s.restoring for s in probed])) if probed else float("nan")
    held_out = None
    if probed and not restoring >= cfg.moving_init_min_restoring_ratio:
        E = np.array([s.weakest for s in probed])
        held_out = np.linalg.eigh(E.T @ E)[1][:, -1]
        positions = positions - np.outer(positions @ held_out, held_out)
    dof = 3 * (len(t) - 2)
    stat, rates = 0.0, []
    floors = ((cfg.still_accel_floor_m_s2 * cfg.still_block_s) ** 2,
              cfg.still_gyro_floor_rad_s ** 2)
    for y, var_rest in ((positions, floors[0]),
                        (np.array([so3.log(R0t @ s.R) for s in scans]), floors[1])):
        coef = np.linalg.lstsq(A, y, rcond=None)[0]
        res = y - A @ coef
        se2 = float((res ** 2).sum()) / dof / spread
        rate = float(np.linalg.norm(coef[1]))
        stat += rate ** 2 / (var_rest + se2)
        rates.append(rate)
    from scipy.special import fdtri

    limit = 6.0 * float(fdtri(6, dof, 1.0 - cfg.still_false_alarm))
    return RestCheck(rates[0], rates[1], stat, limit, len(scans), float(t[-1]),
                     int(scans[-1].t_ns), held_out, restoring)


@dataclass
class _Fit:
    """One motion fit (steps 2-3) over the registered scans ``win``."""

    win: list[_Registered]
    R0: np.ndarray
    b_g: np.ndarray
    g: np.ndarray
    """Gravity scaled to imu.gravity_m_s2 (world = IMU at the first registered scan)."""
    g_norm: float
    """The unconstrained fit's |g|."""
    v0: np.ndarray
    v_end: np.ndarray
    residual: float
    rot_rms: float
    span_s: float
    v_cov: np.ndarray
    g_cov: np.ndarray


class MovingInit:
    """Collects LiDAR-registered scans and IMU samples until a moving-start fit succeeds."""

    def __init__(self, cfg: Config, R_LI: np.ndarray, t_LI: np.ndarray,
                 use_gyro: bool = True) -> None:
        self.cfg = replace(cfg, filter=replace(cfg.filter, plane_within_support=False,
                                               one_ring_max_deg=0.0))
        """The registration uses Faster-LIO's association whatever ``filter.plane_within_support``
        and ``filter.one_ring_max_deg`` say: the fit's acceptance
        (``imu.moving_init_max_residual_m``) was measured with it, and with the support test a
        corridor registration that slides along the axis fits a wrong state within 3 cm (README,
        "Planes within their support")."""
        self.use_gyro = use_gyro
        """False: deskew and predict with zero rotation instead of the gyro, so the
        registration is independent of the gyro (the unit check)."""
        self.R_LI, self.t_LI = R_LI, t_LI
        self.cell_m = min(cfg.map.map_leaf_m, cfg.imu.moving_init_map_leaf_m)
        self.ivox = IVox.from_config(replace(cfg.map, map_leaf_m=self.cell_m, cell_point="first"))
        """The registration map keeps each cell's first point, as when the fit's tests were
        measured (session 34); ``map.cell_point`` is for the filter's map."""
        self.scans: list[_Registered] = []
        self.imu_t_ns = np.empty(0, np.int64)
        self.gyro = np.empty((0, 3))
        self.accel = np.empty((0, 3))
        self.last_points: np.ndarray | None = None
        self._last_scan: tuple[np.ndarray, np.ndarray] | None = None
        """The last registered scan as handed in (points, times), to deskew it again with the
        fitted motion (:meth:`solve`); it was deskewed from the registered scan before it."""
        self.failure = "no scan registered yet"
        self.waiting = False
        """True when the last :meth:`solve` found too short a span of registrations for the
        nested-window check (step 3c): waiting, not a refused fit."""
        self.last_t_ns = np.iinfo(np.int64).min
        """End of the latest scan handed in (int64 ns)."""
        self.n_few_points = 0
        """Scans not registered for having fewer than ``MIN_POINTS`` once downsampled."""
        self.map_since_ns = np.iinfo(np.int64).min
        """End of the scan the registration map was last restarted from (step 3d); the fits use
        only the registrations made against that map."""
        self.n_map_restarts = 0
        """Times the registration map was restarted (step 3d)."""
        self._last_down_world: np.ndarray | None = None
        """The last registered scan's downsampled points (world), to restart the map from."""

    @property
    def starved(self) -> bool:
        """Too few registrations for a fit because scans had too few points: the scans, not the
        IMU, keep the moving start from fitting."""
        return self.n_few_points > 0 and len(self.scans) < MIN_SCANS

    def add_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        if t_ns.size == 0:
            return
        keep = t_ns > (self.imu_t_ns[-1] if self.imu_t_ns.size else np.iinfo(np.int64).min)
        self.imu_t_ns = np.concatenate([self.imu_t_ns, t_ns[keep]])
        self.gyro = np.vstack([self.gyro, gyro[keep]])
        self.accel = np.vstack([self.accel, accel[keep]])
        horizon = self.imu_t_ns[-1] - round(3.0 * self.cfg.imu.moving_init_window_s * 1e9)
        first = int(np.searchsorted(self.imu_t_ns, horizon))
        if first > 0:
            self.imu_t_ns, self.gyro, self.accel = (self.imu_t_ns[first:], self.gyro[first:],
                                                    self.accel[first:])

    # ------------------------------------------------------------------ registration
    def add_scan(self, pts: np.ndarray, t_pts: np.ndarray) -> None:
        """Deskew and register one preprocessed scan (LiDAR frame, absolute int64 ns times)."""
        t_b, t_e = int(t_pts.min()), int(t_pts.max())
        self.last_t_ns = max(self.last_t_ns, t_e)
        if self.imu_t_ns.size < 2 or self.imu_t_ns[0] > t_b:
            self.failure = "no IMU sample before the scans"
            return
        if self.scans:
            last = self.scans[-1]
            t_ref, R0, p0 = last.t_ns, last.R, last.p
            v = self._velocity()
        else:
            t_ref, R0, p0, v = t_b, np.eye(3), np.zeros(3), np.zeros(3)
        if t_e <= t_ref:
            return
        x = State(R=R0.copy(), p=p0.copy(), v=v, R_LI=self.R_LI.copy(), t_LI=self.t_LI.copy(),
                  g=np.array([0.0, 0.0, -1e-9]))
        lo = max(int(np.searchsorted(self.imu_t_ns, t_ref, side="right")) - 1, 0)
        hi = int(np.searchsorted(self.imu_t_ns, t_e, side="right"))
        tau = (self.imu_t_ns[lo:hi] - t_ref) * 1e-9
        rates = self.gyro[lo:hi]
        if not self.use_gyro:
            tau = np.array([min(tau[0], 0.0), (t_e - t_ref) * 1e-9])
            rates = np.zeros((2, 3))
        x_pred, _, rec = imu.propagate(x, np.zeros((DIM, DIM)), tau, rates,
                                       np.zeros_like(rates), 0.0, (t_e - t_ref) * 1e-9,
                                       np.zeros(12))
        pts_e = imu.undistort(pts, (t_pts - t_ref) * 1e-9, rec, x_pred.R, x_pred.p,
                              x_pred.R_LI, x_pred.t_LI)
        general = self.cfg.adaptive.general
        down = voxel_downsample(pts_e, general.voxel_size_m)
        if down.shape[0] < MIN_POINTS:
            self.failure = "scans with too few points to register"
            self.n_few_points += 1
            return
        state = x_pred
        restoring, weakest = float("nan"), None
        if self.scans:
            from adalio.lio.odometry import _Association

            P = np.eye(DIM) * 1e-12
            P[P_, P_] = np.eye(3) * PRIOR_SIGMA_P_M**2
            P[TH, TH] = np.eye(3) * PRIOR_SIGMA_TH_RAD**2
            assoc = _Association(down, self.ivox, self.cfg, general.search_radius_m,
                                 general.plane_margin_m, self.cell_m)
            state = iterated_update(x_pred, P, assoc.measure, self.cfg.filter).state
            if self.use_gyro:  # the unit check never fits
                restoring, weakest = _restoring_along_weakest_translation(
                    assoc, state, self.cfg.adaptive.probe_step_m)
        self._last_down_world = points_to_world(down, state.R, state.p, self.R_LI, self.t_LI)
        self.ivox.add_points(self._last_down_world)
        self.scans.append(_Registered(t_e, state.R.copy(), state.p.copy(), restoring,
                                      weakest))
        self.last_points = pts_e
        self._last_scan = (pts, t_pts)
        if len(self.scans) > 1000:
            del self.scans[:500]

    def _velocity(self) -> np.ndarray:
        if len(self.scans) < 2 or self.scans[-2].t_ns < self.map_since_ns:
            return np.zeros(3)  # the first scan, or the map restarted (step 3d)
        a, b = self.scans[-2], self.scans[-1]
        return (b.p - a.p) / ((b.t_ns - a.t_ns) * 1e-9)

    def _deskew_last(self, v0: np.ndarray, g: np.ndarray, b_g: np.ndarray, t0_ns: int,
                     R0: np.ndarray) -> np.ndarray:
        """The last scan deskewed again to its end, with the fitted motion: the velocity
        ``v0 + g τ + R0 Δv(τ)`` of the fit at the time the scan was deskewed from, the IMU's
        specific force with the fitted gravity, and the gyro with the fitted bias. The
        registration deskewed it with the velocity between its last two registered poses, whose
        noise (the fit's residual over one scan period, 10-30 cm/s) bends the scan by
        centimetres; the filter's first map is this scan."""
        assert self._last_scan is not None
        pts, t_pts = self._last_scan
        prev = self.scans[-2]  # the scan was deskewed from its end (within the fitted window)
        t_ref = prev.t_ns
        tau_imu = (self.imu_t_ns - t0_ns) * 1e-9
        tau_ref = (t_ref - t0_ns) * 1e-9
        dv_ref = preintegrate(tau_imu, self.gyro, self.accel, b_g, np.array([0.0, tau_ref]))[1][1]
        v_ref = v0 + g * tau_ref + R0 @ dv_ref
        t_e = int(t_pts.max())
        x = State(R=prev.R.copy(), v=v_ref, R_LI=self.R_LI.copy(), t_LI=self.t_LI.copy(),
                  b_g=b_g.copy(), g=g.copy(), g_anchor=so3.anchor_frame(g))
        lo = max(int(np.searchsorted(self.imu_t_ns, t_ref, side="right")) - 1, 0)
        hi = int(np.searchsorted(self.imu_t_ns, t_e, side="right"))
        tau = (self.imu_t_ns[lo:hi] - t_ref) * 1e-9
        x_end, _, rec = imu.propagate(x, np.zeros((DIM, DIM)), tau, self.gyro[lo:hi],
                                      self.accel[lo:hi], 0.0, (t_e - t_ref) * 1e-9,
                                      np.zeros(12))
        return imu.undistort(pts, (t_pts - t_ref) * 1e-9, rec, x_end.R, x_end.p, self.R_LI,
                             self.t_LI)

    def rotation_ratio(self, b_g: np.ndarray) -> tuple[float, float]:
        """(k, s): the scale k of the gyro's rotation increments between consecutive
        registered scans against the LiDAR's, ``sqrt(Σ|gyro|² / Σ|lidar|²)`` when the two are
        positively correlated, else NaN (about 1 for a gyro in rad/s, 57 for one reporting deg/s,
        noise included: it scales with the unit too), and the signal s = sqrt(Σ |lidar|²) in rad
        (registration noise, ~0.002 rad per pair, adds little to it, unlike a sum of angles)."""
        scans = [s for s in self.scans if self.imu_t_ns.size and s.t_ns >= self.imu_t_ns[0]]
        if len(scans) < 2:
            return float("nan"), 0.0
        t0 = scans[0].t_ns
        tau_q = np.array([(s.t_ns - t0) * 1e-9 for s in scans])
        dR = preintegrate((self.imu_t_ns - t0) * 1e-9, self.gyro, self.accel, b_g, tau_q)[0]
        gyro = np.array([so3.log(a.T @ b) for a, b in pairwise(dR)])
        lidar = np.array([so3.log(a.R.T @ b.R) for a, b in pairwise(scans)])
        power = float(np.sum(lidar * lidar))
        if not (power > 0 and np.sum(gyro * lidar) > 0):
            return float("nan"), float(np.sqrt(power))
        return float(np.sqrt(np.sum(gyro * gyro) / power)), float(np.sqrt(power))

    # ------------------------------------------------------------------ alignment
    def solve(self) -> MovingInitResult | None:
        """Fit gyro bias, gravity and velocity over the last ``moving_init_window_s``, and
        accept the fit only if the fit over twice that window agrees with it (step 3c)."""
        cfg = self.cfg.imu
        self.waiting = False
        n_fresh = len(self._fresh())
        if n_fresh < MIN_SCANS:
            self.failure = (f"{n_fresh} scans registered"
                            + (" since the registration map restarted" if self.n_map_restarts
                               else "") + f", the fit needs {MIN_SCANS}")
            return None
        short = self._fit(self._window(1))
        if isinstance(short, str):
            self.failure = short
            return None
        probed = np.array([s.restoring for s in short.win if np.isfinite(s.restoring)])
        restoring = float(np.median(probed)) if probed.size else 0.0
        need = cfg.moving_init_min_restoring_ratio
        n = len(short.win)
        if not restoring >= need:
            if short.span_s >= self._span_needed_s(short, 1):
                self._restart_map()
            self.failure = (f"the LiDAR-only registrations of the {n} scans restore "
                            f"{restoring:.2f} (median) of the information they claim along "
                            "their weakest translation (limit "
                            f"imu.moving_init_min_restoring_ratio = {need:g}): "
                            "they cannot vouch for the velocity along it")
            return None
        refusal = self._nested_disagreement(short)
        if refusal:
            self.failure = refusal
            return None
        last = short.win[-1]
        assert self.last_points is not None
        points_end = self._deskew_last(short.v0, short.g, short.b_g, short.win[0].t_ns,
                                       short.R0)
        return MovingInitResult(
            t_ns=last.t_ns, R_world_imu=last.R.copy(), p_world_imu_m=last.p.copy(),
            v_world_m_s=short.v_end, gyro_bias_rad_s=short.b_g, gravity_world_m_s2=short.g,
            residual_m=short.residual, gravity_norm_fit_m_s2=short.g_norm, n_scans=n,
            window_s=short.span_s, points_lidar_end=points_end,
            rotation_residual_rad=short.rot_rms, velocity_cov_m2_s2=short.v_cov,
            gravity_cov_m2_s4=short.g_cov)

    def _fresh(self) -> list[_Registered]:
        """The registrations made against the current map (step 3d): the scan it was
        restarted from and those after it."""
        return [s for s in self.scans if s.t_ns >= self.map_since_ns]

    def _window(self, multiple: int) -> list[_Registered]:
        """The registered scans of the last ``multiple`` fit windows (at least MIN_SCANS),
        among those made against the current map."""
        fresh = self._fresh()
        t_last = fresh[-1].t_ns
        span = round(multiple * self.cfg.imu.moving_init_window_s * 1e9)
        win = [s for s in fresh if s.t_ns >= t_last - span]
        return win if len(win) >= MIN_SCANS else fresh[-MIN_SCANS:]

    def _span_needed_s(self, fit: _Fit, multiple: int) -> float:
        """The span registrations need to count as ``multiple`` full
        ``imu.moving_init_window_s``: the windows count scan ends, so half of ``fit``'s scan
        period is slack."""
        period_s = fit.span_s / max(len(fit.win) - 1, 1)
        return multiple * self.cfg.imu.moving_init_window_s - 0.5 * period_s

    def _restart_map(self) -> None:
        """Step 3d: restart the registration map from the last registered scan alone (at its
        registered pose, so the world frame stays), and fit only the registrations made
        against it from here on."""
        assert self._last_down_world is not None
        self.ivox = IVox.from_config(replace(self.cfg.map, map_leaf_m=self.cell_m,
                                             cell_point="first"))
        self.ivox.add_points(self._last_down_world)
        self.map_since_ns = self.scans[-1].t_ns
        self.n_map_restarts += 1

    def _nested_disagreement(self, short: _Fit) -> str:
        """Step 3c: the reason to refuse ``short``, or "" to accept it.

        Over one window, a registration that slides smoothly (a corridor's axis seen by few
        rings) fits as well as the true walk: its slide is a quadratic the fit takes into
        gravity (several degrees of tilt) and velocity at a residual within the limit. Over
        twice the window the same slide no longer passes for a quadratic. So the registrations
        must span two windows, the fit over both must pass the residual and gravity-norm tests,
        and its gravity direction and end velocity must lie within the short fit's 3σ
        (chi-square at 99.73 %, with the short fit's covariance: the long fit contains the
        short one's data, so the difference has at most that covariance, Hausman's test). That
        covariance includes the accelerometer bias the fits do not model (:meth:`_fit`)."""
        cfg = self.cfg.imu
        wanted_s = 2.0 * cfg.moving_init_window_s
        have_s = (short.win[-1].t_ns - self._fresh()[0].t_ns) * 1e-9
        if have_s < self._span_needed_s(short, 2):
            self.waiting = True
            return (f"the registrations span {have_s:.1f} s; the fit is checked against one "
                    f"over {wanted_s:g} s (twice imu.moving_init_window_s)")
        long = self._fit(self._window(2))
        if isinstance(long, str):
            return f"over {wanted_s:g} s: {long}"
        u = short.g / np.linalg.norm(short.g)
        T = np.eye(3) - np.outer(u, u)
        g_dir = T @ (long.g / np.linalg.norm(long.g) - u)  # on the tangent plane, radians
        C_dir = T @ short.g_cov @ T / float(short.g @ short.g)
        d_g = float(g_dir @ np.linalg.pinv(C_dir, hermitian=True) @ g_dir)
        dv = long.v_end - short.v_end
        d_v = float(dv @ np.linalg.inv(short.v_cov) @ dv)
        if d_g > CHI2_2DOF_3SIGMA or d_v > CHI2_3DOF_3SIGMA:
            return (f"the fit over {len(short.win)} scans disagrees with the fit over "
                    f"{wanted_s:g} s ({len(long.win)} scans): gravity "
                    f"{np.degrees(np.linalg.norm(g_dir)):.1f} deg and velocity "
                    f"{np.linalg.norm(dv):.2f} m/s apart, beyond 3 sigma of the shorter fit "
                    "(a registration sliding along a weak direction)")
        return ""

    def _fit(self, win: list[_Registered]) -> _Fit | str:
        """Steps 2-3 over ``win``: the fit, or why it is refused (IMU missing, residual,
        gravity norm)."""
        cfg = self.cfg.imu
        t0 = win[0].t_ns
        if self.imu_t_ns[0] > t0:
            return "IMU samples missing in the window"
        tau_imu = (self.imu_t_ns - t0) * 1e-9
        tau_q = np.array([(s.t_ns - t0) * 1e-9 for s in win])
        R0 = win[0].R
        rel = np.array([so3.log(R0.T @ s.R) for s in win])

        def rot_err(b: np.ndarray) -> np.ndarray:
            dR = preintegrate(tau_imu, self.gyro, self.accel, b, tau_q)[0]
            return np.concatenate([so3.log(dR[j].T @ so3.exp(rel[j]))
                                   for j in range(1, len(win))])

        b_g = np.zeros(3)
        for _ in range(2):
            e0 = rot_err(b_g)
            eps = 1e-4
            J = np.column_stack([(rot_err(b_g + eps * np.eye(3)[k]) - e0) / eps
                                 for k in range(3)])
            b_g = b_g - np.linalg.lstsq(J, e0, rcond=None)[0]
        # the filter holds the gyro bias to its P0 after the hand-over (step 4): a fitted bias
        # beyond that prior's 3 sigma is the registrations' rotation error, not the gyro's
        P0_bg = initial_covariance(False)[BG, BG]
        d_bg = float(b_g @ np.linalg.solve(P0_bg, b_g))
        if d_bg > CHI2_3DOF_3SIGMA:
            return (f"the gyro bias fitted over {len(win)} scans, "
                    f"{np.degrees(np.linalg.norm(b_g)):.2f} deg/s, lies beyond 3 sigma of the "
                    f"filter's prior ({np.degrees(np.sqrt(np.max(np.diag(P0_bg)))):.2f} deg/s "
                    "per axis): the registrations' rotations disagree with the gyro")
        rot_rms = float(np.sqrt(np.mean(rot_err(b_g) ** 2) * 3))
        _, dv, dp = preintegrate(tau_imu, self.gyro, self.accel, b_g, tau_q)
        P = np.array([s.p for s in win])
        n = len(win)
        eye = np.eye(3)
        A = np.zeros((3 * n, 9))
        for j in range(n):
            A[3 * j:3 * j + 3] = np.hstack([eye, tau_q[j] * eye, 0.5 * tau_q[j] ** 2 * eye])
        rhs = (P - dp @ R0.T).reshape(-1)
        sol = np.linalg.lstsq(A, rhs, rcond=None)[0]
        g_fit = sol[6:9]
        g_norm = float(np.linalg.norm(g_fit))
        if not abs(g_norm - cfg.gravity_m_s2) <= GRAVITY_NORM_TOLERANCE * cfg.gravity_m_s2:
            return (f"the gravity fitted over {n} scans has norm {g_norm:.2f} m/s^2, "
                    f"not {cfg.gravity_m_s2:g}")
        g = g_fit * (cfg.gravity_m_s2 / g_norm)
        rhs_g = rhs - (A[:, 6:9] @ g)
        pv = np.linalg.lstsq(A[:, :6], rhs_g, rcond=None)[0]
        residual = float(np.sqrt(np.mean((A[:, :6] @ pv - rhs_g) ** 2) * 3))
        if not residual <= cfg.moving_init_max_residual_m:
            return (f"the motion fit over {n} scans leaves {residual * 100:.1f} cm RMS "
                    f"(limit imu.moving_init_max_residual_m = "
                    f"{cfg.moving_init_max_residual_m * 100:g} cm)")
        v_end = pv[3:6] + g * tau_q[-1] + R0 @ dv[-1]
        C = _lsq_covariance(A, A @ sol - rhs, 9)
        Jv = np.hstack([np.eye(3), tau_q[-1] * np.eye(3)])
        # the fit does not model the accelerometer bias: within its prior (the filter's P0, as
        # in a still start) it passes for a gravity tilt and, over the window, for a velocity
        var_ba = float(np.mean(np.diag(initial_covariance(False)[BA, BA])))
        span_s = float(tau_q[-1])
        return _Fit(win=win, R0=R0, b_g=b_g, g=g, g_norm=g_norm, v0=pv[3:6], v_end=v_end,
                    residual=residual, rot_rms=rot_rms, span_s=span_s,
                    v_cov=Jv @ C[3:9, 3:9] @ Jv.T + var_ba * span_s**2 * np.eye(3),
                    g_cov=C[6:9, 6:9] + var_ba * np.eye(3))


def _restoring_along_weakest_translation(assoc, x: State,
                                         step_m: float) -> tuple[float, np.ndarray | None]:
    """Restoring ratio (``odometry.restoring_ratios``) of a registration at ``x`` for a
    ``step_m`` shift along the weakest eigenvector of its translation information, and that
    eigenvector (world). 0 and None when the registration has no residual."""
    from adalio.lio.odometry import restoring_ratios

    H, _ = assoc.measure(x, True)
    if H.shape[0] == 0:
        return 0.0, None
    Ht = H[:, :3]
    e = np.linalg.eigh(Ht.T @ Ht)[1][:, 0]
    d = np.concatenate([step_m * e, np.zeros(3)])
    return float(restoring_ratios(assoc, x, d[None])[0]), e


def _lsq_covariance(A: np.ndarray, residual: np.ndarray, n_params: int) -> np.ndarray:
    """``σ² (AᵀA)⁻¹`` of a linear least-squares fit, ``σ²`` = residual sum of squares over
    the degrees of freedom (at least one)."""
    dof = max(A.shape[0] - n_params, 1)
    s2 = float(residual @ residual) / dof
    return s2 * np.linalg.pinv(A.T @ A)


def handover_covariance(fit: MovingInitResult, R_align: np.ndarray,
                        estimate_extrinsic: bool) -> np.ndarray:
    """P₀ of the filter after a moving start (step 4 of the module docstring): the static
    start's P₀ (extrinsic, biases, gravity) with position, attitude and velocity from the
    fit. ``R_align`` rotates the fit's world into the filter's (gravity alignment);
    position and velocity are world-frame errors, attitude body-frame."""
    P = initial_covariance(estimate_extrinsic)
    P[P_, P_] = np.eye(3) * (fit.residual_m**2 / 3.0)
    P[TH, TH] = np.eye(3) * (fit.rotation_residual_rad**2 / 3.0)
    P[V, V] = R_align @ fit.velocity_cov_m2_s2 @ R_align.T
    # gravity's direction from the fit's covariance, on the sphere's tangent: g ⊞ δ ≈ g − [g]× B δ
    g = R_align @ fit.gravity_world_m_s2
    J = -so3.hat(g) @ so3.s2_basis(g, so3.anchor_frame(g))
    P[G, G] = J.T @ (R_align @ fit.gravity_cov_m2_s4 @ R_align.T) @ J / float(g @ g) ** 2
    return P
