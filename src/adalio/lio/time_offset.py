"""The IMU's clock against the LiDAR's: is the gyro's timing the LiDAR's?

An IMU stamped on arrival (USB, a driver's receive time) runs late against the LiDAR's own
stamps by milliseconds to tens of milliseconds. The filter trusts its gyro for the rotation
between scans (``imu.gyro_cov`` is the real white noise), so a late gyro turns the prediction
late, and the map registration pulls the rotation back only partly; measured on the simulated
corridor (XT-32 at 512 columns, HILTI IMU noise): 1.0 cm ATE on time, 2.8 cm at 5 ms late, 9.8
cm at 20 ms and a divergence at 50 ms (README, "IMU time offset").

What measures it (as LI-Init cross-correlates a LiDAR-only odometry's rotation rate with the
gyro): each update's LiDAR-only rotation, the pose block of the last evaluation's normal
equations solved without the prior (``UpdateResult.lidar_step``), gives the orientation the
LiDAR alone sees at the scan end. Between consecutive scans that is a mean angular rate over
``[t_{k-1}, t_k]`` on the LiDAR's clock; the gyro gives the same mean over ``[t_{k-1} + τ,
t_k + τ]`` on its own. The offset ``τ`` (IMU stamp minus LiDAR time) and a constant gyro bias
minimise the difference: a grid over ±``GRID_HALF_WIDTH_S``, then Gauss-Newton with Huber
weights; its standard deviation comes from the residual scale and the angular acceleration's
leverage (no rotation changes, no information).

The estimate sees only part of the offset (0.2-0.65 of it, measured): the map was built from
poses that followed the late gyro and moves with them. It is unbiased at zero (0.1 ± 0.1 ms in
the hall and the corridor on time), so it tells an offset from none; ``pipeline.run_bag`` finds
the value by re-running the first scans with corrected stamps until the estimate is zero
(:func:`next_offset`: a secant, then false position, on the estimate as a function of the
correction). Its standard deviation also allows for the residuals' autocorrelation
(:func:`_long_run_variance`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

MIN_SPAN_S = 10.0
"""Scans (LiDAR-updated) the check looks at before it may conclude (seconds)."""
MAX_SPAN_S = 60.0
"""Without a conclusion by then (too little rotation change to time it), the check stops."""
END_MIN_SPAN_S = 5.0
"""At the end of a recording shorter than MIN_SPAN_S the check concludes from this span on."""
SIGMA_DONE_S = 1.0e-3
"""The check concludes once the estimate's standard deviation is at most this."""
SIGMA_SIGNIFICANT_S = 3.0e-3
"""... or once its estimate is significant with a standard deviation of at most this: the
passes of ``run_bag`` make it precise (a noisy IMU in a floor-blind stairwell reached no 1 ms
within 60 s)."""
MIN_OFFSET_S = 2.0e-3
"""Smaller estimates are not acted on (5 ms late already costs the corridor 1.8 cm)."""
SIGNIFICANCE = 4.0
"""... nor are estimates within this many of their standard deviations of zero."""
MAX_PASSES = 6
"""``run_bag``'s passes over the first scans to find the offset (three or four suffice)."""
SECANT_MAX_GAIN = 4.0
"""The estimate sees 0.2-0.65 of an offset (0.2 once the filter has lost track): a secant step
is at most this many times the offset left."""
GRID_HALF_WIDTH_S = 0.2
GRID_STEP_S = 2.5e-3
HUBER_K = 2.5
RATE_HALF_WINDOW_S = 12.5e-3
"""The gyro rate at an instant: its mean over ± this (for the offset's derivative)."""
IMU_BEFORE_FIRST_SCAN_S = 2.0
"""Gyro kept from before the first update (the grid reaches GRID_HALF_WIDTH_S back)."""
MIN_PAIR_S, MAX_PAIR_S = 0.02, 0.3
"""Consecutive scans further apart (a LiDAR gap) or closer (split sweeps) are not paired."""


