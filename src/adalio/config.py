"""Configuration: one dataclass per section, YAML presets, strict loading.

Conventions (written once, here and in the README):

* Time is int64 nanoseconds at every interface (``t_ns``).
* Extrinsic ``T_imu_lidar`` is a 4x4 homogeneous matrix (row-major nested list in YAML) that maps
  LiDAR-frame points into the IMU frame: ``p_imu = R @ p_lidar + t`` (lio-design.md §1,
  Faster-LIO's ``extrinsic_R`` / ``extrinsic_T``). On the command line it is given as
  ``"tx ty tz qx qy qz qw"`` (quaternion in x y z w order).
* The world frame is the IMU frame at the end of initialization (lio-design.md §1), unless
  ``imu.gravity_align_world`` is set, in which case its z axis points up (against gravity).

Each section receives only its own dataclass. Unknown keys are rejected with the nearest valid key
suggested. Presets live in ``adalio/presets/*.yaml`` and are partial: they override defaults.
"""

from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from adalio.errors import ConfigError

MODES = ("fixed", "adaptive", "adaptive+")
ROBUST_KERNELS = ("auto", "huber", "geman_mcclure", "none")
"""``filter.robust_kernel`` (``lio.measurement.robust_row_factors``)."""


def _identity4() -> list[list[float]]:
    return [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]


def _identity3() -> list[list[float]]:
    return [[1.0 if i == j else 0.0 for j in range(3)] for i in range(3)]


@dataclass
class SensorConfig:
    """Topics, extrinsic and time handling of the LiDAR + IMU rig."""

    lidar_topic: str = ""
    """PointCloud2 or Livox CustomMsg topic; empty = auto-detect (the bag's only such topic)."""
    imu_topic: str = ""
    """sensor_msgs/Imu topic; empty = auto-detect (the only Imu topic of the bag)."""
    T_imu_lidar: list[list[float]] = field(default_factory=_identity4)
    """4x4 row-major, maps LiDAR points into the IMU frame: p_imu = R p_lidar + t (metres)."""
    extrinsic_source: str = "auto"
    """'config' (use T_imu_lidar), 'tf_static' (require /tf_static), 'auto' (tf_static if the bag
    has a transform between the two sensors' frame ids, else T_imu_lidar)."""
    imu_rate_hz: float = 400.0
    """Nominal IMU rate (Hz); used for diagnostics and the simulator, never to invent stamps."""
    lidar_rate_hz: float = 10.0
    """Nominal sweep rate (Hz); used to reconstruct per-point times from azimuth when absent."""
    accel_unit: str = "auto"
    """'auto' (g if the static mean norm is near 1), 'm_s2' or 'g'."""
    gyro_unit: str = "rad_s"
    """'rad_s' or 'deg_s' (converted on reading). A deg/s gyro read as rad/s is detected (rates
    beyond 2000 deg/s, or 57x the LiDAR-registered rotation) and stops the run naming this key."""
    gyro_sensitivity: list[list[float]] = field(default_factory=_identity3)
    """3x3 row-major: the gyro reads ``S ω`` for the true rate ``ω`` (its scale factors on the
    diagonal, its cross-axis sensitivity and axis misalignment off it; an IMU intrinsic
    calibration such as Kalibr's ``scale-misalignment`` model or OpenVINS's ``Dw`` gives it).
    adalio reads ``S⁻¹ x`` for every sample ``x`` (after ``gyro_unit``). The identity: taken as
    exact. Within ``MAX_SENSITIVITY_ERROR`` of it per entry."""
    accel_sensitivity: list[list[float]] = field(default_factory=_identity3)
    """The same for the accelerometer (after ``accel_unit``)."""
    point_time_field: str = "auto"
    """Per-point time field name, or 'auto' (t, time, timestamp, timestamps, offset_time, ...),
    or 'none' to reconstruct times from azimuth."""
    point_time_unit: str = "auto"
    """'auto', 's', 'ms', 'us' or 'ns'."""
    point_time_reference: str = "auto"
    """'auto', 'absolute' (epoch time) or 'relative' (offset from the header stamp)."""
    imu_time_offset_s: float = 0.0
    """The IMU's stamps minus the LiDAR's for the same instant (seconds; FAST-LIO's
    ``time_offset_lidar_to_imu``): subtracted from every IMU stamp on reading. Positive when the
    IMU's stamps run late (e.g. stamped on arrival after a USB or driver latency)."""
    imu_time_offset_check: bool = True
    """Check the gyro's timing against the rotation the LiDAR alone registers over the first
    10-60 s of updates (:mod:`adalio.lio.time_offset`); ``adalio run`` then finds the offset
    left after ``imu_time_offset_s`` and restarts with it when it matters."""
    extrinsic_rotation_check: bool = True
    """Check the rotation of ``T_imu_lidar`` against the data over the same updates: the axes
    the gyro turns about against those the LiDAR alone registers (:mod:`adalio.lio.
    extrinsic_check`); ``adalio run`` then finds the rotation left and restarts with the
    corrected extrinsic when it matters."""
    extrinsic_rotation_sigma_deg: float = 0.1
    """How well ``T_imu_lidar``'s rotation is known (degrees, one standard deviation about each
    axis). The filter uses the rotation as exact, so an error in it turns the whole map about
    the first pose (the rows register against a map built through the same rotation) and no
    update can see that: the reported sigmas add it (:mod:`adalio.lio.extrinsic_sigma`),
    narrowed by what the rotation check estimates. 0.1 is a calibrated rig; a rotation read off
    a drawing is good to about 0.5; 0 reports the filter's sigmas alone. After a restart with a
    found rotation, the restarted run's ``config.yaml`` holds the correction's own deviation
    here (at least this value; 0 stays 0)."""
    extrinsic_translation_sigma_m: float = 0.01
    """How well ``T_imu_lidar``'s translation (the lever arm) is known (metres, one standard
    deviation along each axis): the reported sigmas add what an error of it does, a position
    error ``(R₀ - R) δ`` that changes as the rig turns (:mod:`adalio.lio.extrinsic_sigma`),
    narrowed across the rig's vertical by what the lever arm check estimates. 0.01 is a
    calibrated rig's or a careful tape measure's; 0 leaves it out."""
    gyro_axes_sigma_deg: float = 0.0
    """How well the gyro's axes are known against the IMU's frame, the accelerometer's, which
    the trajectory is given in (degrees, one standard deviation about each axis). The rotation
    check measures the gyro's axes against the LiDAR's and cannot tell a turn of the gyro
    inside the IMU (an uncalibrated IMU's axis misalignment) from one of the extrinsic: after a
    restart that also found the gyro's scale off, ``adalio run`` sets it to the rotation it
    applied, and the reported sigmas add it like ``extrinsic_rotation_sigma_deg`` (never
    narrowed by the check, which cannot see it). 0: the gyro's axes are the IMU's."""
    gyro_scale_check: bool = True
    """Check the gyro's scale factors (``gyro_sensitivity``) against the data over the same
    updates: the rates the gyro reads against those the LiDAR alone registers
    (:mod:`adalio.lio.gyro_scale`); ``adalio run`` then finds the scale error left and restarts
    with the corrected ``gyro_sensitivity`` when it matters."""
    extrinsic_translation_check: bool = True
    """Check the translation of ``T_imu_lidar`` (the lever arm) against the data over the same
    updates: the accelerometer against the motion the LiDAR alone registers through it
    (:mod:`adalio.lio.lever_arm`); a significant disagreement is a summary line with the
    correction across the rig's vertical (a hint: no warning, no restart)."""


