"""Data passed between the bag reader, the estimator and the writers.

Frames: ``lidar`` = LiDAR sensor frame, ``imu`` = IMU/body frame, ``world`` = IMU frame at the
end of initialization (or its gravity-aligned version). Units are in the names. Time is int64
nanoseconds since the epoch of the bag's clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class ImuBatch:
    """IMU samples in time order: body angular rate and specific force in the IMU frame."""

    t_ns: np.ndarray
    """(N,) int64."""
    gyro_rad_s: np.ndarray
    """(N, 3) float64."""
    accel_m_s2: np.ndarray
    """(N, 3) float64 (already converted from g if the sensor reports in g)."""

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass
class Scan:
    """One LiDAR sweep with per-point absolute times."""

    points_lidar: np.ndarray
    """(N, 3) float64, metres, LiDAR frame. NaN/inf points already removed."""
    t_ns: np.ndarray
    """(N,) int64 absolute time of each point."""
    stamp_ns: int
    """Header stamp of the message (int64 ns)."""
    intensity: np.ndarray | None = None
    """(N,) float32 or None."""
    ring: np.ndarray | None = None
    """(N,) uint16 or None."""
    line: np.ndarray | None = None
    """(N,) uint8 or None: a Livox cloud's laser of each point (a ``CustomMsg``'s ``line``, or a
    Livox driver's PointCloud2's), one of the lasers drawing its pattern, not a ring; the stray
    test reads each laser's points in firing order where the cloud has no rings
    (``Odometry.add_scan``'s ``line``)."""

    @property
    def t_start_ns(self) -> int:
        return int(self.t_ns.min()) if self.t_ns.size else int(self.stamp_ns)

    @property
    def t_end_ns(self) -> int:
        return int(self.t_ns.max()) if self.t_ns.size else int(self.stamp_ns)

    def __len__(self) -> int:
        return int(self.points_lidar.shape[0])


@dataclass
class ScanStats:
    """Per-scan diagnostics; one row of ``scans.csv``."""

    t_ns: int = 0
    n_raw: int = 0
    """Points in the message after NaN removal."""
    n_down: int = 0
    """Points after voxel downsampling with the leaf actually used."""
    n_down_general: int = 0
    """Points after downsampling with the general leaf (the detector's N_down)."""
    n_near: int = 0
    """Downsampled points (general leaf) with |x|,|y| < d_xy in the LiDAR frame."""
    degenerate: bool = False
    trigger: str = ""
    """Why the degenerate set is active: '', 'count', 'near', 'near_ratio', 'eigen', 'hold'."""
    voxel_size_m: float = 0.0
    search_radius_m: float = 0.0
    plane_margin_m: float = 0.0
    n_matched: int = 0
    """Points with an accepted point-to-plane residual at the last iteration."""
    iterations: int = 0
    n_searches: int = 0
    """Map searches (kNN + plane fits) of the update; see filter.research_min_shift_m."""
    n_moving: int = 0
    """Points of the sweep kept out of the update and the map as moving (map.remove_moving)."""
    n_seen_through: int = 0
    """Map points this sweep saw through, removed from the map (map.remove_moving)."""
    n_stray: int = 0
    """Stray returns among the finite points (``adalio.lio.stray``; 0 without rings), dropped
    before the range gates with preprocess.drop_stray_returns, or where they are more than
    preprocess.stray_drop_share of the finite points."""
    n_stray_dropped: int = 0
    """Points dropped as stray (0: kept): in a sweep that drops them, the stray returns and the
    points whose ring does not continue them either but an adjacent ring does (``adalio.lio.
    stray.SUPPORTED``)."""
    wall_ms: float = 0.0
    eigenvalues: np.ndarray = field(default_factory=lambda: np.zeros(6))
    """Ascending eigenvalues of the 6x6 (rotation, translation) information matrix H^T H / R."""
    weakest_direction: np.ndarray = field(default_factory=lambda: np.zeros(6))
    """Unit eigenvector of the smallest eigenvalue (rotation xyz, translation xyz)."""
    degeneracy_score: float = 0.0
    """0 (well constrained) .. 1 (an unobservable direction); see lio/degeneracy.py."""
    held_directions: int = 0
    """adaptive+: pose directions left at the IMU prediction (6 - rank of the projector)."""
    min_restoring: float = float("nan")
    """adaptive+: smallest re-association restoring ratio of the probed weak directions (1 =
    real information, ~0 = the residuals follow the pose; NaN = not probed)."""
    imu_gap_s: float = 0.0
    """Length of an IMU gap bridged by the motion model in this scan (s; 0 = none)."""
    lidar_gap_s: float = 0.0
    """LiDAR time missing before this scan (s; 0 = none): the scans of at least one sweep
    period did not arrive, and the IMU alone carried the pose across (``Odometry.lidar_gaps``)."""
    height_blind: bool = False
    """filter.sigmas_height_blind: the scan's height claim is mostly what its fitted normals'
    noise fakes (``ieskf.height_blind``), so the reported sigmas take no height from it and
    leave the height to the IMU (README, Outputs, *Uncertainty*)."""
    rest_update: bool = False
    """The IMU rested before the scan end and the filter took a zero velocity there
    (imu.zero_velocity_update)."""
    sigma_p_world_m: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    """Standard deviations of the world-frame position x, y, z from the filter covariance at
    the scan end (m)."""
    sigma_rot_world_deg: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    """Standard deviations of small rotations about the world x, y, z axes (deg): roll, pitch
    and yaw of a level sensor (yaw exactly)."""
    sigma_extrinsic_m: float = 0.0
    """Of ``sigma_p_world_m``, the largest position standard deviation (m) the LiDAR-IMU
    extrinsic's own uncertainty alone gives (``sensor.extrinsic_rotation_sigma_deg``,
    ``sensor.extrinsic_translation_sigma_m``; :mod:`adalio.lio.extrinsic_sigma`)."""
    var_extrinsic_world: np.ndarray = field(default_factory=lambda: np.zeros(6))
    """The extrinsic's share of the diagonal of the reported world covariance: variances of
    the position x, y, z (m²) and of small rotations about the world x, y, z axes (rad²), from
    the extrinsic checks' estimates at the scan (``run_bag`` widens ``scans.csv``'s sigmas to
    the estimates at the run's end, :meth:`adalio.lio.odometry.Odometry.extrinsic_variance`;
    not a column)."""
    backfill: bool = False
    """The pose comes from the backfill (the filter run backwards from the initialization over
    the scans read before it), stamped at the scan's start rather than its end."""
    stage_ms: dict[str, float] = field(default_factory=dict)
    """Wall time per pipeline stage (undistort, downsample, degeneracy, update, map)."""


@dataclass
class Estimate:
    """The filter state at the end of one scan."""

    t_ns: int
    """Scan end time (int64 ns)."""
    T_world_imu: np.ndarray
    """(4, 4) float64 pose of the IMU in the world frame."""
    velocity_world_m_s: np.ndarray
    gyro_bias_rad_s: np.ndarray
    accel_bias_m_s2: np.ndarray
    gravity_world_m_s2: np.ndarray
    cov_diag: np.ndarray
    """(23,) diagonal of the error-state covariance (lio-design.md §2 ordering)."""
    stats: ScanStats = field(default_factory=ScanStats)
    points_world: np.ndarray | None = None
    """(M, 3) the downsampled scan registered into the world (for visualisation)."""


@dataclass
class UnsettledCheck:
    """A sensor check (the IMU time offset's, the LiDAR-IMU rotation's, the lever arm's) that
    closed without a conclusion: its last estimate was neither precise enough to call the value
    right nor significant at a usable precision (``Odometry.time_offset_unsettled``,
    ``.extrinsic_rotation_unsettled``, ``.extrinsic_translation_unsettled``). The configured
    value was used as it is."""

    span_s: float
    """Time between the first and the last update the check saw (s)."""
    estimate: Any = None
    """Its last estimate (:class:`adalio.lio.time_offset.TimeOffsetEstimate`,
    :class:`adalio.lio.extrinsic_check.RotationEstimate`,
    :class:`adalio.lio.lever_arm.TranslationEstimate`), or None: too few updates, or too little
    rotation (or change of it) to estimate anything."""
    gave_up: bool = False
    """True: it stopped at the check's longest span (``time_offset.MAX_SPAN_S``); False: the
    recording ended first."""


@dataclass
class InitReport:
    """How the estimator initialized (``Odometry.init_report``); written to config.yaml."""

    method: str
    """'static' (a still IMU window) or 'moving' (LiDAR-registered scans fitted to the IMU)."""
    t_ns: int
    """End of the initialization (the world frame's epoch)."""
    gyro_bias_rad_s: np.ndarray
    gravity_imu_m_s2: np.ndarray
    """Gravity in the IMU frame at initialization."""
    window_s: float
    """Length of the still window or of the fitted moving window."""
    gravity_world_m_s2: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    """Gravity in the world frame at initialization (the filter's ``g``): the world is the IMU
    frame at init (or the moving fit's, or gravity-aligned), so this says where its up is (the
    report levels its plots by it)."""
    accel_norm_m_s2: float = float("nan")
    """Static: mean accelerometer norm over the window (in the bag's unit, before scaling)."""
    gyro_noise_rad_s_sqrt_hz: float = float("nan")
    """Gyro white-noise density measured in the still window, or over the moving start's IMU
    samples (``imu.moving_noise``); NaN when not measured."""
    accel_noise_m_s2_sqrt_hz: float = float("nan")
    """Accelerometer white-noise density measured as the gyro's."""
    noise_used: str = "config"
    """Which densities the filter uses: 'config', 'measured', or which sensor
    'at_least_config' raised to its measured density (``imu.noise_used``)."""
    generic_noise: bool = False
    """The config's densities are Faster-LIO's generic values (``config.imu_noise_is_generic``):
    the summary line says to set the IMU's own."""
    detail: str = ""
    """The stillness test's figures (static) or the fit's (moving)."""
    wait_s: float = float("nan")
    """From the start of the first scan to the end of the initialization (s)."""
    scans_without_pose: int = 0
    """Scans handed in before the initialization, which got no pose."""
    refused_fits: int = 0
    """Moving start: fits refused before one passed (motion_init.MovingInit.solve)."""
    last_refusal: str = ""
    """Moving start: why the last refused fit was refused."""
    backfilled: int = 0
    """Of the scans without a pose, those the backfill gave one (imu.backfill_s)."""
    lidar_rest: str = ""
    """What the LiDAR said of the rest (imu.rest_lidar_check): a static start's check, or the
    still window a moving start refused because the scene moved ('' when not checked)."""

    @property
    def scans_left_without_pose(self) -> int:
        """Scans read before the initialization that the backfill did not reach either."""
        return self.scans_without_pose - self.backfilled

    def describe_wait(self) -> str:
        """Why the scans before the initialization got no pose ('' if none went without)."""
        if self.scans_without_pose == 0:
            return ""
        if self.refused_fits:
            return (f"{self.refused_fits} moving-start fits refused, the last because "
                    f"{self.last_refusal}")
        return "no still window and no moving-start fit before"

    def describe(self) -> str:
        """One line for the run summary."""
        bias = ", ".join(f"{v:+.2e}" for v in self.gyro_bias_rad_s)
        text = f"{self.method} start, gyro bias ({bias}) rad/s"
        if np.isfinite(self.accel_norm_m_s2):
            text += f", mean |accel| {self.accel_norm_m_s2:.3f}"
        text += f"; the filter uses the {self.noise_used} noise densities"
        if self.generic_noise:
            text += (" (Faster-LIO's generic values, not this IMU's: set its own imu.gyro_cov, "
                     "accel_cov and bias walks, README Presets)")
        text += f"; {self.detail}"
        if self.lidar_rest:
            text += f"; {self.lidar_rest}"
        if self.scans_without_pose:
            why = f"; {self.describe_wait()}" if self.refused_fits else ""
            text += (f"; first filter pose {self.wait_s:.1f} s after the first scan "
                     f"({self.scans_without_pose} scans read before it, {self.backfilled} of "
                     f"them given a pose by the backfill{why})")
        return text

    def to_dict(self) -> dict:
        def num(x: float) -> float | None:
            return None if not np.isfinite(x) else float(f"{x:.6g}")

        return {"init_method": self.method, "init_t_s": self.t_ns * 1e-9,
                "init_window_s": num(self.window_s),
                "gyro_bias_rad_s": [num(v) for v in self.gyro_bias_rad_s],
                "gravity_imu_m_s2": [num(v) for v in self.gravity_imu_m_s2],
                "gravity_world_m_s2": [num(v) for v in self.gravity_world_m_s2],
                "accel_norm_m_s2": num(self.accel_norm_m_s2),
                "gyro_noise_rad_s_sqrt_hz": num(self.gyro_noise_rad_s_sqrt_hz),
                "accel_noise_m_s2_sqrt_hz": num(self.accel_noise_m_s2_sqrt_hz),
                "filter_noise": self.noise_used, "detail": self.detail,
                "init_wait_s": num(self.wait_s),
                "init_scans_without_pose": int(self.scans_without_pose),
                "init_refused_fits": int(self.refused_fits),
                "init_backfilled": int(self.backfilled),
                "init_lidar_rest": self.lidar_rest}
