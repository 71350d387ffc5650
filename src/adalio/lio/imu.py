"""IMU processing: static initialization, discrete propagation and scan undistortion.

lio-design.md §3 (process model, F and G), §4 (static init), §5 (forward propagation with pose
records, backward compensation of each point to the scan end). Frames per ``state.py``; times inside
a scan are float seconds relative to a reference ``t_ref_ns`` (int64 ns at the interface); gyro in
rad/s, accel in m/s² after the init scale ``|g|/|ā_init|``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numba import prange

from adalio.config import ImuConfig
from adalio.jit import kernel
from adalio.lio import so3
from adalio.lio.state import DIM, State


# --------------------------------------------------------------------------- initialization (§4)
@dataclass
class StaticInit:
    """Result of the static initialization."""

    gyro_bias_rad_s: np.ndarray
    gravity_world_m_s2: np.ndarray
    R_world_imu: np.ndarray
    accel_scale: float
    """Multiplier applied to raw accel samples (|g| / |ā_init|, §3.1)."""
    n_samples: int


MAX_REST_LAG_S = 0.05
"""The zero-velocity update judges rest only on samples reaching within this long of the scan
end: across an IMU gap or a stalled IMU stream nothing says the rig still rests."""


def stillness_window(t_ns: np.ndarray, t_end_ns: int, window_s: float) -> slice | None:
    """Index range of the samples in ``[t_end − window, t_end]`` if the buffer reaches back that far."""
    start_ns = t_end_ns - round(window_s * 1e9)
    if t_ns.size == 0 or t_ns[0] > start_ns:
        return None
    lo = int(np.searchsorted(t_ns, start_ns, side="left"))
    hi = int(np.searchsorted(t_ns, t_end_ns, side="right"))
    return slice(lo, hi)


@dataclass
class StillnessTest:
    """Outcome of :func:`stillness_test` on one IMU window (lio-design.md §4, adalio's rule).

    ``gyro_ratio`` / ``accel_ratio`` are the test statistics divided by their thresholds: the
    window is still when both are <= 1. The densities are the white-noise densities measured in
    the window (second differences, pooled over the axes: :func:`white_noise_variance`), valid
    as a noise calibration only when ``still``.
    """

    still: bool
    gyro_ratio: float
    accel_ratio: float
    gyro_noise_rad_s_sqrt_hz: float
    accel_noise_m_s2_sqrt_hz: float
    rate_hz: float
    n_samples: int
    window_s: float
    noise_dof: int = 0
    """Effective degrees of freedom of each measured density's variance
    (:func:`white_noise_variance`)."""

    def describe(self) -> str:
        return (f"{self.window_s:.2f} s window of {self.n_samples} samples at "
                f"{self.rate_hz:.0f} Hz: low-frequency gyro spread {self.gyro_ratio:.1f}x and "
                f"accel spread {self.accel_ratio:.1f}x the rest threshold (measured noise "
                f"{self.gyro_noise_rad_s_sqrt_hz:.2e} rad/s/sqrt(Hz), "
                f"{self.accel_noise_m_s2_sqrt_hz:.2e} m/s^2/sqrt(Hz))")


def block_samples(cfg: ImuConfig, rate_hz: float) -> int:
    """Samples per block of ``imu.still_block_s`` at ``rate_hz`` (at least 2)."""
    return max(round(cfg.still_block_s * rate_hz), 2)


def _blocks(x: np.ndarray, n_block: int) -> np.ndarray:
    """(n_blocks, n_block, 3): ``x`` (n, 3) cut into whole blocks (a partial last one dropped)."""
    n_blocks = x.shape[0] // n_block
    return x[: n_blocks * n_block].reshape(n_blocks, n_block, 3)


def _block_statistic(x: np.ndarray, n_block: int, floor: float) -> tuple[float, int]:
    """Chi-square statistic of the block means of ``x`` (n, 3) around their mean.

    The within-block (pooled, per axis) variance s² is what averages out inside a block (white
    noise, tremor, vibration); a block mean of n_b samples then has variance s²/n_b at rest.
    ``floor`` is a motion amplitude still counted as rest. Returns (statistic, dof).
    """
    blocks = _blocks(x, n_block)
    n_blocks = blocks.shape[0]
    means = blocks.mean(axis=1)
    within = blocks.var(axis=1, ddof=1).mean(axis=0)
    dev2 = (means - means.mean(axis=0)) ** 2
    stat = float(np.sum(dev2 / (within / n_block + floor * floor)))
    return stat, 3 * (n_blocks - 1)


SECOND_DIFFERENCE_DOF_FACTOR = 36.0 / 70.0
"""Effective degrees of freedom per sample of the mean squared second difference of white
noise: its autocovariances are 6, -4, 1 (x σ²), so the mean of N squares has the variance of a
chi-square mean with N·36/(36 + 2·16 + 2·1) degrees of freedom."""


def _second_differences(x: np.ndarray) -> np.ndarray:
    """``x[i+1] − 2x[i] + x[i−1]`` of the rows of ``x`` (n, 3): white noise of per-sample
    variance σ² gives 6σ² each, a motion slow against the sample rate almost nothing."""
    return x[2:] - 2.0 * x[1:-1] + x[:-2]


def white_noise_variance(x: np.ndarray) -> tuple[float, int]:
    """Per-sample white-noise variance of ``x`` (n, 3), pooled over the axes, from second
    differences: ``mean((x[i+1] − 2x[i] + x[i−1])²) / 6``. Unbiased for white noise, and blind to
    what moves slowly against the sample rate (a hand's tremor at 10 Hz reaches a 400 Hz
    IMU's second differences at 6e-4 of its power, its within-block spread in full). Returns
    (variance, effective degrees of freedom)."""
    d = _second_differences(x)
    return float(np.mean(d * d)) / 6.0, max(int(d.size * SECOND_DIFFERENCE_DOF_FACTOR), 1)


CHI2_1_MEDIAN = 0.454936423119572
"""Median of a chi-square variable with one degree of freedom (``scipy.stats.chi2.ppf(0.5, 1)``)."""
MEDIAN_DOF_FACTOR = 0.25287394
"""Effective degrees of freedom per sample of the median of squared second differences of white
noise, as a scale estimate: ``2 (m f(m))² / Σ_k cov(I_0, I_k)`` with ``m`` :data:`CHI2_1_MEDIAN`,
``f`` the chi-square(1) density and ``I_k`` the indicator that the ``k``-th second difference is
below its median; the second differences are normal with correlations -2/3 and 1/6 at lags 1
and 2, so ``Σ_k = 1/4 + 2 (cov_1 + cov_2)`` = 0.3633 (bivariate normal probabilities). Checked
by Monte Carlo in ``tests/lio/test_imu.py``."""


def robust_white_noise_variance(x: np.ndarray) -> tuple[float, int]:
    """:func:`white_noise_variance` from the median of the squared second differences instead
    of their mean: ``median(d²) / (6 · CHI2_1_MEDIAN)``, pooled over the axes. Unbiased for
    white noise, and a few samples of a jolt (a foot strike or a bump in a moving window, whose
    second differences are tens of times the noise's) move it by their share of the samples,
    not by their power. Effective degrees of freedom: :data:`MEDIAN_DOF_FACTOR` per second
    difference (the mean's: :data:`SECOND_DIFFERENCE_DOF_FACTOR`)."""
    d = _second_differences(x)
    var = float(np.median(d * d)) / (6.0 * CHI2_1_MEDIAN)
    return var, max(int(d.size * MEDIAN_DOF_FACTOR), 1)


@dataclass
class NoiseMeasurement:
    """White-noise densities measured in an IMU window while moving (:func:`moving_noise`);
    the fields :func:`measured_noise_config` reads, as a :class:`StillnessTest` has them."""

    gyro_noise_rad_s_sqrt_hz: float
    accel_noise_m_s2_sqrt_hz: float
    rate_hz: float
    noise_dof: int


MIN_NOISE_SAMPLES = 100
"""Fewest IMU samples :func:`moving_noise` measures from."""


def moving_noise(t_ns: np.ndarray, gyro_rad_s: np.ndarray,
                 accel_m_s2: np.ndarray) -> NoiseMeasurement | None:
    """The gyro's and accelerometer's white-noise densities in a window where the IMU moves
    (a moving start's), from :func:`robust_white_noise_variance`: a hand's or a robot's motion
    varies slowly against the sample rate, so the second differences see the noise, and their
    median ignores the jolts. None with fewer than ``MIN_NOISE_SAMPLES`` samples."""
    n = int(gyro_rad_s.shape[0])
    span_s = float(t_ns[-1] - t_ns[0]) * 1e-9 if n > 1 else 0.0
    if n < MIN_NOISE_SAMPLES or not span_s > 0:
        return None
    rate = (n - 1) / span_s
    g_var, dof = robust_white_noise_variance(gyro_rad_s)
    a_var, _ = robust_white_noise_variance(accel_m_s2)
    return NoiseMeasurement(float(np.sqrt(g_var / rate)), float(np.sqrt(a_var / rate)), rate, dof)


@functools.lru_cache(maxsize=64)
def chi2_quantile(q: float, dof: int) -> float:
    """``scipy.stats.chi2.ppf(q, dof)``, remembered: the stillness test runs on every scan with
    the same few window sizes, and scipy's call costs more than the test's arithmetic. Computed
    as scipy.stats computes it, ``2 gammaincinv(dof / 2, q)`` (the same bits), from
    scipy.special, which a run imports anyway: importing scipy.stats alone took 0.35-0.5 s of
    every run's start."""
    from scipy.special import gammaincinv

    return float(2 * gammaincinv(dof / 2, q))


def stillness_test(t_ns: np.ndarray, gyro_rad_s: np.ndarray, accel: np.ndarray,
                   cfg: ImuConfig) -> StillnessTest:
    """Is the IMU at rest over this window? A test that adapts to the sensor's own noise (§4).

    The window is cut into blocks of ``still_block_s``. Whatever averages out within a block
    (white noise, hand tremor, engine vibration) sets the noise level, measured in the window
    itself; motion is what moves the block means: a slow walk's step bobbing (~2 Hz) and turns.
    Per sensor, ``Σ (block mean − mean)² / (s²/n_b + floor²)`` over blocks and axes is compared
    with the chi-square quantile ``1 − still_false_alarm`` (3 (B − 1) degrees of freedom). The
    floors (``still_gyro_floor_rad_s``, ``still_accel_floor_m_s2``) are motion small enough to
    count as rest: the static initialization then errs by at most about that much in gyro bias
    and in gravity. The accelerometer is scaled to |g| first, so a g-unit IMU is judged alike.
    Limit: motion at constant velocity and rate (a smoothly driven robot) is indistinguishable
    from rest for any IMU.
    """
    n = int(gyro_rad_s.shape[0])
    span_s = float(t_ns[-1] - t_ns[0]) * 1e-9 if n > 1 else 0.0
    rate = (n - 1) / span_s if span_s > 0 else 0.0
    n_block = block_samples(cfg, rate)
    nan = float("nan")
    if n < max(cfg.init_samples, 3 * n_block) or not rate > 0:
        return StillnessTest(False, nan, nan, nan, nan, rate, n, span_s)
    acc_norm = float(np.linalg.norm(accel.mean(axis=0)))
    if not acc_norm > 0:
        return StillnessTest(False, nan, nan, nan, nan, rate, n, span_s)
    acc = accel * (cfg.gravity_m_s2 / acc_norm)
    g_stat, dof = _block_statistic(gyro_rad_s, n_block, cfg.still_gyro_floor_rad_s)
    a_stat, _ = _block_statistic(acc, n_block, cfg.still_accel_floor_m_s2)
    limit = chi2_quantile(1.0 - cfg.still_false_alarm, dof)
    g_ratio, a_ratio = g_stat / limit, a_stat / limit
    g_var, noise_dof = white_noise_variance(gyro_rad_s)
    a_var, _ = white_noise_variance(acc)
    return StillnessTest(bool(g_ratio <= 1.0 and a_ratio <= 1.0), g_ratio, a_ratio,
                         float(np.sqrt(g_var / rate)), float(np.sqrt(a_var / rate)), rate, n,
                         span_s, noise_dof)


def rest_mean_variances(gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                        n_block: int) -> tuple[float, float]:
    """Variance of the gyro and accelerometer window means of a still window (batch means).

    The window is cut into blocks of ``n_block`` samples; the spread of the block means around
    their mean, pooled over the three axes, divided by the number of blocks, is the variance of
    the window mean. It includes what the stillness test accepted as rest (slow sway, drift) as
    well as white noise, and needs no configured density.
    """
    out = []
    for x in (gyro_rad_s, accel_m_s2):
        means = _blocks(x, n_block).mean(axis=1)
        n_blocks = means.shape[0]
        if n_blocks < 2:
            raise ValueError("rest_mean_variances: fewer than 2 blocks")
        spread = float(np.sum((means - means.mean(axis=0)) ** 2)) / (3 * (n_blocks - 1))
        out.append(spread / n_blocks)
    return out[0], out[1]


def static_init(gyro_rad_s: np.ndarray, accel: np.ndarray, cfg: ImuConfig) -> StaticInit:
    """Gravity and gyro bias from the static mean (§4): ``g = −|g| ā/|ā|``, ``b_g = ω̄``.

    The world is the IMU frame at init (``R = I``) unless ``cfg.gravity_align_world``, in which
    case ``R`` is the smallest rotation taking the measured up direction to +z.
    """
    acc_mean = accel.mean(axis=0)
    norm = float(np.linalg.norm(acc_mean))
    up_imu = acc_mean / norm
    R = so3.rotation_to_z(up_imu) if cfg.gravity_align_world else np.eye(3)
    g_world = -cfg.gravity_m_s2 * (R @ up_imu)
    return StaticInit(gyro_bias_rad_s=gyro_rad_s.mean(axis=0), gravity_world_m_s2=g_world,
                      R_world_imu=R, accel_scale=cfg.gravity_m_s2 / norm,
                      n_samples=int(gyro_rad_s.shape[0]))


def measured_noise_config(cfg: ImuConfig, test: StillnessTest | NoiseMeasurement,
                          only_if_noisier: bool = False) -> ImuConfig:
    """``cfg`` with gyro_cov / accel_cov replaced by the densities measured in a still window
    (or a moving start's, :func:`moving_noise`), in the configured discretization: ``σ²`` for
    'dt' (Q dt), ``σ² f_s`` for 'dt2' (Q dt²).

    ``only_if_noisier`` ('at_least_config'): a sensor's configured value is kept unless the
    window shows that sensor noisier than configured beyond doubt: its measured variance (a
    chi-square variable with ``test.noise_dof`` degrees of freedom) exceeds the configured one
    by more than the ``1 − still_false_alarm`` quantile allows. The configured values then act
    as a floor (they may include vibration and model error the window does not show)."""
    from dataclasses import replace

    scale = 1.0 if cfg.noise_discretization == "dt" else test.rate_hz
    gyro = test.gyro_noise_rad_s_sqrt_hz**2 * scale
    accel = test.accel_noise_m_s2_sqrt_hz**2 * scale
    if only_if_noisier:
        dof = max(test.noise_dof, 1)
        limit = chi2_quantile(1.0 - cfg.still_false_alarm, dof) / dof
        gyro = gyro if gyro > cfg.gyro_cov * limit else cfg.gyro_cov
        accel = accel if accel > cfg.accel_cov * limit else cfg.accel_cov
    return replace(cfg, gyro_cov=gyro, accel_cov=accel)


def noise_used(cfg: ImuConfig, used: ImuConfig) -> str:
    """Which white-noise densities the filter uses, for the run summary: 'config', 'measured',
    or, where 'at_least_config' raised a sensor, e.g. 'measured gyro (9.8x the configured
    density) and config accelerometer'."""
    if cfg.noise_source != "at_least_config":
        return cfg.noise_source
    pairs = (("gyro", cfg.gyro_cov, used.gyro_cov), ("accelerometer", cfg.accel_cov,
                                                     used.accel_cov))
    if all(u == c for _, c, u in pairs):
        return "config"
    return " and ".join(f"measured {name} ({np.sqrt(u / c):.1f}x the configured density)"
                        if u != c else f"config {name}" for name, c, u in pairs)


def process_noise(cfg: ImuConfig) -> np.ndarray:
    """Diagonal of Q in noise order (n_g, n_a, n_bg, n_ba) (§3.2-3.3)."""
    return np.repeat([cfg.gyro_cov, cfg.accel_cov, cfg.gyro_bias_cov, cfg.accel_bias_cov], 3)


def gap_noise(cfg: ImuConfig, q_diag: np.ndarray, period_s: float) -> np.ndarray:
    """Q across an IMU gap, continuous-time (Q dt): the motion model's random rate and
    acceleration densities²; the bias walks as configured, as densities². In the 'dt2' form a
    configured value ``c`` adds ``c dt²`` per sample, so over a stretch of ``L`` seconds of
    samples ``period_s`` apart it adds ``c L period_s``: its density² is ``c period_s`` (the
    samples' nominal period, as measured), and a gap adds what the missing samples would have."""
    q = np.repeat([cfg.gap_motion_gyro_rad_s_sqrt_hz**2, cfg.gap_motion_accel_m_s2_sqrt_hz**2,
                   0.0, 0.0], 3)
    scale = 1.0 if cfg.noise_discretization == "dt" else period_s
    q[6:] = q_diag[6:] * (scale if np.isfinite(scale) else 0.0)
    return q


# --------------------------------------------------------------------------- propagation (§3)
@kernel()
def world_accel(R, b_g, b_a, g, gyro_rad_s, accel_m_s2, dt, measured_accel=True):
    """The world acceleration held over one step: the specific force turned by the attitude at
    the interval's middle, ``R Exp(ω Δt/2) (a − b_a) + g``. ``measured_accel`` False (the
    motion model across an IMU gap, whose specific force :func:`_gap_inputs` makes cancel
    gravity at ``R``): turned by ``R`` itself, so the world acceleration is zero."""
    acc = accel_m_s2 - b_a
    if not measured_accel:
        return so3.mul_vec(R, acc) + g
    R_mid = so3.mul(R, so3.exp((gyro_rad_s - b_g) * (0.5 * dt)))
    return so3.mul_vec(R_mid, acc) + g


@kernel()
def discrete_step(p, R, v, b_g, b_a, g, gyro_rad_s, accel_m_s2, dt, measured_accel=True):
    """One step on the manifold (§3.1), second order in Δt: returns (p, R, v).

    ``R ← R Exp(ω Δt)``; the world acceleration ``a_w`` of :func:`world_accel` (the specific
    force at the interval's mid attitude) is held over the step, ``v ← v + a_w Δt``,
    ``p ← p + v Δt + ½ a_w Δt²``: exact for a constant rate and specific force, where Faster-LIO's
    explicit Euler (the start attitude, ``p ← p + v Δt``) errs by O(Δt) per second of dead
    reckoning (benchmark log, *Session 51*: 6.5-8 cm after 20 s at 100 Hz, 0.5-0.9 cm so)."""
    a_w = world_accel(R, b_g, b_a, g, gyro_rad_s, accel_m_s2, dt, measured_accel)
    return _advance(p, R, v, gyro_rad_s - b_g, a_w, dt)


@kernel()
def _advance(p, R, v, omega, a_w, dt):
    """:func:`discrete_step` given its body rate ``ω`` and world acceleration ``a_w`` (which
    :func:`propagate_scan` has already computed for the interval's pose record)."""
    p_new = p + v * dt + a_w * (0.5 * dt * dt)
    R_new = so3.mul(R, so3.exp(omega * dt))
    v_new = v + a_w * dt
    return p_new, R_new, v_new


@kernel()
def _step_blocks(R, b_g, b_a, g, g_anchor, gyro_rad_s, accel_m_s2, dt, measured_accel):
    """The blocks of F and G of :func:`discrete_step` (§3.2): the attitude's ``E_th = Exp(−ω Δt)``
    and ``J_bg = −J_r(ω Δt) Δt`` (also the gyro noise's), and the velocity's increment per
    error, ``Δt ∂a_w/∂·``: attitude ``A = −R [R_h ã]× Δt``, gyro bias (and gyro noise)
    ``D = R R_h [ã]× J_r(ω Δt/2) Δt²/2``, accel bias (and accel noise) ``B = −R R_h Δt``,
    gravity ``C = −[g]× B(g) Δt``; ``R_h = Exp(ω Δt/2)``, ``ã = a − b_a``. The position takes
    ``Δt/2`` times the velocity's increment. ``measured_accel`` False: the gap's motion model,
    whose world acceleration is zero whatever the state (A, B, C, D zero)."""
    omega = gyro_rad_s - b_g
    acc = accel_m_s2 - b_a
    E_th = so3.exp(-omega * dt)
    J_bg = -so3.jr(omega * dt) * dt
    R_h = so3.exp(omega * (0.5 * dt))
    R_mid = so3.mul(R, R_h)
    A_vth = -so3.mul(R, so3.hat(so3.mul_vec(R_h, acc))) * dt
    D_vbg = so3.mul(so3.mul(R_mid, so3.hat(acc)), so3.jr(omega * (0.5 * dt))) * (0.5 * dt * dt)
    B_vba = -R_mid * dt
    C_vg = -so3.mul(so3.hat(g), so3.s2_basis(g, g_anchor)) * dt
    if not measured_accel:
        A_vth[:] = 0.0
        D_vbg[:] = 0.0
        B_vba[:] = 0.0
        C_vg[:] = 0.0
    return E_th, J_bg, A_vth, D_vbg, B_vba, C_vg


@kernel()
def jacobians_fg(R, b_g, b_a, g, g_anchor, gyro_rad_s, accel_m_s2, dt, measured_accel=True):
    """F (23×23) and G (23×12) of the discrete step (§3.2), noise order (n_g, n_a, n_bg, n_ba)."""
    E_th, J_bg, A_vth, D_vbg, B_vba, C_vg = _step_blocks(
        R, b_g, b_a, g, g_anchor, gyro_rad_s, accel_m_s2, dt, measured_accel)
    F = np.eye(DIM)
    Gm = np.zeros((DIM, 12))
    F[3:6, 3:6] = E_th
    F[3:6, 15:18] = J_bg
    for i in range(3):
        F[i, 12 + i] = dt
    F[12:15, 3:6] = A_vth
    F[12:15, 15:18] = D_vbg
    F[12:15, 18:21] = B_vba
    F[12:15, 21:23] = C_vg
    F[0:3, 3:6] = A_vth * (0.5 * dt)
    F[0:3, 15:18] = D_vbg * (0.5 * dt)
    F[0:3, 18:21] = B_vba * (0.5 * dt)
    F[0:3, 21:23] = C_vg * (0.5 * dt)
    Gm[0:3, 0:3] = D_vbg * (0.5 * dt)
    Gm[3:6, 0:3] = J_bg
    Gm[12:15, 0:3] = D_vbg
    if measured_accel:
        Gm[0:3, 3:6] = B_vba * (0.5 * dt)
        Gm[12:15, 3:6] = B_vba
    else:  # the motion model's random acceleration (isotropic: its direction does not
        Gm[12:15, 3:6] = -R * dt  # matter), the velocity's only
    for i in range(3):
        Gm[15 + i, 6 + i] = dt
        Gm[18 + i, 9 + i] = dt
    return F, Gm


@kernel()
def propagate_covariance(P, F, Gm, q_diag):
    """``F P Fᵀ + G diag(q) Gᵀ`` exploiting the sparsity of F and G."""
    FP = so3.mul(F, P)
    out = so3.mul(F, FP.T).T
    GQ = Gm * q_diag
    out += so3.mul(Gm, GQ.T).T
    return out


@kernel()
def _left_mul_F(M, E_th, J_bg, A_vth, D_vbg, B_vba, C_vg, dt):
    """``F @ M`` using the block structure of F (§3.2); rows not listed are identity rows."""
    out = M.copy()
    n = M.shape[1]
    half = 0.5 * dt
    for c in range(n):
        for i in range(3):
            th = 0.0
            dv = 0.0
            for k in range(3):
                th += E_th[i, k] * M[3 + k, c] + J_bg[i, k] * M[15 + k, c]
                dv += (A_vth[i, k] * M[3 + k, c] + D_vbg[i, k] * M[15 + k, c]
                       + B_vba[i, k] * M[18 + k, c])
            dv += C_vg[i, 0] * M[21, c] + C_vg[i, 1] * M[22, c]
            out[i, c] = M[i, c] + dt * M[12 + i, c] + half * dv
            out[3 + i, c] = th
            out[12 + i, c] = M[12 + i, c] + dv
    return out


@kernel()
def propagate_covariance_fast(P, R, b_g, b_a, g, g_anchor, gyro_rad_s, accel_m_s2, dt, q_diag,
                              measured_accel=True):
    """``F P Fᵀ + G diag(q) Gᵀ`` (§3.2) from the blocks of F and G, without forming them.

    ``P`` may hold several covariances side by side, (DIM, c·DIM): each block is propagated,
    bit for bit as it would be alone (every column of ``F M`` depends on that column only).
    Requires isotropic accel noise (``q_diag[3:6]`` equal), so that ``R σ_a² Rᵀ = σ_a² I``.
    ``measured_accel`` False: the velocity is carried by a constant-velocity model, not by a
    measured specific force, so it does not depend on attitude, accel bias or gravity.
    """
    E_th, J_bg, A_vth, D_vbg, B_vba, C_vg = _step_blocks(
        R, b_g, b_a, g, g_anchor, gyro_rad_s, accel_m_s2, dt, measured_accel)
    d = P.shape[0]
    FP = _left_mul_F(P, E_th, J_bg, A_vth, D_vbg, B_vba, C_vg, dt)
    FPt = _block_transpose(FP, d)
    out = _block_transpose(_left_mul_F(FPt, E_th, J_bg, A_vth, D_vbg, B_vba, C_vg, dt), d)
    # G diag(q) Gᵀ: the gyro noise reaches (p, θ, v) through (D Δt/2, J_bg, D); the accel noise
    # (p, v) through (B Δt/2, B), B Bᵀ = Δt² I when the noise is isotropic. Across a gap the
    # motion model's random acceleration reaches the velocity only (its position share, the
    # Δt³/4 of a held acceleration, took tests/lio/test_imu_gaps.py's 3 s gap from 2.9 to 7.0 cm)
    G_g = np.zeros((9, 3))
    for i in range(3):  # element by element: an array slice assignment compiles numba's
        for k in range(3):  # shape-error message (2.6 s of a cold start, tests/lio/test_warmup.py)
            G_g[i, k] = D_vbg[i, k] * (0.5 * dt)
            G_g[3 + i, k] = J_bg[i, k]
            G_g[6 + i, k] = D_vbg[i, k]
    GQG = np.zeros((9, 9))
    for r in range(9):
        for s in range(9):
            acc_rs = 0.0
            for k in range(3):
                acc_rs += G_g[r, k] * q_diag[k] * G_g[s, k]
            GQG[r, s] = acc_rs
    rows = (0, 3, 12)
    dt2 = dt * dt
    q_a = q_diag[3] * dt2
    for b in range(0, P.shape[1], d):
        for bi in range(3):
            for bj in range(3):
                for i in range(3):
                    for k in range(3):
                        out[rows[bi] + i, b + rows[bj] + k] += GQG[3 * bi + i, 3 * bj + k]
        for i in range(3):
            if measured_accel:
                out[i, b + i] += q_a * 0.25 * dt2
                out[i, b + 12 + i] += q_a * 0.5 * dt
                out[12 + i, b + i] += q_a * 0.5 * dt
            out[12 + i, b + 12 + i] += q_a
            out[15 + i, b + 15 + i] += q_diag[6 + i] * dt2
            out[18 + i, b + 18 + i] += q_diag[9 + i] * dt2
    return out


@kernel()
def _block_transpose(M, d):
    """Each (d, d) block of the (d, c·d) ``M`` transposed in place of itself, as a new array."""
    out = np.empty_like(M)
    for b in range(0, M.shape[1], d):
        for i in range(d):
            for j in range(d):
                out[i, b + j] = M[j, b + i]
    return out


@kernel()
def _gap_inputs(R, b_a, g, gyro, k):
    """Motion-model inputs across an IMU gap: the body rate of the last samples before it, and
    the specific force that keeps the world velocity constant (R (a − b_a) + g = 0)."""
    lo = max(k - 7, 0)
    rate = np.zeros(3)
    for j in range(lo, k + 1):
        rate += gyro[j]
    return rate / (k + 1 - lo), so3.mul_vec(R.T, -g) + b_a


@kernel()
def _record(m, tau, R, p, v, w, a, rec_tau, rec_R, rec_p, rec_v, rec_w, rec_a):
    """Write pose record ``m`` element by element (an array assigned to a slice costs numba a
    shape-checked broadcast, slow to compile)."""
    rec_tau[m] = tau
    for i in range(3):
        rec_p[m, i] = p[i]
        rec_v[m, i] = v[i]
        rec_w[m, i] = w[i]
        rec_a[m, i] = a[i]
        for j in range(3):
            rec_R[m, i, j] = R[i, j]


@kernel()
def propagate_scan(p, R, v, b_g, b_a, g, g_anchor, P, imu_tau, gyro, accel, tau_start, tau_end,
                   q_diag, noise_dt, gap_s, q_gap):
    """Forward propagation over one scan with pose records (§5.2).

    ``imu_tau`` (n,) sample times (s, relative), ``accel`` already scaled; the first sample is the
    last one consumed by the previous scan (it may precede ``tau_start``). Mid-point inputs per
    interval, also for the interval ``tau_end`` falls in when its sample after is given (the
    Odometry passes the first sample after the scan end when it has it: the whole interval then
    takes one input, wherever a scan end splits it); without it the last input is held to
    ``tau_end``. Record k holds the state at ``rec_tau[k]``
    and the body rate / world acceleration valid from it to the next record.

    IMU gaps (an interval between samples, or from the last sample to ``tau_end``, longer than
    ``gap_s``): nothing is integrated there. A constant-velocity, constant-rate motion model
    (:func:`_gap_inputs`) carries the state and ``q_gap`` (continuous-time densities², the
    motion model's random acceleration and rate) grows the covariance with the gap's length, so
    the LiDAR update carries the pose.
    """
    n = imu_tau.shape[0]
    m_max = n + 1
    rec_tau = np.empty(m_max)
    rec_R = np.empty((m_max, 3, 3))
    rec_p = np.empty((m_max, 3))
    rec_v = np.empty((m_max, 3))
    rec_w = np.empty((m_max, 3))
    rec_a = np.empty((m_max, 3))
    tau = tau_start
    m = np.int64(0)
    gyro_in = gyro[n - 1].copy()
    acc_in = accel[n - 1].copy()
    gap = False
    broke = False
    for k in range(n - 1):
        t1 = imu_tau[k + 1]
        gap = t1 - imu_tau[k] > gap_s
        if gap:
            gyro_in, acc_in = _gap_inputs(R, b_a, g, gyro, k)
        else:
            gyro_in = 0.5 * (gyro[k] + gyro[k + 1])
            acc_in = 0.5 * (accel[k] + accel[k + 1])
        if t1 <= tau:
            continue
        if t1 > tau_end:
            broke = True
            break
        dt = t1 - max(imu_tau[k], tau)
        a_w = world_accel(R, b_g, b_a, g, gyro_in, acc_in, dt, not gap)
        _record(m, tau, R, p, v, gyro_in - b_g, a_w, rec_tau, rec_R, rec_p, rec_v, rec_w, rec_a)
        m += 1
        q = q_gap / dt if gap else (q_diag if not noise_dt else q_diag / dt)
        P = propagate_covariance_fast(P, R, b_g, b_a, g, g_anchor, gyro_in, acc_in, dt, q,
                                      not gap)
        p, R, v = _advance(p, R, v, gyro_in - b_g, a_w, dt)
        tau = t1
    if not broke:
        gap = tau_end - imu_tau[n - 1] > gap_s
        if gap:
            gyro_in, acc_in = _gap_inputs(R, b_a, g, gyro, n - 1)
    dt = tau_end - tau
    a_w = world_accel(R, b_g, b_a, g, gyro_in, acc_in, max(dt, 0.0), not gap)
    _record(m, tau, R, p, v, gyro_in - b_g, a_w, rec_tau, rec_R, rec_p, rec_v, rec_w, rec_a)
    m += 1
    if dt > 0.0:
        q = q_gap / dt if gap else (q_diag if not noise_dt else q_diag / dt)
        P = propagate_covariance_fast(P, R, b_g, b_a, g, g_anchor, gyro_in, acc_in, dt, q,
                                      not gap)
        p, R, v = _advance(p, R, v, gyro_in - b_g, a_w, dt)
    return (p, R, v, P, rec_tau[:m].copy(), rec_R[:m].copy(), rec_p[:m].copy(),
            rec_v[:m].copy(), rec_w[:m].copy(), rec_a[:m].copy())


@dataclass
class PoseRecords:
    """IMU pose records of one scan (§5.2); times in s relative to the scan's reference."""

    tau_s: np.ndarray
    R: np.ndarray
    p: np.ndarray
    v: np.ndarray
    omega: np.ndarray
    acc_world: np.ndarray


def propagate(state: State, P: np.ndarray, imu_tau_s: np.ndarray, gyro_rad_s: np.ndarray,
              accel_m_s2: np.ndarray, tau_start_s: float, tau_end_s: float, q_diag: np.ndarray,
              noise_discretization: str = "dt2", gap_s: float = np.inf,
              q_gap: np.ndarray | None = None) -> tuple[State, np.ndarray, PoseRecords]:
    """Propagate ``state`` and ``P`` from ``tau_start_s`` to ``tau_end_s`` (§5.2), bridging
    IMU gaps longer than ``gap_s`` with the motion model of :func:`propagate_scan`.

    ``P`` may hold several covariances side by side, (DIM, c·DIM), all propagated along the same
    state (:func:`propagate_covariance_fast`); the result has the same layout."""
    out = propagate_scan(state.p, state.R, state.v, state.b_g, state.b_a, state.g,
                         state.g_anchor, P, imu_tau_s, gyro_rad_s, accel_m_s2,
                         float(tau_start_s), float(tau_end_s), q_diag,
                         noise_discretization == "dt", float(gap_s),
                         np.zeros(12) if q_gap is None else q_gap)
    new = state.copy()
    new.p, new.R, new.v = out[0], out[1], out[2]
    return new, out[3], PoseRecords(*out[4:])


# --------------------------------------------------------------------------- undistortion (§5.3)
@kernel(parallel=True)
def _undistort_kernel(points_lidar, tau_s, rec_tau, rec_R, rec_p, rec_v, rec_w, rec_a, R_end,
                      p_end, R_LI, t_LI):
    """Rows are independent, so they run on all numba threads; the result does not depend on
    how many."""
    n = points_lidar.shape[0]
    m = rec_tau.shape[0]
    out = np.empty((n, 3))
    M = R_end.T
    for i in prange(n):
        tau = tau_s[i]
        lo, hi = 0, m
        while lo < hi:
            mid = (lo + hi) // 2
            if rec_tau[mid] <= tau:
                lo = mid + 1
            else:
                hi = mid
        k = max(lo - 1, 0)
        dt = tau - rec_tau[k]
        x, y, z = points_lidar[i, 0], points_lidar[i, 1], points_lidar[i, 2]
        px = R_LI[0, 0] * x + R_LI[0, 1] * y + R_LI[0, 2] * z + t_LI[0]
        py = R_LI[1, 0] * x + R_LI[1, 1] * y + R_LI[1, 2] * z + t_LI[1]
        pz = R_LI[2, 0] * x + R_LI[2, 1] * y + R_LI[2, 2] * z + t_LI[2]
        wx, wy, wz = rec_w[k, 0] * dt, rec_w[k, 1] * dt, rec_w[k, 2] * dt
        th2 = wx * wx + wy * wy + wz * wz
        if th2 < 1e-4:
            a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
            b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
        else:
            th = np.sqrt(th2)
            a = np.sin(th) / th
            b = (1.0 - np.cos(th)) / th2
        c1x = wy * pz - wz * py
        c1y = wz * px - wx * pz
        c1z = wx * py - wy * px
        c2x = wy * c1z - wz * c1y
        c2y = wz * c1x - wx * c1z
        c2z = wx * c1y - wy * c1x
        qx = px + a * c1x + b * c2x
        qy = py + a * c1y + b * c2y
        qz = pz + a * c1z + b * c2z
        half = 0.5 * dt * dt
        w0 = (rec_R[k, 0, 0] * qx + rec_R[k, 0, 1] * qy + rec_R[k, 0, 2] * qz + rec_p[k, 0]
              + rec_v[k, 0] * dt + rec_a[k, 0] * half - p_end[0])
        w1 = (rec_R[k, 1, 0] * qx + rec_R[k, 1, 1] * qy + rec_R[k, 1, 2] * qz + rec_p[k, 1]
              + rec_v[k, 1] * dt + rec_a[k, 1] * half - p_end[1])
        w2 = (rec_R[k, 2, 0] * qx + rec_R[k, 2, 1] * qy + rec_R[k, 2, 2] * qz + rec_p[k, 2]
              + rec_v[k, 2] * dt + rec_a[k, 2] * half - p_end[2])
        ex = M[0, 0] * w0 + M[0, 1] * w1 + M[0, 2] * w2 - t_LI[0]
        ey = M[1, 0] * w0 + M[1, 1] * w1 + M[1, 2] * w2 - t_LI[1]
        ez = M[2, 0] * w0 + M[2, 1] * w1 + M[2, 2] * w2 - t_LI[2]
        for r in range(3):
            out[i, r] = R_LI[0, r] * ex + R_LI[1, r] * ey + R_LI[2, r] * ez
    return out


def undistort(points_lidar: np.ndarray, tau_s: np.ndarray, rec: PoseRecords, R_end: np.ndarray,
              p_end: np.ndarray, R_LI: np.ndarray, t_LI: np.ndarray) -> np.ndarray:
    """Backward compensation of every point to the scan end (§5.3), one numba pass.

    k = last record at or before the point time (binary search; the first record for earlier
    points, the last one extrapolates), ``Δ = τ − τ_k``, ``R_j = R_k Exp(ω_k Δ)`` (Rodrigues),
    ``p_j = p_k + v_k Δ + ½ a_k Δ²``; returns ``R_LIᵀ(R_eᵀ(R_j p_I + p_j − p_e) − t_LI)``,
    ``p_I = R_LI p_L + t_LI``: the points in the LiDAR frame at the scan end.
    """
    return _undistort_kernel(np.ascontiguousarray(points_lidar, dtype=np.float64),
                             np.ascontiguousarray(tau_s, dtype=np.float64), rec.tau_s, rec.R,
                             rec.p, rec.v, rec.omega, rec.acc_world, R_end, p_end, R_LI, t_LI)