@dataclass
class PreprocessConfig:
    """Per-scan range gates and decimation (lio-design.md §6.1)."""

    blind_m: float = 0.5
    """Points closer than this to the LiDAR (operator, rig) are dropped (metres)."""
    max_range_m: float = 100.0
    """Points farther than this are dropped (metres)."""
    point_filter_num: int = 1
    """Keep every n-th point of the message (1 = all)."""
    drop_stray_returns: bool = False
    """Drop in every sweep the returns whose range neither the two points before them along
    their ring nor the two after them continue (along a Livox laser: whose ray meets neither
    side's straight line; ``adalio.lio.stray``): dust or rain in front of a surface, multipath
    or cross-talk ghosts behind it, mixed pixels, and thin things. Needs a ring per point (or a
    Livox laser); off by default (README, *Stray returns*): with it off, a sweep drops them
    where its stray returns are more than ``stray_drop_share`` of its points."""
    stray_drop_share: float = 0.02
    """A sweep whose stray returns (``adalio.lio.stray``) are more than this share of its
    finite points drops them (dust, ghosts: a dirty sweep), with the points its ring does not
    continue either but an adjacent ring does, as drop_stray_returns does in every sweep; a
    sweep under it keeps them (simulated clean sweeps hold up to 0.45 %, a real sweep of a
    construction site 1.35 %, sweeps with ghosts on 3 % of the returns 2.9 %: README, *Stray
    returns*). 1 keeps them always, 0 drops them wherever there is one. Needs a ring per
    point."""
    stray_tolerance_m: float = 0.1
    """Stray returns: a point continues its ring within this plus ``stray_tolerance_rel`` times
    its range (the second difference of a surface's ranges: noise and curvature), and an
    adjacent ring's return lies at its range within the same."""
    stray_tolerance_rel: float = 0.02
    """Stray returns: the tolerance's part that grows with the range."""


@dataclass
class ImuConfig:
    """IMU noise, initialization and gravity (lio-design.md §3-4)."""

    gyro_cov: float = 0.1
    """sigma_g^2 of the gyro white noise, used as-is (Faster-LIO ``gyr_cov``)."""
    accel_cov: float = 0.1
    """sigma_a^2 of the accelerometer white noise (Faster-LIO ``acc_cov``)."""
    gyro_bias_cov: float = 1e-4
    """sigma_bg^2 of the gyro bias random walk (Faster-LIO ``b_gyr_cov``)."""
    accel_bias_cov: float = 1e-4
    """sigma_ba^2 of the accel bias random walk (Faster-LIO ``b_acc_cov``)."""
    noise_discretization: str = "dt2"
    """'dt2' (Faster-LIO parity: G carries dt, so Q dt^2 is injected) or 'dt' (Q dt)."""
    gravity_m_s2: float = 9.81
    """Magnitude of gravity (m/s^2)."""
    init_samples: int = 20
    """Minimum number of static IMU samples averaged for gravity and gyro bias (MAX_INI_COUNT)."""
    init_window_s: float = 0.5
    """Length of the IMU window the stillness test looks at, ending at a scan start (seconds)."""
    still_block_s: float = 0.1
    """Stillness test: block length (s). What averages out within a block (noise, tremor,
    vibration) is the sensor's noise; what moves the block means is motion (lio/imu.py)."""
    still_gyro_floor_rad_s: float = 0.01
    """Stillness test: slow rotation (block-mean spread, rad/s) still treated as rest."""
    still_accel_floor_m_s2: float = 0.05
    """Stillness test: slow acceleration (block-mean spread, m/s^2) still treated as rest."""
    still_false_alarm: float = 1e-3
    """Stillness test: probability that a window at rest is judged moving (chi-square level)."""
    noise_source: str = "at_least_config"
    """'at_least_config' (the white-noise density measured at the start, in the still window or
    over a moving start's IMU samples, replaces a sensor's configured one only where it shows
    that sensor noisier beyond the ``still_false_alarm`` level: the configured values are a
    floor; README, Initialization), 'config' (gyro_cov / accel_cov as given) or 'measured' (the
    measured densities replace them). Bias walks always stay as configured."""
    track_noise_ratio: float = 2.0
    """After every scan the white-noise densities are measured again over the last
    ``TRACK_NOISE_WINDOW_S`` of IMU samples (second differences, their median: motion and jolts
    do not count; lio/imu.py ``moving_noise``). Where a sensor's is more than this many times
    the density the filter uses (a vibrating robot, an engine started after the still start),
    the filter uses the measured one from there on, and the summary says so; once crossed,
    later windows raise it by the still start's chi-square rule; never lowered. 0 turns it off,
    and so does ``noise_source: config``. A measurement's own spread is about 10 % in variance,
    so a clean IMU never reaches 2 (README, Initialization)."""
    init_timeout_s: float = 1.0
    """No still window within this long after the first scan: initialize in motion (s)."""
    moving_init_window_s: float = 1.0
    """Moving start: LiDAR-registered scans over this long are fitted against the IMU (s); the
    fit is accepted once the fit over twice this long agrees with it (motion_init step 3c)."""
    moving_init_max_residual_m: float = 0.03
    """Moving start: largest RMS position residual of that fit accepted (m)."""
    moving_init_min_restoring_ratio: float = 0.6
    """Moving start: the fit is refused while its window's LiDAR-only registrations restore, in
    the median, less than this share of the information they claim along their weakest
    translation (re-searched ``adaptive.probe_step_m`` either way: the probe of ``adaptive+``,
    whose ``adaptive.min_restoring_ratio`` has the same default). A registration stuck to its
    map's viewpoint in a corridor fits as well as the true walk, since the IMU does not see a
    constant velocity (README, Initialization)."""
    moving_init_map_leaf_m: float = 0.05
    """Moving start: map cell of the local map the scans are registered against, LiDAR only (m;
    the finer of this and map.map_leaf_m). That map starts from one viewpoint, whose ring lines
    coarse cells sample; measured on the sensor matrix (README, Initialization)."""
    gap_periods: float = 5.0
    """An IMU gap: consecutive samples (or the last one and the scan end) further apart than
    this many nominal sample periods (measured at initialization)."""
    gap_motion_gyro_rad_s_sqrt_hz: float = 0.5
    """Across a gap, the constant-rate motion model's random rate density (rad/s/sqrt(Hz))."""
    gap_motion_accel_m_s2_sqrt_hz: float = 1.0
    """Across a gap, the constant-velocity motion model's random acceleration density
    (m/s^2/sqrt(Hz)): a handheld or driven rig changes speed by about this much per sqrt(s)."""
    max_gap_s: float = 5.0
    """A longer IMU gap stops the run with an error (outputs so far kept)."""
    gravity_align_world: bool = False
    """Rotate the world frame so that its z axis points up (default: world = IMU at init)."""
    rest_prior: bool = True
    """After a static initialization, condition the filter covariance on the still window's
    gyro and specific-force means (lio/state.py, condition_on_rest): the gyro bias and the sum
    of accelerometer bias and gravity tilt start as well known as the window measured them,
    instead of Faster-LIO's independent priors (b_g 0.01 rad/s, b_a 0.03 m/s^2, gravity 0.2 deg),
    so that the first steps along a corridor cannot be explained away as a bias plus a tilt.
    On by default since session 26, together with the filter's errors in variables and support
    test: with the real HILTI hands in the corridor, 5 of 12 runs diverged without them and none
    with them (README, "Session 26: new defaults"). False: Faster-LIO's P0."""
    zero_velocity_update: bool = True
    """While the IMU rests (the stillness test of the initialization, on the last
    ``init_window_s`` of samples before each scan end), the filter takes a zero velocity at the
    scan end as a measurement (a zero-velocity update, as pedestrian and visual-inertial
    navigation do at rest; lio/state.py, ``rest_velocity_update``), unless the filter's
    velocity refutes rest (chi-square gate at ``still_false_alarm``, with the velocity spread
    of the discounted covariance behind the reported sigmas): motion at constant velocity looks
    still to an IMU. Its standard deviation is the velocity that rest-level
    motion makes within one block, ``still_accel_floor_m_s2 * still_block_s``. On by default
    since session 42 (README, Initialization, *Zero-velocity update*); False: no velocity
    information but the LiDAR's after the initialization (Faster-LIO's behaviour)."""
    rest_lidar_check: bool = True
    """A still window must not contradict the LiDAR: an IMU cannot tell rest from a constant
    velocity and rotation rate (a robot already cruising when its recording starts), so a
    static start is checked against LiDAR-only registrations of the scans over
    ``init_window_s`` (those before it, or, at the recording's start, those after it, whose
    poses are then held back until the check has judged, ``Odometry.take_backfill``). When
    they moved beyond rest (``motion_init.lidar_rest_check``), the window is refused and the
    start is a moving start (README, Initialization, *A still window the LiDAR refutes*).
    False: every still window starts the filter at rest (the behaviour before session 76)."""
    backfill_s: float = 60.0
    """Scans read before the initialization (a moving start's refused fits, or motion before a
    still window) get their pose from a time-reversed pass of the filter, started from the first
    pose and run back through them (lio/odometry.py, "Backfill"). At most this many seconds of
    such scans are kept for it, the latest ones (s; 0 = off)."""
    backfill_after_s: float = 10.0
    """The backfill runs once the filter has tracked this long after its initialization, from
    its state and map then (s): by then its gravity and biases have converged from the
    initialization's (a moving start's gravity is 0.1-1 deg off at the hand-over)."""


