"""IMU model: body angular rate and specific force with white noise and bias random walks.

Frame: IMU frame. Gravity ``g_world = (0, 0, -GRAVITY_M_S2)`` in the scene world (z up);
specific force ``f = R_world_imuᵀ (a_world - g_world)``. Noise densities are continuous-time
(HILTI 2022 BMI085 calibration): the white noise of a sample at rate ``fs`` has standard deviation
``sigma * sqrt(fs)`` and the bias random walk advances by ``sigma_b * sqrt(1/fs) * N(0, 1)`` per
sample. ``noise_scale`` multiplies every noise and the initial biases (0 = a perfect IMU).
A real IMU also reads the true rate and specific force through a sensitivity matrix ``I + E``
per sensor (scale-factor errors on the diagonal, cross-axis sensitivity and axis misalignment
off it; Kalibr's and OpenVINS's IMU intrinsics): :func:`sensitivity_errors` draws ``E``, and
:func:`synthesize_imu` applies it before the biases and the white noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from adalio.sim.trajectory import Trajectory

GRAVITY_M_S2 = 9.81


@dataclass
class ImuNoise:
    """Continuous-time noise densities (HILTI BMI085 defaults) and initial bias scale."""

    gyro_noise_rad_s_sqrt_hz: float = 1.9e-4
    accel_noise_m_s2_sqrt_hz: float = 1.32e-3
    gyro_bias_walk_rad_s2_sqrt_hz: float = 2.66e-4
    accel_bias_walk_m_s3_sqrt_hz: float = 4.3e-3
    gyro_bias0_rad_s: float = 1.0e-3
    """Standard deviation per axis of the initial gyro bias."""
    accel_bias0_m_s2: float = 2.0e-2
    """Standard deviation per axis of the initial accelerometer bias."""


@dataclass
class ImuData:
    """Synthesized IMU stream and its truth."""

    t_ns: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray
    gyro_bias_rad_s: np.ndarray
    accel_bias_m_s2: np.ndarray
    gyro_true_rad_s: np.ndarray = field(repr=False, default=None)
    accel_true_m_s2: np.ndarray = field(repr=False, default=None)


def true_imu(traj: Trajectory, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free body rate (rad/s) and specific force (m/s^2) in the IMU frame."""
    s = traj.sample(t_s)
    g_world = np.array([0.0, 0.0, -GRAVITY_M_S2])
    f = np.einsum("nji,nj->ni", s.R_world_imu, s.a_world_m_s2 - g_world)
    return s.omega_imu_rad_s, f


def sensitivity_errors(seed: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """(gyro, accelerometer) sensitivity errors ``E`` (3, 3), each of their nine entries drawn
    N(0, ``sigma``) from ``seed`` (a stream of its own: the noise and biases of a sequence do not
    change with it): the IMU reads ``(I + E) x`` for the true ``x``. ``sigma`` 0: zeros."""
    rng = np.random.default_rng([seed, 300])
    draws = rng.standard_normal((2, 3, 3))
    return sigma * draws[0], sigma * draws[1]


def synthesize_imu(traj: Trajectory, t_ns: np.ndarray, t0_ns: int, rng: np.random.Generator,
                   noise: ImuNoise | None = None, noise_scale: float = 1.0,
                   rate_hz: float = 400.0, white_scale: float = 1.0,
                   bias_scale: float = 1.0,
                   sensitivity: tuple[np.ndarray, np.ndarray] | None = None) -> ImuData:
    """IMU samples at ``t_ns`` (absolute) for a trajectory whose time origin is ``t0_ns``;
    ``white_scale`` further multiplies the white-noise densities only, ``bias_scale`` the
    initial biases and the bias random walks only (0: biases stay zero). ``sensitivity``: the
    (gyro, accelerometer) sensitivity errors ``E`` (:func:`sensitivity_errors`), the samples
    ``(I + E) x + bias + noise``; None: ``E = 0``."""
    noise = noise or ImuNoise()
    n = len(t_ns)
    gyro_true, accel_true = true_imu(traj, (t_ns - t0_ns) * 1e-9)
    dt = 1.0 / rate_hz
    k = noise_scale * bias_scale
    bg0 = k * noise.gyro_bias0_rad_s * rng.standard_normal(3)
    ba0 = k * noise.accel_bias0_m_s2 * rng.standard_normal(3)
    wg = rng.standard_normal((n, 3))
    wa = rng.standard_normal((n, 3))
    steps_g = rng.standard_normal((n, 3))
    steps_a = rng.standard_normal((n, 3))
    steps_g[0] = 0.0
    steps_a[0] = 0.0
    bg = bg0 + k * noise.gyro_bias_walk_rad_s2_sqrt_hz * np.sqrt(dt) * np.cumsum(steps_g, 0)
    ba = ba0 + k * noise.accel_bias_walk_m_s3_sqrt_hz * np.sqrt(dt) * np.cumsum(steps_a, 0)
    kw = noise_scale * white_scale
    gyro_read, accel_read = gyro_true, accel_true
    if sensitivity is not None:
        E_gyro, E_accel = sensitivity
        gyro_read = gyro_true + gyro_true @ np.asarray(E_gyro).T
        accel_read = accel_true + accel_true @ np.asarray(E_accel).T
    gyro = gyro_read + bg + kw * noise.gyro_noise_rad_s_sqrt_hz / np.sqrt(dt) * wg
    accel = accel_read + ba + kw * noise.accel_noise_m_s2_sqrt_hz / np.sqrt(dt) * wa
    return ImuData(t_ns=t_ns, gyro_rad_s=gyro, accel_m_s2=accel, gyro_bias_rad_s=bg,
                   accel_bias_m_s2=ba, gyro_true_rad_s=gyro_true, accel_true_m_s2=accel_true)