@dataclass
class TimeOffsetEstimate:
    """The residual IMU time offset over the scans checked."""

    offset_s: float
    """IMU stamp minus LiDAR time for the same instant, left after ``sensor.imu_time_offset_s``
    (positive: the IMU's stamps run late)."""
    sigma_s: float
    span_s: float
    """Time between the first and the last scan used."""
    n_pairs: int

    @property
    def significant(self) -> bool:
        return abs(self.offset_s) >= max(MIN_OFFSET_S, SIGNIFICANCE * self.sigma_s)

    @property
    def conclusive(self) -> bool:
        """Precise enough to call the IMU on time, or significant at a usable precision."""
        return self.sigma_s <= SIGMA_DONE_S or (self.significant
                                                and self.sigma_s <= SIGMA_SIGNIFICANT_S)


class TimeOffsetCheck:
    """Collects the IMU and the LiDAR-only poses at scan ends; :meth:`estimate`."""

    def __init__(self) -> None:
        self._imu_t: list[np.ndarray] = []
        self._imu_w: list[np.ndarray] = []
        self._imu_a: list[np.ndarray] = []
        self._scan_t: list[int] = []
        self._scan_R: list[np.ndarray] = []
        self._scan_p: list[np.ndarray] = []
        self._scan_rot_sd: list[float] = []

    def add_imu(self, t_ns: np.ndarray, gyro_rad_s: np.ndarray,
                accel_m_s2: np.ndarray | None = None) -> None:
        t = np.asarray(t_ns, dtype=np.int64).ravel().copy()
        self._imu_t.append(t)
        self._imu_w.append(np.asarray(gyro_rad_s, dtype=np.float64).reshape(-1, 3).copy())
        self._imu_a.append(np.full((t.size, 3), np.nan) if accel_m_s2 is None else
                           np.asarray(accel_m_s2, dtype=np.float64).reshape(-1, 3).copy())
        if not self._scan_t:  # before the first update: only the latest samples can be needed
            horizon = int(self._imu_t[-1][-1]) - round(IMU_BEFORE_FIRST_SCAN_S * 1e9)
            while len(self._imu_t) > 1 and int(self._imu_t[1][0]) <= horizon:
                del self._imu_t[0], self._imu_w[0], self._imu_a[0]

    def add_scan(self, t_ns: int, R_world_imu: np.ndarray,
                 p_world_imu: np.ndarray | None = None, rot_sd_rad: float = np.nan) -> None:
        """The LiDAR-only orientation (and position) of the IMU at the scan end ``t_ns``, and
        how well the registration knows that orientation about its weakest axis
        (``rot_sd_rad``, :meth:`rotation_sds`)."""
        if self._scan_t and t_ns <= self._scan_t[-1]:
            return
        self._scan_rot_sd.append(float(rot_sd_rad))
        self._scan_t.append(int(t_ns))
        self._scan_R.append(np.asarray(R_world_imu, dtype=np.float64).copy())
        self._scan_p.append(np.full(3, np.nan) if p_world_imu is None else
                            np.asarray(p_world_imu, dtype=np.float64).copy())

    def rotation_sds(self) -> np.ndarray:
        """(n,) per scan of :meth:`samples`, the standard deviation (rad) of its LiDAR-only
        orientation about its weakest axis (NaN: not given)."""
        return np.asarray(self._scan_rot_sd, dtype=np.float64)

    @property
    def span_s(self) -> float:
        return (self._scan_t[-1] - self._scan_t[0]) * 1e-9 if self._scan_t else 0.0

    def estimate(self) -> TimeOffsetEstimate | None:
        """The offset and its standard deviation, or None (too few scans or IMU samples)."""
        data = self.samples()
        return None if data is None else estimate_offset(*data, self.span_s)

    def samples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """(scan ends s, orientations, IMU stamps s, gyro), times from the first scan end;
        None with fewer than 10 scans or no IMU sample (also the LiDAR-IMU rotation check's
        data, :func:`adalio.lio.extrinsic_check.estimate_rotation`; :meth:`motion_samples` adds
        the positions and the accelerometer for the lever arm check)."""
        data = self.motion_samples()
        return None if data is None else (data[0], data[1], data[3], data[4])

    def motion_samples(self) -> tuple[np.ndarray, ...] | None:
        """(scan ends s, orientations, positions, IMU stamps s, gyro, accelerometer), as
        :meth:`samples` with the LiDAR-only positions and the accelerometer (NaN where they were
        not given; the LiDAR-IMU translation check's data,
        :func:`adalio.lio.lever_arm.estimate_translation`)."""
        if len(self._scan_t) < 10 or not self._imu_t:
            return None
        t_ref = self._scan_t[0]
        t_scan = (np.asarray(self._scan_t, dtype=np.int64) - t_ref) * 1e-9
        R = np.stack(self._scan_R)
        p = np.stack(self._scan_p)
        t_imu, w_imu, a_imu = self.imu_samples()
        return t_scan, R, p, (t_imu - t_ref) * 1e-9, w_imu, a_imu

    def imu_samples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(stamps int64 ns, gyro, accelerometer) of the IMU samples held, in time order, each
        stamp once (also the gross rotation check's gyro,
        :func:`adalio.lio.extrinsic_check.estimate_gross_rotation`)."""
        if not self._imu_t:
            return np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 3))
        t_imu = np.concatenate(self._imu_t)
        w_imu = np.concatenate(self._imu_w)
        a_imu = np.concatenate(self._imu_a)
        order = np.argsort(t_imu, kind="stable")
        t_imu, w_imu, a_imu = t_imu[order], w_imu[order], a_imu[order]
        keep = np.r_[True, np.diff(t_imu) > 0]
        return t_imu[keep], w_imu[keep], a_imu[keep]


def estimate_offset(t_scan_s: np.ndarray, R_scan: np.ndarray, t_imu_s: np.ndarray,
                    gyro_rad_s: np.ndarray, span_s: float) -> TimeOffsetEstimate | None:
    """IMU time offset from orientations ``R_scan`` (N,3,3) at ``t_scan_s`` and gyro samples.

    ``τ`` with ``Log(R_{k-1}ᵀ R_k) / Δt_k = mean gyro over [t_{k-1} + τ, t_k + τ] − b``.
    """
    if t_imu_s.size < 4:
        return None
    dt = np.diff(t_scan_s)
    pairs = (dt > MIN_PAIR_S) & (dt < MAX_PAIR_S)
    a, b = t_scan_s[:-1][pairs], t_scan_s[1:][pairs]
    # the pair must lie within the gyro's span for every shift of the grid
    inside = (a - GRID_HALF_WIDTH_S - RATE_HALF_WINDOW_S >= t_imu_s[0]) & \
             (b + GRID_HALF_WIDTH_S + RATE_HALF_WINDOW_S <= t_imu_s[-1])
    idx = np.flatnonzero(pairs)[inside]
    if idx.size < 10:
        return None
    a, b = t_scan_s[idx], t_scan_s[idx + 1]
    rel = np.einsum("nji,njk->nik", R_scan[idx], R_scan[idx + 1])
    w_lidar = Rotation.from_matrix(rel).as_rotvec() / (b - a)[:, None]
    steps = np.diff(t_imu_s)
    C = np.concatenate([np.zeros((1, 3)),
                        np.cumsum(0.5 * (gyro_rad_s[1:] + gyro_rad_s[:-1]) * steps[:, None],
                                  axis=0)])

    def integral(t: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(t, t_imu_s, C[:, i]) for i in range(3)], axis=1)

    def mean_gyro(tau: float) -> np.ndarray:
        return (integral(b + tau) - integral(a + tau)) / (b - a)[:, None]

    def rate(t: np.ndarray) -> np.ndarray:
        h = RATE_HALF_WINDOW_S
        return (integral(t + h) - integral(t - h)) / (2.0 * h)

    # the gyro's white noise (second differences: 6 sigma^2 for white noise, the motion's own
    # are negligible at IMU rates) makes the rate at an instant noisy, and with it the offset's
    # leverage: that part of the leverage is no information
    d2 = gyro_rad_s[2:] - 2.0 * gyro_rad_s[1:-1] + gyro_rad_s[:-2]
    noise_var = (1.4826 * np.median(np.abs(d2), axis=0)) ** 2 / 6.0 if len(d2) else np.zeros(3)
    per_window = max(1.0, 2.0 * RATE_HALF_WINDOW_S / float(np.median(steps)))
    leverage_noise = float(np.sum(noise_var)) * 2.0 / per_window / (b - a) ** 2

    # coarse: robust cost on a grid (the bias as the residuals' median)
    best_tau, best_cost = 0.0, np.inf
    for tau in np.arange(-GRID_HALF_WIDTH_S, GRID_HALF_WIDTH_S + 1e-12, GRID_STEP_S):
        r = w_lidar - mean_gyro(float(tau))
        r -= np.median(r, axis=0)
        cost = float(np.sum(np.minimum(np.sum(r * r, axis=1), 0.1**2)))
        if cost < best_cost:
            best_tau, best_cost = float(tau), cost
    # fine: Gauss-Newton on (τ, b) with Huber weights
    tau = best_tau
    scale, info = np.inf, 0.0
    for _ in range(8):
        r = w_lidar - mean_gyro(tau)
        D = (rate(b + tau) - rate(a + tau)) / (b - a)[:, None]  # ∂ mean_gyro / ∂τ
        weights = np.ones(len(r))
        for _ in range(3):
            bias = np.average(r, axis=0, weights=weights)
            e = r - bias
            norm = np.linalg.norm(e, axis=1)
            scale = 1.4826 * float(np.median(norm)) / np.sqrt(3.0) + 1e-12
            z = norm / scale
            weights = np.where(z < HUBER_K, 1.0, HUBER_K / np.maximum(z, 1e-12))
        Dc = D - np.average(D, axis=0, weights=weights)
        info = float(np.sum(weights * (np.sum(Dc * Dc, axis=1) - leverage_noise)))
        if info <= 0.0:  # no change of rotation rate beyond the gyro's noise: no timing
            return None
        score = weights * np.sum(Dc * e, axis=1)
        step = float(np.sum(score)) / info
        tau = float(np.clip(tau + step, -GRID_HALF_WIDTH_S, GRID_HALF_WIDTH_S))
        if abs(step) < 1e-5:
            break
    sigma = max(scale / np.sqrt(info), np.sqrt(_long_run_variance(score)) / info)
    return TimeOffsetEstimate(offset_s=tau, sigma_s=float(sigma), span_s=float(span_s),
                              n_pairs=int(idx.size))


def _long_run_variance(score: np.ndarray, lags: int = 10) -> float:
    """Variance of the sum of ``score`` allowing for its autocorrelation (Newey-West, Bartlett
    weights up to ``lags`` pairs): consecutive LiDAR-only orientations share their map and their
    errors, so their residuals are not independent, and the independent form claimed 1.2 ms
    where a robot's walk (few turns, the x10 IMU) moved the estimate by 3-4 ms."""
    return max(float(long_run_covariance(score[:, None], lags)[0, 0]), 0.0)