@dataclass
class MapConfig:
    """iVox local map (lio-design.md §7)."""

    ivox_resolution_m: float = 0.5
    """iVox voxel edge (metres); fixed for the whole run."""
    nearby_type: int = 18
    """Neighbourhood searched around the query voxel: 0 (centre), 6, 18 or 26."""
    capacity_voxels: int = 1_000_000
    """Voxels kept; the least recently inserted are evicted beyond this."""
    max_points_per_voxel: int = 64
    """Per-voxel cap (numba deviation from upstream's unbounded lists); oldest replaced."""
    map_leaf_m: float = 0.2
    """Map cell (Faster-LIO ``filter_size_map``): the map keeps at most one point per cell (m)."""
    cell_follows_voxel: bool = True
    """Map cell of a scan = min(map_leaf_m, the active parameter set's voxel_size_m), so a
    degenerate scan (finer leaf) also densifies the map where it sees."""
    cell_point: str = "first"
    """Which point a map cell keeps: 'first' (the first point to reach it; descending past a wall,
    that layers the wall's map points one cell apart) or 'uniform' (a uniform sample, by a hash of
    their coordinates, of the points that reached it within cell_sample_scans: better in the
    simulated spiral shaft on the XT-32 and the OS1-64, worse in the corridor; benchmark log,
    sessions 35, 39 and 79)."""
    cell_sample_scans: int = 5
    """With cell_point 'uniform': a cell samples the points of the scans within this many of the
    one that first filled it, then stays fixed (a walking sensor's field-of-view edge crosses a
    0.1-0.2 m cell in 1-7 scans at 10 Hz); 0: never fixed, so the map follows later poses."""
    remove_moving: bool = True
    """Keep moving things (people walking by) out of the update and the map, by where the
    LiDAR has seen through (``lio/moving.py``; README, "Moving things"): a recently inserted map
    point that a sweep's rays pass is removed, a sweep's point in space an earlier sweep saw
    through takes no part in the update and is not inserted, nor do its points on the same body
    (moving_body_m), and a sweep's point next to what was seen through enters the map
    moving_probation_s late. False: every point goes in, as Faster-LIO."""
    moving_margin_m: float = 0.1
    """remove_moving: a point is in free space only if the rays around it returned farther by
    more than this plus moving_margin_fraction of its range (metres; about three standard
    deviations of the point-to-plane noise, filter.laser_point_cov 0.001 m²)."""
    moving_margin_fraction: float = 0.01
    """remove_moving: the margin's part proportional to the range (pose and beam width)."""
    moving_pixel_deg: float = 1.0
    """remove_moving: pixel of the sweeps' range images, in elevation and azimuth (degrees)."""
    moving_lookback_s: float = 0.5
    """remove_moving: a sweep's points are tested against the sweep about this long before
    (a person walking at 1 m/s has moved half a metre, well beyond the margin)."""
    moving_window_s: float = 3.0
    """remove_moving: map points inserted within this long are tested against each sweep."""
    moving_probation_s: float = 0.3
    """remove_moving: a scan's points near where a sweep saw through lately (moving_near_m)
    enter the map this long after the scan, unless a sweep in between saw through them:
    someone walking at 1 m/s has moved 0.3 m by then, so the scans right after never match
    their points to the walker's last positions."""
    moving_near_m: float = 0.5
    """remove_moving: a scan's points within this of a point a sweep saw through within the
    last moving_lookback_s wait for their probation (the back of someone walking away, whose
    last positions are being seen through)."""
    moving_surface_check: bool = True
    """remove_moving: a map point a sweep sees through is removed only if no return of the
    sweep lies within moving_margin_m plus moving_margin_fraction and one pixel
    (moving_pixel_deg) of its range of it: a point on the edge of a surface the sweep still
    sees beside it (a stair's nosing, a wall's end, a rail), placed a few centimetres off by the
    poses in between, has not moved away (README, "Moving things"). False: session 65's test,
    free space alone."""
    moving_surface_check_behind: bool = True
    """moving_surface_check: the returns behind the map point along its ray (farther than it
    by more than moving_margin_m) keep it too. False: only those beside or in front of it, so
    the trail of someone walking away ahead is carved although their back is within the
    check's reach behind it: the corridor with people loses fewer walks, the spiral shaft
    loses some centimetres (README, "Moving things", session 71)."""
    moving_body_m: float = 0.3
    """remove_moving: a sweep's points within this of its own points in free space, or of a
    point a sweep saw through within the last moving_lookback_s, are on the same moving body
    (the visibility tests catch a third to two thirds of a walker's points) and are kept out
    like them, no part in the update and not inserted, unless the map holds a point within
    moving_margin_m or the map's cell of them, the larger (the floor under a walker's feet).
    0.3 m: about a person's width less a margin (default since session 68, with
    moving_surface_check; README, "Moving things"); 0: only the points the visibility tests
    catch."""


@dataclass
class FilterConfig:
    """Iterated error-state Kalman filter and point-to-plane update (lio-design.md §6)."""

    max_iterations: int = 3
    """N_max of the iterated update (up to N_max + 1 evaluations)."""
    knn_k: int = 5
    """Neighbours per point for the plane fit."""
    min_neighbors: int = 3
    """Fewer neighbours than this: no correspondence."""
    laser_point_cov: float = 0.001
    """Point-to-plane residual variance R (m^2)."""
    convergence_eps: float = 0.001
    """Per-component convergence threshold of the error-state step."""
    estimate_extrinsic: bool = False
    """Estimate the LiDAR-IMU extrinsic online (off for calibrated rigs)."""
    plane_fit: str = "ls"
    """'ls' (a^T x = -1 least squares, Faster-LIO parity) or 'pca'."""
    knn_max_range_m: float = 5.0
    """Neighbours farther than this are never returned by the map search (iVox max_range)."""
    plane_min_extent_fraction: float = 0.25
    """A plane needs neighbours spanning sqrt(middle covariance eigenvalue) >= this fraction of
    the map cell; rejects fits on stray clusters (0 disables)."""
    one_ring_max_deg: float = 0.0
    """Use a plane only where its neighbours, seen from the scan's LiDAR position, spread over
    at least this many degrees of elevation about the LiDAR's spin axis. A spinning LiDAR's ring
    is a cone of one elevation; neighbours one ring laid down from (near) here lie on it, and
    the plane fitted to them is the cone's tangent (it contains the rays), not the surface,
    whose tilt about the ring no single ring shows. A point of a later ring off that line then
    gets a residual from the cone's tilt: the floor and ceiling rows of a 16-ring LiDAR pulled
    the pitch into the walk by 0.2-0.4 degrees as a walk set off from a still start (README,
    "Session 43"). Far below any spinning LiDAR's ring spacing (0.35 degrees on a 128-ring
    unit, 2 on a VLP-16), so a plane fitted across two rings passes. Applies to the filter,
    not to the moving start's registration. 0 disables it."""
    plane_within_support: bool = True
    """Use a plane only where the query lies within its neighbours' span along the plane (not
    beyond every neighbour): no residuals against extrapolated planes. Applies to the filter,
    not to the moving start's registration. On by default since session 26, with
    ``errors_in_variables`` and ``imu.rest_prior`` (README, "Session 26: new defaults"); False:
    Faster-LIO's rule (every valid plane of the k nearest map points)."""
    share_weighting: bool = True
    """Residuals whose nearest map point is the same count as one measurement (each row's
    variance is multiplied by the group size)."""
    plane_uncertainty_weighting: bool = True
    """Scale each residual's variance by 1 + 1/k + rho^2 / (k lambda_mid), the offset and tilt
    uncertainty of a k-neighbour plane fit at the query's in-plane distance rho."""
    robust_kernel: str = "auto"
    """'auto' | 'huber' | 'geman_mcclure' | 'none': iteratively reweighted rows in the filter's
    update (``measurement.robust_row_factors``), so that rows whose map plane is not the surface
    they lie on pull less. A row's kernel width is ``robust_scale`` times the spread its residual
    has if the row is right: the scan's own residual noise (1.4826 x the median |residual|) and
    what the predicted discounted pose covariance (the one behind the reported sigmas) adds
    along the row: a row that corrects an error the estimate admits is not an outlier. 'auto'
    (since session 31): 'huber' in modes fixed and adaptive (spiral shaft 12.1 -> 5.9 cm, and
    equal or better means and worsts on every scene, sensor and IMU of the matrix), 'none' in
    adaptive+ (with a kernel its stairwell diverged) and in the backfill's reversed pass of an
    adaptive run (since session 97: with Huber it stalled along a Mid-360's corridor, README,
    Initialization, "Backfill"). 'geman_mcclure' silences far rows (spiral
    4.8 cm) but let a corridor slip along its axis with a noisy IMU; 'none' is Faster-LIO's
    plain least squares (README, "Session 31")."""
    robust_scale: float = 0.0
    """robust_kernel: the kernel width in units of a row's spread; 0: the kernel's usual width
    (Huber 1.345, Geman-McClure 3; ``measurement.KERNEL_WIDTH``)."""
    gate_sigmas: float = 3.0
    """On the scan after a LiDAR gap or across an IMU gap, also accept a row whose residual lies
    within this many standard deviations of what the predicted pose's covariance (the
    discounted one, as the robust kernel's) lets it be, where FAST-LIO2's range gate
    (``|p_L| > 81 r²``: 11 cm at 1 m, 33 cm at 9 m) rejects it. After seconds without a scan the
    prediction can be decimetres off; the range gate then keeps only the rows that cannot
    correct that error, and the scan locks onto the map where it is and enters the map there
    (README, "LiDAR gaps"). Every other scan has the range gate alone, as FAST-LIO2: applied to
    every scan, this gate cost the fixed mode's demo shaft 7.6 -> 19.8 cm. 0: the range gate
    only."""
    refit_every_iteration: bool = False
    """Re-search and refit planes at every iteration (FAST-LIO2) instead of on convergence only."""
    research_min_shift_m: float = 0.005
    """A re-search is skipped (the correspondences of the last search are kept) while no scan
    point has moved more than this since that search (0: always re-search, as FAST-LIO2). 5 mm is
    a sixth of the point-to-plane noise (sqrt(laser_point_cov)) and a fortieth of the map cell;
    on the 4 scenes x 4 seeds of bench_modes it halves the searches at unchanged accuracy in
    mode adaptive (adaptive+ on the spiral: 15.0 instead of 13.3 cm, see the README)."""
    map_uncertainty: bool = True
    """Report world-frame sigmas that include the map's own uncertainty (the covariance of the
    poses that inserted the matched map points, moved by their lever arm; lio/map_uncertainty.py)
    instead of the filter's covariance alone, which is relative to a map it treats as exact. Only
    the reported sigmas change, never the trajectory."""
    errors_in_variables: bool = True
    """The update corrects for the noise of the fitted plane normals (errors in variables,
    ``ieskf.errors_in_variables``): each iteration's gradient loses the pull that a normal's
    tilt puts into the residual of a point beyond its neighbours (``measurement.
    normal_noise_terms``), and the information keeps only what that tilt does not fake, with
    the point noise taken from each row's neighbours (their scatter about their plane). On by
    default since session 26, with ``plane_within_support`` and ``imu.rest_prior`` (README,
    "Session 26: new defaults"); with the support test it costs 1.2-1.3x the time per scan
    (an idle machine, session 25). False: the plain point-to-plane normal equations
    (Faster-LIO's). Pose block only (``estimate_extrinsic`` off)."""
    sigmas_discount_normal_noise: bool = True
    """Report sigmas from a covariance that does not count the information the noise of the
    fitted plane normals fakes (``measurement.normal_noise_information``): e.g. the height that
    walls whose fitted normals lean by noise claim in a shaft. The filter's own covariance and
    the trajectory are unchanged; only the reported sigmas (and the map's, which inherits them)
    grow where the scene holds no information."""
    sigmas_deskew_noise: bool = True
    """Report sigmas whose attitude holds the rotation the gyro's white noise puts into the
    scan's undistortion (``lio/map_uncertainty.py``, ``deskew_covariance``): the points are
    moved to the scan's end with the integrated gyro, a random walk pinned at that end, and
    the registration takes its average over the sweep (variance ``q_g T / 3`` per axis for a
    sweep of T seconds and a gyro noise density² q_g), which no update sees. It enters the map's
    uncertainty with the lever arm (not the first scan's: that scan defines the world, and its
    map stays exact, as before). Only the reported sigmas change, never the trajectory."""
    sigmas_height_blind: bool = True
    """Report sigmas that take no height from a height-blind scan: one whose claimed height
    information lies mostly (more than half of ``HᵀH``'s world-z diagonal) in the directions
    the normals' discount judges fake (``ieskf.height_blind``). On such a scan the sigmas'
    covariance takes the scan's information with the height marginalised out, so its height is
    left to the IMU's model (in a floor-blind stairwell the rows that remain hold the height
    with a few m⁻² per scan that the discount cannot tell from bias). A covariance of its own,
    propagated with the filter's: the robust kernel's and the trajectory are unchanged.
    Needs ``sigmas_discount_normal_noise``. On by default since session 46 (README,
    Benchmarks, *Session 46*)."""
    local_surface_check: bool = False
    """Drop a row whose map plane disagrees with the scan's own surface at the point
    (``lio/local_surface.py``): the plane fitted to the samples around the point on its ring and
    the two adjacent rings, where that patch is one plane and at most
    ``local_surface_max_patch_m`` tall. Needs the scans' ring field (``Scan.ring``); without it, or in
    the backfill's reverse pass, no row is checked."""
    local_surface_max_angle_deg: float = 30.0
    """local_surface_check: a row is dropped when its map plane's normal is more than this off
    the local plane's."""
    local_surface_max_patch_m: float = 0.1
    """local_surface_check: a point is checked only within the range at which its patch (two
    ring spacings tall) is at most this tall (the degenerate voxel leaf: 2.9 m for the XT-32's
    1° rings). Farther out the rows a corridor would lose are its door frames and ends, which
    carry the along-axis information (``lio/local_surface.py``)."""
    local_surface_window_ring_spacings: float = 1.5
    """local_surface_check: the patch's half-width in azimuth, in ring spacings (the sweep's
    median elevation step), so it keeps its angular size at any column count."""
    map_provenance_cell_m: float = 0.5
    """Cell (m) at which map_uncertainty remembers which scan first filled the map."""
    map_error_correlated: bool = True
    """With map_uncertainty: add the filter's covariance and the map's with a bound that holds
    whatever their correlation (lio/map_uncertainty.py, ``world_covariance``), instead of as
    independent errors. In shafts and stairwells a scan's registration bias has the sign of the
    bias of the map it registers to, so the map's error grows linearly, not as a random walk."""