def long_run_covariance(score: np.ndarray, lags: int) -> np.ndarray:
    """Covariance of the sum of the rows of ``score`` (n, k) allowing for their
    autocorrelation (Newey-West, Bartlett weights up to ``lags`` rows)."""
    s = score - score.mean(axis=0)
    total = s.T @ s
    for lag in range(1, min(lags, len(s) - 1) + 1):
        G = s[lag:].T @ s[:-lag]
        total += (1.0 - lag / (lags + 1.0)) * (G + G.T)
    return total


def huber_least_squares(r: np.ndarray, H: np.ndarray, k: int, *, iterations: int,
                        min_excitation: float, lags: int,
                        huber_k: float = HUBER_K) -> tuple[np.ndarray, np.ndarray] | None:
    """Huber-weighted least squares of residuals ``r`` (n,3) on ``H`` (n,3,p), iterated
    ``iterations`` times (the weights from the residuals' robust spread), then the solution
    and the covariance of its first ``k`` unknowns: the sandwich form with Newey-West over
    ``lags`` rows, or the plain ``spread² A⁻¹`` where that is larger (trace). None where the
    first ``k`` unknowns are not told apart: the smallest eigenvalue of their information (the
    others marginalised) under ``min_excitation`` times its largest. The fit of the lever arm
    and of the gyro's scale (:mod:`adalio.lio.lever_arm`, :mod:`adalio.lio.gyro_scale`)."""
    n = len(r)
    weights = np.ones(n)
    scale = 1.0
    for _ in range(iterations):
        A = np.einsum("n,nki,nkj->ij", weights, H, H)
        lam = np.linalg.eigvalsh(A[:k, :k] - A[:k, k:] @ np.linalg.solve(A[k:, k:], A[k:, :k]))
        if not lam[0] > min_excitation * max(lam[-1], 1e-300) or not lam[-1] > 0.0:
            return None
        x = np.linalg.solve(A, np.einsum("n,nki,nk->i", weights, H, r))
        e = r - np.einsum("nki,i->nk", H, x)
        norm = np.linalg.norm(e, axis=1)
        scale = 1.4826 * float(np.median(norm)) / np.sqrt(3.0) + 1e-12
        z = norm / scale
        weights = np.where(z < huber_k, 1.0, huber_k / np.maximum(z, 1e-12))
    A = np.einsum("n,nki,nkj->ij", weights, H, H)
    x = np.linalg.solve(A, np.einsum("n,nki,nk->i", weights, H, r))
    e = r - np.einsum("nki,i->nk", H, x)
    score = weights[:, None] * np.einsum("nki,nk->ni", H, e)
    A_inv = np.linalg.inv(A)
    cov = A_inv @ long_run_covariance(score, lags) @ A_inv
    naive = scale**2 * A_inv
    C = cov[:k, :k] if np.trace(cov[:k, :k]) >= np.trace(naive[:k, :k]) else naive[:k, :k]
    return x, C


def next_offset(tried: list[tuple[float, float]]) -> float:
    """The next correction to try, from the (correction, offset left) pairs so far.

    The offset left falls as the correction grows (each correction removes what it applies,
    and the estimate sees a share of what is left, a share that shrinks as the filter loses
    track). Once two corrections leave offsets of opposite signs: false position between the
    closest of each sign. Before: the secant through the last two (a step of at most
    ``SECANT_MAX_GAIN`` times the offset left), else the last correction plus its offset left.
    """
    above = [p for p in tried if p[1] > 0]
    below = [p for p in tried if p[1] < 0]
    if above and below:
        a0, e0 = min(above, key=lambda p: p[1])
        a1, e1 = max(below, key=lambda p: p[1])
        return a0 - e0 * (a1 - a0) / (e1 - e0)
    a1, e1 = tried[-1]
    if len(tried) >= 2:
        a0, e0 = tried[-2]
        if a1 != a0:
            slope = (e1 - e0) / (a1 - a0)
            if slope < 0.0:
                step = -e1 / slope
                return a1 + float(np.clip(step, -SECANT_MAX_GAIN * abs(e1),
                                          SECANT_MAX_GAIN * abs(e1)))
    return a1 + e1