@dataclass
class ParamSet:
    """The three data-association parameters AdaLIO switches (paper Table I, lio-design.md §9)."""

    voxel_size_m: float = 0.2
    """Leaf of the scan voxel-grid downsampling (metres)."""
    search_radius_m: float = 3.0
    """Gate on the farthest of the k neighbours (metres, lio-design.md §9.4)."""
    plane_margin_m: float = 0.05
    """Max |n^T q + d| of every neighbour for a valid plane (metres)."""


def _degenerate_set() -> ParamSet:
    return ParamSet(voxel_size_m=0.1, search_radius_m=2.0, plane_margin_m=0.025)


@dataclass
class AdaptiveConfig:
    """Degeneracy detection and parameter switching (lio-design.md §9)."""

    mode: str = "adaptive"
    """'fixed' (Faster-LIO, general set always), 'adaptive' (AdaLIO), 'adaptive+' (localizability)."""
    general: ParamSet = field(default_factory=ParamSet)
    """Parameters in the general (open) case."""
    degenerate: ParamSet = field(default_factory=_degenerate_set)
    """Parameters in the degenerate (narrow) case."""
    detector: str = "count"
    """'count' (public code: N_down < tau_n or N_near < tau_near), 'near_ratio' (paper: N_down <
    tau_n and N_near / N_down > near_ratio)."""
    tau_n: int = 800
    """Threshold on the number of downsampled points (general leaf)."""
    tau_near: int = 500
    """Threshold on the number of downsampled points with |x|, |y| < d_xy."""
    d_xy_m: float = 5.0
    """Half-width of the 'near' box around the sensor (metres, z ignored)."""
    near_ratio: float = 0.8
    """Fraction of near points for the paper's reading."""
    hold_scans: int = 3
    """The degenerate set stays active for this many scans after the last trigger (incl. it)."""
    use_localizability_trigger: bool = True
    """Also trigger on a weak information direction (modes adaptive and adaptive+)."""
    min_eigen_ratio: float = 0.02
    """Trigger when the smallest translational eigenvalue / largest is below this."""
    min_voxel_size_m: float = 0.05
    """adaptive+: smallest leaf tried while refining."""
    point_budget: int = 8000
    """adaptive+: max downsampled points per scan while refining."""
    observable_eigen_ratio: float = 0.01
    """adaptive+: directions with eigenvalue ratio below this are left at the IMU prediction."""
    probe_directions: int = 3
    """adaptive+: re-association probes along this many weakest directions (0 disables)."""
    probe_step_m: float = 0.05
    """adaptive+: probe displacement (RMS motion of the scan points, metres)."""
    min_restoring_ratio: float = 0.6
    """adaptive+: a probed direction whose re-associated residuals restore less than this
    fraction of the information H^T H claims is left at the IMU prediction."""
    hold_horizontal: bool = False
    """adaptive+: also leave at the IMU prediction a weak direction (probed, or below
    observable_eigen_ratio) that is mostly a horizontal translation (|dp_xy|² above half of its
    mean square point motion), as before session 30. Off: the IMU predicts the horizontal
    position worst (a tilt error projects gravity into it), and such a direction is often weak
    but real, as a corridor's axis (``lio/degeneracy.py`` §5)."""


@dataclass
class OutputConfig:
    """What `adalio run` writes."""

    map_format: str = "ply"
    """'ply' (binary little-endian) or 'pcd' (binary)."""
    map_voxel_m: float = 0.05
    """Leaf of the voxel filter applied to the exported map (0 = no filter)."""
    map_min_returns: int = 2
    """The exported map keeps the points of the map cells (``map.map_leaf_m``) that at least
    this many of the scans' points reached over the run, and the others that lie on a plane of
    the map: a stray return (dust, rain, a ghost) is seen once where a surface is seen again by
    every sweep that looks at it, or lies in a plane a ring swept over (1 = keep all)."""
    dense_map_voxel_m: float = 0.05
    """``map_dense.ply`` (or ``.pcd``): every still point of every scan at its scan's updated
    pose, one per voxel of this edge (m; at least 0.01), kept where the map written out holds
    a point within one ``map.map_leaf_m`` (``adalio.lio.dense_map``); ``adalio run
    --dense-map`` sets it. 0: not kept, not written."""


@dataclass
class Config:
    """The effective configuration of a run."""

    sensor: SensorConfig = field(default_factory=SensorConfig)
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    map: MapConfig = field(default_factory=MapConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    adaptive: AdaptiveConfig = field(default_factory=AdaptiveConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    # ------------------------------------------------------------------ helpers
    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None)

    def T_imu_lidar(self) -> np.ndarray:
        """The extrinsic as a validated 4x4 float64 array (a rigid transform whose translation is
        at most ``MAX_LEVER_ARM_M`` long)."""
        T = validate_transform(self.sensor.T_imu_lidar, "sensor.T_imu_lidar")
        t = T[:3, 3]
        length = float(np.linalg.norm(t))
        if length > MAX_LEVER_ARM_M:
            def metres(scale: float) -> str:
                return "[" + ", ".join(f"{v * scale:.4g}" for v in t) + "]"
            raise ConfigError(
                f"sensor.T_imu_lidar's translation {metres(1.0)} is {length:.1f} m long, more "
                f"than the {MAX_LEVER_ARM_M:g} m any one rig spans: give it in metres (read as "
                f"millimetres, as Ouster's metadata gives it, it is {metres(1e-3)} m; as "
                f"centimetres {metres(1e-2)} m)")
        return T

    def validate(self) -> Config:
        """Check enumerations, ranges and the extrinsic; raise ConfigError naming the key and
        what it allows (rules: ``CHOICES``, ``RANGES``, ``_cross_checks``)."""
        values = _leaf_values(self)
        for key, allowed in CHOICES.items():
            _choice(values[key], allowed, key)
        for key, rule in RANGES.items():
            rule.check(key, values[key])
        _cross_checks(self)
        self.T_imu_lidar()
        validate_sensitivity(self.sensor.gyro_sensitivity, "sensor.gyro_sensitivity")
        validate_sensitivity(self.sensor.accel_sensitivity, "sensor.accel_sensitivity")
        return self


MAX_SENSITIVITY_ERROR = 0.1
"""``sensor.gyro_sensitivity`` and ``sensor.accel_sensitivity`` may differ from the identity by
at most this per entry: MEMS scale factors and cross-axis sensitivities are off by 0.1-3 %; a
matrix further off is not a sensitivity (a frame's rotation belongs in ``T_imu_lidar``, a unit in
``gyro_unit`` / ``accel_unit``)."""


def validate_sensitivity(S: Any, where: str) -> np.ndarray:
    """Return ``S`` as a 3x3 float64 sensitivity matrix or raise ConfigError naming ``where``."""
    M = _finite_matrix(S, 3, where)
    off = float(np.abs(M - np.eye(3)).max())
    if off > MAX_SENSITIVITY_ERROR:
        raise ConfigError(f"{where} differs from the identity by {off:.3g} in an entry, more "
                          f"than the {MAX_SENSITIVITY_ERROR:g} a sensitivity (scale factors, "
                          f"cross-axis) does: a frame's rotation belongs in sensor.T_imu_lidar, "
                          f"a unit in sensor.gyro_unit / sensor.accel_unit")
    return M


def _choice(value: Any, allowed: tuple, key: str) -> None:
    if value not in allowed:
        raise ConfigError(f"{key} must be one of {', '.join(map(str, allowed))} (got {value!r})")


def _leaf_values(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted key -> value of every non-section field (``{"sensor.imu_rate_hz": 400.0, ...}``)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            out.update(_leaf_values(value, key + "."))
        else:
            out[key] = value
    return out


@dataclass(frozen=True)
class Range:
    """Allowed interval of a numeric field; ``lo``/``hi`` None = unbounded on that side, and
    ``lo_open``/``hi_open`` exclude the bound itself. Non-finite values are always rejected."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def describe(self) -> str:
        if self.lo is not None and self.hi is not None:
            return (f"in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}"
                    f"{')' if self.hi_open else ']'}")
        if self.lo is not None:
            return f"{'>' if self.lo_open else '>='} {self.lo:g}"
        if self.hi is not None:
            return f"{'<' if self.hi_open else '<='} {self.hi:g}"
        return "finite"

    def allows(self, value: float) -> bool:
        if not np.isfinite(value):
            return False
        if self.lo is not None and (value <= self.lo if self.lo_open else value < self.lo):
            return False
        return self.hi is None or (value < self.hi if self.hi_open else value <= self.hi)

    def check(self, key: str, value: Any) -> None:
        try:
            ok = not isinstance(value, bool) and self.allows(float(value))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            finite = isinstance(value, (int, float)) and not isinstance(value, bool) \
                and not np.isfinite(float(value))
            need = f"finite and {self.describe()}" if finite and self.describe() != "finite" \
                else self.describe()
            raise ConfigError(f"{key} must be {need} (got {value!r})")


POSITIVE = Range(0.0, lo_open=True)
NON_NEGATIVE = Range(0.0)
AT_LEAST_ONE = Range(1)
FRACTION = Range(0.0, 1.0)

CHOICES: dict[str, tuple] = {
    "sensor.extrinsic_source": ("auto", "config", "tf_static"),
    "sensor.accel_unit": ("auto", "m_s2", "g"),
    "sensor.point_time_unit": ("auto", "s", "ms", "us", "ns"),
    "sensor.point_time_reference": ("auto", "absolute", "relative"),
    "imu.noise_discretization": ("dt2", "dt"),
    "imu.noise_source": ("config", "measured", "at_least_config"),
    "sensor.gyro_unit": ("rad_s", "deg_s"),
    "map.nearby_type": (0, 6, 18, 26),
    "map.cell_point": ("first", "uniform"),
    "filter.plane_fit": ("ls", "pca"),
    "filter.robust_kernel": ROBUST_KERNELS,
    "adaptive.mode": MODES,
    "adaptive.detector": ("count", "near_ratio"),
    "output.map_format": ("ply", "pcd"),
}
"""Fields with a fixed set of values."""

RANGES: dict[str, Range] = {
    "sensor.imu_rate_hz": POSITIVE,
    "sensor.lidar_rate_hz": POSITIVE,
    "sensor.imu_time_offset_s": Range(-1.0, 1.0),
    "sensor.extrinsic_rotation_sigma_deg": Range(0.0, 10.0),
    "sensor.gyro_axes_sigma_deg": Range(0.0, 10.0),
    "sensor.extrinsic_translation_sigma_m": Range(0.0, 1.0),
    "preprocess.blind_m": NON_NEGATIVE,
    "preprocess.max_range_m": POSITIVE,
    "preprocess.point_filter_num": AT_LEAST_ONE,
    "preprocess.stray_tolerance_m": NON_NEGATIVE,
    "preprocess.stray_tolerance_rel": NON_NEGATIVE,
    "preprocess.stray_drop_share": Range(0.0, 1.0),
    "imu.gyro_cov": POSITIVE,
    "imu.accel_cov": POSITIVE,
    "imu.gyro_bias_cov": NON_NEGATIVE,
    "imu.accel_bias_cov": NON_NEGATIVE,
    "imu.gravity_m_s2": POSITIVE,
    "imu.init_samples": AT_LEAST_ONE,
    "imu.init_window_s": POSITIVE,
    "imu.still_block_s": POSITIVE,
    "imu.still_gyro_floor_rad_s": NON_NEGATIVE,
    "imu.still_accel_floor_m_s2": NON_NEGATIVE,
    "imu.still_false_alarm": Range(0, 1, lo_open=True, hi_open=True),
    "imu.track_noise_ratio": Range(0.0),
    "imu.init_timeout_s": NON_NEGATIVE,
    "imu.moving_init_window_s": POSITIVE,
    "imu.moving_init_max_residual_m": POSITIVE,
    "imu.moving_init_map_leaf_m": POSITIVE,
    "imu.moving_init_min_restoring_ratio": FRACTION,
    "imu.backfill_s": NON_NEGATIVE,
    "imu.backfill_after_s": NON_NEGATIVE,
    "imu.gap_periods": Range(1, lo_open=True),
    "imu.gap_motion_gyro_rad_s_sqrt_hz": POSITIVE,
    "imu.gap_motion_accel_m_s2_sqrt_hz": POSITIVE,
    "imu.max_gap_s": POSITIVE,
    "map.ivox_resolution_m": POSITIVE,
    "map.capacity_voxels": AT_LEAST_ONE,
    "map.max_points_per_voxel": AT_LEAST_ONE,
    "map.cell_sample_scans": Range(0),
    "map.map_leaf_m": POSITIVE,
    "map.moving_margin_m": NON_NEGATIVE,
    "map.moving_margin_fraction": Range(0.0, 1.0),
    "map.moving_pixel_deg": Range(0.05, 10.0),
    "map.moving_lookback_s": POSITIVE,
    "map.moving_window_s": NON_NEGATIVE,
    "map.moving_probation_s": NON_NEGATIVE,
    "map.moving_near_m": NON_NEGATIVE,
    "map.moving_body_m": NON_NEGATIVE,
    "filter.max_iterations": AT_LEAST_ONE,
    "filter.knn_k": Range(3),
    "filter.min_neighbors": Range(3),
    "filter.laser_point_cov": POSITIVE,
    "filter.robust_scale": NON_NEGATIVE,
    "filter.gate_sigmas": NON_NEGATIVE,
    "filter.convergence_eps": POSITIVE,
    "filter.knn_max_range_m": POSITIVE,
    "filter.plane_min_extent_fraction": NON_NEGATIVE,
    "filter.one_ring_max_deg": Range(0.0, 90.0),
    "filter.research_min_shift_m": NON_NEGATIVE,
    "filter.map_provenance_cell_m": POSITIVE,
    "filter.local_surface_max_angle_deg": Range(0.0, 90.0, lo_open=True),
    "filter.local_surface_max_patch_m": POSITIVE,
    "filter.local_surface_window_ring_spacings": POSITIVE,
    **{f"adaptive.{s}.{f}": POSITIVE for s in ("general", "degenerate")
       for f in ("voxel_size_m", "search_radius_m", "plane_margin_m")},
    "adaptive.tau_n": NON_NEGATIVE,
    "adaptive.tau_near": NON_NEGATIVE,
    "adaptive.d_xy_m": POSITIVE,
    "adaptive.near_ratio": FRACTION,
    "adaptive.hold_scans": AT_LEAST_ONE,
    "adaptive.min_eigen_ratio": FRACTION,
    "adaptive.min_voxel_size_m": POSITIVE,
    "adaptive.point_budget": AT_LEAST_ONE,
    "adaptive.observable_eigen_ratio": FRACTION,
    "adaptive.probe_directions": Range(0, 6),
    "adaptive.probe_step_m": POSITIVE,
    "adaptive.min_restoring_ratio": FRACTION,
    "output.map_voxel_m": NON_NEGATIVE,
    "output.map_min_returns": AT_LEAST_ONE,
    "output.dense_map_voxel_m": NON_NEGATIVE,
}
"""Allowed range of every numeric field (a new numeric field needs one line here; the tests
check that every int/float field has a rule)."""


def _cross_checks(cfg: Config) -> None:
    """Rules that relate two fields."""
    if not cfg.preprocess.max_range_m > cfg.preprocess.blind_m:
        raise ConfigError(f"preprocess.max_range_m must be > preprocess.blind_m (got "
                          f"{cfg.preprocess.max_range_m} <= {cfg.preprocess.blind_m})")
    if cfg.filter.min_neighbors > cfg.filter.knn_k:
        raise ConfigError(f"filter.min_neighbors must be <= filter.knn_k (got "
                          f"{cfg.filter.min_neighbors} > {cfg.filter.knn_k})")
    dense = cfg.output.dense_map_voxel_m
    if 0.0 < dense < DENSE_MAP_MIN_VOXEL_M:
        raise ConfigError(f"output.dense_map_voxel_m must be 0 (no dense map) or at least "
                          f"{DENSE_MAP_MIN_VOXEL_M:g} m (got {dense:g})")


DENSE_MAP_MIN_VOXEL_M = 0.01
"""The smallest voxel of the dense map (:mod:`adalio.lio.dense_map`): finer gains nothing over
a spinning LiDAR's 1-3 cm of range noise and leaves its 21-bit voxel keys less than ±10 km."""


MAX_LEVER_ARM_M = 10.0
"""The longest translation ``sensor.T_imu_lidar`` may hold. A LiDAR and its IMU on one rig are
centimetres to a metre or two apart; a translation typed in millimetres (Ouster's metadata gives
its transforms in mm) comes out tens of metres long, and the run would still track, metres
off without a word (the 14 s hall walk: 0.17 cm right, 2.3 m with the HILTI rig's 55 mm lever
arm read as 55 m)."""


def _finite_matrix(value: Any, n: int, where: str) -> np.ndarray:
    """``value`` as a finite n x n float64 array, or a ConfigError naming ``where``."""
    try:
        M = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where} must be a {n}x{n} matrix of numbers") from None
    if M.shape != (n, n) or not np.all(np.isfinite(M)):
        raise ConfigError(f"{where} must be a finite {n}x{n} matrix (got shape {M.shape})")
    return M


def validate_transform(T: Any, where: str) -> np.ndarray:
    """Return ``T`` as a 4x4 float64 rigid transform or raise ConfigError naming ``where``."""
    M = _finite_matrix(T, 4, where)
    R = M[:3, :3]
    if (np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1.0) > 1e-3
            or np.abs(M[3] - [0, 0, 0, 1]).max() > 1e-9):
        raise ConfigError(f"{where} is not a rigid transform: its 3x3 block must be a rotation "
                          "(orthonormal, det +1) and its last row 0 0 0 1")
    # re-orthonormalize small rounding errors of hand-typed matrices
    U, _, Vt = np.linalg.svd(R)
    M = M.copy()
    M[:3, :3] = U @ Vt
    return M


def transform_from_xyz_quat(text: str, where: str = "--extrinsic") -> list[list[float]]:
    """Parse ``"tx ty tz qx qy qz qw"`` into a 4x4 nested list (rotation must be a unit quat)."""
    try:
        vals = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise ConfigError(f"{where} must be 7 numbers 'tx ty tz qx qy qz qw' (got {text!r})") \
            from None
    if len(vals) != 7 or not np.all(np.isfinite(vals)):
        raise ConfigError(f"{where} must be 7 numbers 'tx ty tz qx qy qz qw' (got {text!r})")
    q = np.array(vals[3:])
    norm = np.linalg.norm(q)
    if abs(norm - 1.0) > 1e-3:
        raise ConfigError(f"{where}: quaternion (qx qy qz qw) has norm {norm:.4f}, not 1: "
                          "it is not a rotation")
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
    T[:3, 3] = vals[:3]
    return T.tolist()


# ---------------------------------------------------------------------- loading
RETIRED_KEYS = {
    "imu.still_gyro_rad_s": "the stillness test adapts to the IMU's own noise now "
                            "(imu.still_gyro_floor_rad_s)",
    "imu.still_accel_m_s2": "the stillness test adapts to the IMU's own noise now "
                            "(imu.still_accel_floor_m_s2)",
}
"""Keys of earlier versions, ignored with a warning so that old config.yaml files still load."""
OUTPUT_ONLY_KEYS = ("measured",)
"""Top-level keys that ``adalio run`` writes into config.yaml for information (the IMU
calibration measured at initialization); ignored when the file is read back."""


def _key_hint(key: str, prefix: str, names: Any) -> str:
    """The '; did you mean ...' of an unknown key, as a dotted key: a setting of that very name
    in another section first (a key at the wrong level: ``voxel_size_m`` at the top,
    ``filter.map_voxel_m``), else a close name in the same section, else a close name in
    another section, else the section's valid keys."""
    dotted = (prefix + ".") if prefix else ""
    leaves = list(_leaf_values(Config()))
    same = [k for k in leaves if k.rsplit(".", 1)[-1] == key]
    close = difflib.get_close_matches(key, list(names), n=1, cutoff=0.5)
    if close and not same:
        return f"; did you mean '{dotted}{close[0]}'?"
    if not same:
        near = difflib.get_close_matches(key, [k.rsplit(".", 1)[-1] for k in leaves], n=1,
                                         cutoff=0.8)
        same = [k for k in leaves if near and k.rsplit(".", 1)[-1] == near[0]]
    if same:
        return f"; did you mean '{same[0]}'?" + (f" (or {', '.join(same[1:4])})"
                                                 if len(same) > 1 else "")
    return f"; valid keys: {', '.join(dotted + n for n in names)}"


def _merge_into(obj: Any, data: dict[str, Any], prefix: str) -> None:
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix or 'config'} must be a mapping of keys to values")
    names = {f.name: f for f in dataclasses.fields(obj)}
    for key, value in data.items():
        full = f"{prefix}.{key}" if prefix else str(key)
        if full in RETIRED_KEYS or (not prefix and key in OUTPUT_ONLY_KEYS):
            if full in RETIRED_KEYS:
                import warnings

                warnings.warn(f"config key '{full}' is ignored: {RETIRED_KEYS[full]}",
                              stacklevel=2)
            continue
        if key not in names:
            raise ConfigError(f"unknown config key '{full}'{_key_hint(str(key), prefix, names)}")
        current = getattr(obj, key)
        path = f"{prefix}.{key}" if prefix else key
        if dataclasses.is_dataclass(current):
            _merge_into(current, value, path)
            continue
        setattr(obj, key, _coerce(current, value, path))


def _coerce(current: Any, value: Any, path: str) -> Any:
    try:
        if isinstance(current, bool):
            if isinstance(value, bool):
                return value
            if isinstance(value, str) and value.lower() in ("true", "false", "yes", "no", "1", "0"):
                return value.lower() in ("true", "yes", "1")
            raise ValueError
        if isinstance(current, int):
            if isinstance(value, bool) or float(value) != int(float(value)):
                raise ValueError
            return int(float(value))
        if isinstance(current, float):
            if isinstance(value, bool):
                raise TypeError
            return float(value)
        if isinstance(current, str):
            if not isinstance(value, (str, int, float)):
                raise TypeError
            return str(value)
        if isinstance(current, list):
            if isinstance(value, str):  # a matrix given as text (--set key=[[...]])
                try:
                    value = yaml.safe_load(value)
                except yaml.YAMLError:
                    raise TypeError from None
            if not isinstance(value, list):
                raise TypeError
            return value
    except (TypeError, ValueError):
        pass
    else:
        return value
    raise ConfigError(f"config key '{path}' expects a {type(current).__name__} (got {value!r})")


GENERIC_IMU_FIELDS = ("noise_discretization", "gyro_cov", "accel_cov", "gyro_bias_cov",
                      "accel_bias_cov")
"""The IMU densities whose defaults are Faster-LIO's generic values, kept by the generic presets."""


def imu_noise_is_generic(imu_cfg: ImuConfig) -> bool:
    """True when the filter's IMU noise is Faster-LIO's generic values (``ImuConfig``'s
    defaults, which the generic presets keep) rather than an IMU's own: every density and the
    discretization at its default, the white noise not measured. In shafts and stairwells they
    cost 2-3x the ATE or the track (README, Presets)."""
    default = ImuConfig()
    return imu_cfg.noise_source != "measured" and all(
        getattr(imu_cfg, k) == getattr(default, k) for k in GENERIC_IMU_FIELDS)


def available_presets() -> list[str]:
    root = resources.files("adalio") / "presets"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".yaml"))


class _UniqueKeyLoader(yaml.SafeLoader):
    """A safe YAML loader that refuses a key given twice in one mapping (PyYAML keeps the last
    silently: a second ``preprocess:`` section dropped the first one's settings)."""

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise ConfigError(f"'{key}' is given twice in one mapping (line "
                                  f"{key_node.start_mark.line + 1}); YAML keeps only the last: "
                                  "merge the two into one")
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def _read_yaml(text: str, where: str) -> dict[str, Any]:
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    except yaml.YAMLError as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        at = f" (line {line + 1})" if line is not None else ""
        raise ConfigError(f"{where} is not valid YAML{at}: fix the syntax") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must contain a mapping of sections (sensor, map, ...)")
    return data


def preset_dict(name: str) -> dict[str, Any]:
    """The raw override mapping of a shipped preset."""
    names = available_presets()
    if isinstance(name, Path) or (isinstance(name, str) and name.endswith((".yaml", ".yml"))):
        raise ConfigError(f"'{name}' is a file, not a preset name: pass it with --config "
                          f"(Python: load_config(config_file=...)); presets: "
                          f"{', '.join(names)}")
    if not isinstance(name, str):
        raise ConfigError(f"a preset is named by a string, got {type(name).__name__} {name!r}; "
                          f"available: {', '.join(names)}")
    if name not in names:
        close = difflib.get_close_matches(name, names, n=1)
        hint = f"did you mean '{close[0]}'? " if close else ""
        raise ConfigError(f"unknown preset '{name}': {hint}available: {', '.join(names)}")
    text = (resources.files("adalio") / "presets" / f"{name}.yaml").read_text()
    return _read_yaml(text, f"preset {name}")


def set_options(items: list[str] | None) -> dict[str, str]:
    """The command line's ``--set KEY=VALUE`` options as :func:`load_config` overrides (the
    values as given: the config types them); ConfigError for an item without ``=`` or key."""
    out: dict[str, str] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set expects KEY=VALUE (got {item!r}), e.g. --set "
                              "map.map_leaf_m=0.3")
        out[key.strip()] = value.strip()
    return out


def load_config(preset: str | None = None, config_file: str | Path | None = None,
                overrides: dict[str, Any] | None = None) -> Config:
    """Build the effective config: defaults < preset < config file < overrides.

    ``overrides`` uses dotted keys (``{"adaptive.mode": "fixed"}``) or nested mappings.
    A config file may name a preset itself with a top-level ``preset:`` key.
    """
    cfg = Config()
    file_data: dict[str, Any] = {}
    if config_file is not None:
        path = Path(config_file)
        if path.is_dir():
            raise ConfigError(f"config file {path} is a folder: give the YAML file in it (e.g. "
                              f"{path / 'config.yaml'})")
        if not path.is_file():
            raise ConfigError(f"config file {path} does not exist: check the path")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise ConfigError(f"config file {path} is not UTF-8 text (byte {exc.start}): give "
                              "a YAML config such as a run's config.yaml, saved as UTF-8") \
                from None
        file_data = _read_yaml(text, f"config file {path}")
        file_preset = file_data.pop("preset", None)
        if preset is None and file_preset is not None:
            preset = str(file_preset)
    if preset:
        _merge_into(cfg, preset_dict(preset), "")
    if file_data:
        _merge_into(cfg, file_data, "")
    if overrides:
        if not isinstance(overrides, dict):
            raise ConfigError(f"overrides must be a mapping of keys to values, got "
                              f"{type(overrides).__name__}")
        for key, value in overrides.items():  # in order, each on what the ones before set
            if value is None:
                continue
            nested: dict[str, Any] = {}
            parts = str(key).split(".")
            node = nested
            for part in parts[:-1]:
                node = node.setdefault(part, {})
            node[parts[-1]] = value
            _merge_into(cfg, nested, "")
    return cfg.validate()


def config_from_dict(data: dict[str, Any]) -> Config:
    """A validated Config from a nested mapping (e.g. a saved ``config.yaml``)."""
    cfg = Config()
    _merge_into(cfg, dict(data), "")
    return cfg.validate()
