"""The per-scan LiDAR-inertial odometry pipeline (lio-design.md §10, AdaLIO §9).

``Odometry.add_imu`` buffers IMU samples (int64 ns, gyro rad/s, accel m/s² or g);
``Odometry.add_scan`` takes one sweep (LiDAR-frame points in metres, absolute per-point int64 ns)
and runs, in paper order: preprocess → (static init) → propagate + undistort to the scan end →
voxel downsample (general leaf) → degeneracy check / parameter switch → iterated ESKF update →
map insertion, returning the IMU pose in the world frame stamped at the scan end.

Search radius (§9.4): the kNN query returns up to k neighbours within ``filter.knn_max_range_m``; a
correspondence is rejected when fewer than ``filter.min_neighbors`` were found or when the
farthest of the found neighbours lies beyond the active ``search_radius_m`` (FAST-LIO2-style gate
on the k-th neighbour). The plane margin of the active set is the §6.2 validity threshold; a plane
must also be spanned by its neighbours (``filter.plane_min_extent_fraction``) and, optionally,
the query must lie within their span along the plane, not beyond every one of them
(``filter.plane_within_support``): an extrapolated plane's error grows with the distance and does
not average out (a curved wall, the map's leading edge). Residuals sharing
their nearest map point are down-weighted as one measurement (``filter.share_weighting``): a finer scan
leaf than the map cell would otherwise count the same map error several times and make the
filter over-confident along weakly observable directions. Each residual's variance is also
scaled by the plane-fit uncertainty at the query (``filter.plane_uncertainty_weighting``:
1 + 1/k + rho²/(k lambda_mid)), so planes extrapolated far from narrow neighbourhoods weigh less.

Map insertion (deviation from Faster-LIO's §7 rule): every scan, including the first one (Faster-LIO's
INIT_TIME insert-all window is not needed), is offered whole to the iVox map, which keeps at most one point per
``map.map_leaf_m`` cell (``IVox(cell_m=...)``; a finer active scan leaf also refines the cell,
``map.cell_follows_voxel``). Upstream's rule lets cells accumulate clusters
whose plane fits have arbitrary normals; in degenerate scenes those fake constraints hold the
estimate against the IMU (corridor ATE 11 m → 2 cm in the simulator).

Backfill (not in Faster-LIO): the scans read before the initialization (a moving start's
refused fits, motion before a still window) are kept (``imu.backfill_s``) and, once the filter
has tracked ``imu.backfill_after_s``, get their poses from a copy of the filter run backwards in
time (``_backfill``, ``take_backfill``).

AdaLIO hooks (§9, degeneracy.py): the detector sees the general-leaf cloud and a "weak geometry"
flag from the previous scan's localizability (translation eigenvalue ratio below
``adaptive.min_eigen_ratio``, if ``use_localizability_trigger``). In mode ``adaptive+`` a
degenerate scan is refined (leaf halved down to ``min_voxel_size_m`` within ``point_budget``)
while its translation information stays weak, and the update is restricted to the observable pose
directions (``observable_projector``). Stage timers: ``degeneracy`` includes those refinement
searches; ``undistort`` includes the IMU propagation.
"""

from __future__ import annotations

import copy
import dataclasses
import time
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from adalio.config import Config, ImuConfig, imu_noise_is_generic
from adalio.errors import ConfigError, InputError
from adalio.jit import kernel
from adalio.lio import imu, so3
from adalio.lio.associate import Correspondences, associate
from adalio.lio.degeneracy import (
    DegeneracyDetector,
    Localizability,
    consistent_projector,
    localizability,
    observable_projector,
    weak_directions,
)
from adalio.lio.dense_map import DenseMap
from adalio.lio.extrinsic_check import (
    GROSS_MIN_SPAN_S,
    GROSS_SPAN_S,
    SEEN_SHARE,
    GrossRotation,
    RotationEstimate,
    estimate_gross_rotation,
    estimate_rotation,
)
from adalio.lio.extrinsic_sigma import (
    error_second_moment,
    extrinsic_rotation_covariance,
    extrinsic_translation_covariance,
)
from adalio.lio.gyro_scale import GyroScaleEstimate, estimate_gyro_scale
from adalio.lio.ieskf import (
    UpdateResult,
    _reprojection,
    height_direction,
    iterated_update,
    real_information_and_height_blind,
    without_direction,
)
from adalio.lio.ivox import IVox, hash_key3
from adalio.lio.lever_arm import TranslationEstimate, estimate_translation
from adalio.lio.lidar_view import LidarView, lidar_view
from adalio.lio.local_surface import LocalSurface, disagrees
from adalio.lio.map_uncertainty import MapProvenance, deskew_covariance, world_covariance
from adalio.lio.measurement import (
    normal_noise_information,
    normal_noise_matrices,
    normal_noise_sums,
    point_to_plane,
    points_to_world,
    residual_weights,
    robust_row_factors,
)
from adalio.lio.motion_init import MovingInit, RestCheck, handover_covariance, lidar_rest_check
from adalio.lio.moving import MovingPoints, SweepImage
from adalio.lio.plane import fit_planes
from adalio.lio.state import (
    BG,
    DIM,
    P_,
    TH,
    State,
    V,
    anchored_covariance,
    condition_on_rest,
    initial_covariance,
    joseph_update,
    pose_covariance_world,
    rest_velocity_covariance,
    rest_velocity_update,
    sigmas_from_world_covariance,
)
from adalio.lio.stray import CONTINUED, STRAY, ring_id_span, rings_testable, stray_codes
from adalio.lio.time_offset import (
    END_MIN_SPAN_S,
    MAX_SPAN_S,
    MIN_SPAN_S,
    TimeOffsetCheck,
    TimeOffsetEstimate,
    estimate_offset,
)
from adalio.lio.voxel import voxel_downsample_with_index
from adalio.types import Estimate, InitReport, ScanStats, UnsettledCheck

ANCHOR_VARIANCE = 1e-12
"""The backfill's hold to the anchor (:meth:`Odometry._hold_to_anchor`): the variance, m² and
rad², of a position and yaw the world's definition makes exact; not zero only so the update's
innovation matrix stays invertible."""
STAGES = ("preprocess", "undistort", "moving", "downsample", "degeneracy", "update", "map")
MAX_SCAN_SPAN_NS = 1_000_000_000
"""Per-point times of one sweep spanning more than this are rejected as malformed (units?)."""
MIN_POINTS_FOR_UPDATE = 5
"""Fewer downsampled points than this: the scan is not used for an update (§6.1)."""
API_UNITS = (" (the bag Sequencer converts by it; samples handed to Odometry.add_imu must be "
             "in rad/s and m/s^2 already)")
"""What the sensor unit messages add for a caller of the Python API: Odometry applies none of
sensor.gyro_unit, accel_unit, imu_time_offset_s and the sensitivities (the Sequencer does)."""
GYRO_RANGE_RAD_S = 35.0
"""2000 deg/s, the widest range of common MEMS gyros: a larger reading is not in rad/s."""
DEG_PER_RAD = 57.29577951308232
UNITS_CHECK_ANGLE_RAD = 0.05
"""LiDAR-registered rotation, sqrt of the sum of squared increments between scans, needed before
the gyro's unit is judged against it (registration noise, ~0.002 rad per pair, adds little)."""
UNITS_CHECK_S = 10.0
"""After a still start, the unit check registers scans LiDAR-only for at most this long."""
TIME_OFFSET_JUDGE_NS = 2_000_000_000
"""The IMU time offset check estimates every 2 s of updates (20-45 ms each time)."""
TRANSLATION_JUDGE_NS = 10_000_000_000
"""The lever arm check estimates every 10 s of updates (45-60 ms at 60 s of data; every 2 s
it cost the 64 s corridor's run 1.17x its wall time), and at the end of its span."""
LIDAR_GAP_PERIODS = 1.5
"""An interval between scans longer than this many nominal periods is a LiDAR gap: at least
one sweep is missing (jitter of half a period passes)."""
TRACK_NOISE_WINDOW_S = 1.0
"""imu.track_noise_ratio measures the IMU's white noise after each scan over its samples of the
last second: 400 at 400 Hz, whose second differences' median leaves the variance within about
10 % (a raise needs 4 times the variance), and a robot that starts to shake is caught within a
second."""
SCAN_PERIOD_WINDOW = 20
"""The nominal scan period is the median of this many latest intervals without a gap."""


@kernel()
def _range_gate_rows(points, blind_m, max_range_m, point_filter_num):
    """§6.1 steps 1-2: the rows of the finite points whose range is in ``[blind_m,
    max_range_m]`` (in order), which of them the decimation keeps (every
    ``point_filter_num``-th message index), and the number of finite points."""
    n = points.shape[0]
    rows = np.empty(n, np.int64)
    decimated = np.empty(n, np.bool_)
    n_finite = 0
    m = 0
    lo2, hi2 = blind_m * blind_m, max_range_m * max_range_m
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        n_finite += 1
        r2 = x * x + y * y + z * z
        if lo2 <= r2 <= hi2:
            rows[m] = i
            decimated[m] = i % point_filter_num == 0
            m += 1
    return rows[:m], decimated[:m], n_finite


@kernel()
def _group_ids(points: np.ndarray) -> tuple[np.ndarray, int]:
    """Group index of each row (rows holding bit-for-bit the same point share one, numbered in
    order of first appearance) and the number of groups: an open-addressing table over the
    rows' float bits, sized to at most half full."""
    n = points.shape[0]
    bits = points.view(np.int64)
    size = 2
    while size < 2 * n:
        size *= 2
    mask = size - 1
    first = np.full(size, -1, np.int64)
    gid = np.empty(n, np.int64)
    n_groups = 0
    for i in range(n):
        a, b, c = bits[i, 0], bits[i, 1], bits[i, 2]
        slot = hash_key3(a, b, c, mask)
        while True:
            j = first[slot]
            if j < 0:
                first[slot] = i
                gid[i] = n_groups
                n_groups += 1
                break
            if bits[j, 0] == a and bits[j, 1] == b and bits[j, 2] == c:
                gid[i] = gid[j]
                break
            slot = (slot + 1) & mask
    return gid, n_groups


def robust_kernel_name(cfg: Config) -> str:
    """``filter.robust_kernel`` resolved: ``auto`` is ``huber``, except in mode ``adaptive+``,
    whose held directions and probes diverged with it in the stairwell (README, Session 31).
    The backfill's reversed pass of an ``adaptive`` run is given ``none`` outright
    (:meth:`Odometry._reversed_copy`)."""
    name = cfg.filter.robust_kernel
    if name != "auto":
        return name
    return "none" if cfg.adaptive.mode == "adaptive+" else "huber"


class _Association:
    """Point-to-plane correspondences of one downsampled scan against the map (§6.2-6.3).

    Used as the ``measure`` callback of :func:`iterated_update`; keeps the neighbours of the last
    search for the map-insertion rule and the raw H of the last evaluation.
    """

    def __init__(self, points_lidar: np.ndarray, ivox: IVox, cfg: Config, radius_m: float,
                 margin_m: float, cell_m: float,
                 local: tuple[np.ndarray, np.ndarray] | None = None,
                 prior_pose_cov: np.ndarray | None = None, after_gap: bool = False) -> None:
        self.points_lidar = points_lidar
        self.prior_pose_cov = prior_pose_cov
        """(6,6) the predicted discounted pose covariance [δp, δθ] (which does not count the
        information noisy plane normals fake): with it (the filter's update), the rows take
        ``filter.robust_kernel``'s weights (:func:`robust_row_factors`) and, on the scan after
        a LiDAR or IMU gap (``after_gap``), the gate admits the residuals it allows
        (``filter.gate_sigmas``); None: neither."""
        gate = prior_pose_cov is not None and after_gap
        self._gate_cov = np.ascontiguousarray(prior_pose_cov) if gate else np.zeros((6, 6))
        self._gate_sigmas = float(cfg.filter.gate_sigmas) if gate else 0.0
        self.kernel = robust_kernel_name(cfg)
        self.local = local
        """(normals (n,3) LiDAR frame, judged (n,)) of the scan's own surface at each point
        (filter.local_surface_check), or None."""
        self.n_disagree = 0
        self.ivox = ivox
        self.cfg = cfg.filter
        self.min_extent_m = cfg.filter.plane_min_extent_fraction * cell_m
        self.radius_m = radius_m
        self.margin_m = margin_m
        n = points_lidar.shape[0]
        self.nearest = np.full((n, 3), np.nan)
        self.counts = np.zeros(n, np.int64)
        self.normals = np.zeros((n, 3))
        self.d = np.zeros(n)
        self.selected = np.zeros(n, np.bool_)
        self.H = np.zeros((0, 12))
        self._searched_at: tuple[np.ndarray, ...] | None = None
        # the last search (its queries and neighbours); the map does not change meanwhile
        self._last: Correspondences | None = None
        self.n_searches = 0
        self._noise: tuple[np.ndarray, np.ndarray] | None = None
        self._noise_of: Correspondences | None = None  # the search _noise was computed for

    def _same_pose(self, x: State) -> bool:
        last = self._searched_at
        return last is not None and all(np.array_equal(a, b) for a, b in
                                        zip(last, (x.R, x.p, x.R_LI, x.t_LI)))

    def _small_shift(self, p_world: np.ndarray) -> bool:
        """No scan point moved more than ``filter.research_min_shift_m`` since the last search."""
        last = None if self._last is None else self._last.queries
        tol = self.cfg.research_min_shift_m
        if last is None or not tol > 0:
            return False
        return bool(np.max(np.abs(p_world - last)) <= tol)

    def measure(self, x: State, research: bool) -> tuple[np.ndarray, np.ndarray]:
        f = self.cfg
        p_world = None
        if research and not self._same_pose(x):
            p_world = points_to_world(self.points_lidar, x.R, x.p, x.R_LI, x.t_LI)
            if self._small_shift(p_world):
                p_world = None
        if research and p_world is None:
            self.selected = self._valid_after_search.copy()
        elif research:
            self.n_searches += 1
            c = associate(self.ivox, p_world, f.knn_k, f.knn_max_range_m, f.min_neighbors,
                          self.radius_m, self.margin_m, f.plane_fit, self.min_extent_m,
                          f.plane_within_support, keep_neighbours=True, warm_from=self._last,
                          ring_origin=x.R @ x.t_LI + x.p, ring_axis=x.R @ x.R_LI[:, 2],
                          ring_max_deg=f.one_ring_max_deg)
            self._last = c
            self.normals, self.d, self.counts = c.normals, c.d, c.counts
            self.mu, self.lam_mid, self.nearest = c.mu, c.lam_mid, c.nearest
            self.selected = c.valid
            if self.local is not None:
                bad = disagrees(c.normals, self.local[0], self.local[1], x.R @ x.R_LI,
                                f.local_surface_max_angle_deg)
                self.n_disagree = int(np.count_nonzero(bad & c.valid))
                self.selected = c.valid & ~bad
            self.group_id, self.n_groups = _group_ids(c.nearest)
            self._valid_after_search = self.selected.copy()
            self._searched_at = (x.R.copy(), x.p.copy(), x.R_LI.copy(), x.t_LI.copy())
        H, r, accepted = point_to_plane(self.points_lidar, x.R, x.p, x.R_LI, x.t_LI, self.normals,
                                        self.d, self.selected, f.estimate_extrinsic,
                                        self._gate_cov, self._gate_sigmas)
        self.selected = accepted
        if (f.plane_uncertainty_weighting or f.share_weighting) and H.shape[0]:
            w = residual_weights(self.points_lidar, accepted, x.R, x.p, x.R_LI, x.t_LI,
                                 self.normals, self.mu, self.lam_mid, self.counts,
                                 self.group_id, self.n_groups, f.plane_uncertainty_weighting,
                                 f.share_weighting)
            H *= w[:, None]
            r *= w
        if self.kernel != "none" and self.prior_pose_cov is not None and H.shape[0]:
            c = robust_row_factors(r, H[:, :6], self.prior_pose_cov, self.kernel, f.robust_scale)
            H *= c[:, None]
            r *= c
        self.H = H
        return H.copy(), r

    @property
    def row_weights(self) -> np.ndarray:
        """(m,) the weight of each row of the last evaluation: ``|H[:, :3]|``, since the position
        columns are the unit normal times the row's weight (:func:`residual_weights`)."""
        return np.sqrt(np.sum(self.H[:, :3] ** 2, axis=1))

    def noise_terms(self, x: State) -> tuple[np.ndarray, np.ndarray]:
        """``measurement.normal_noise_terms`` of the last evaluation's rows at ``x``, in ``HᵀH``'s
        units (each row's point noise from its neighbours' scatter), for
        ``filter.errors_in_variables``."""
        if self.H.shape[0] == 0:
            return np.zeros((6, 6)), np.zeros(6)
        if self._noise_of is not self._last:  # the normals' covariances, once per search
            self._noise = normal_noise_matrices(self._valid_after_search, self.normals,
                                                self._last.neighbours, self.counts,
                                                self.cfg.laser_point_cov, True)
            self._noise_of = self._last
        return normal_noise_sums(self.points_lidar, self.selected, x.R, x.p, x.R_LI, x.t_LI,
                                 self.mu, *self._noise, self.row_weights)

    @property
    def neighbours(self) -> np.ndarray:
        """(n, k, 3) the k nearest map points of every scan point at the last search."""
        return self._last.neighbours

    def points_body(self, x: State) -> np.ndarray:
        """IMU-frame coordinates of the accepted points (rows of ``H``)."""
        return self.points_lidar[self.selected] @ x.R_LI.T + x.t_LI


@dataclass
class _ImuBuffer:
    t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def last(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
             span_ns: int) -> _ImuBuffer:
        """These samples and the given ones after them, from the last one before the newest
        minus ``span_ns`` on (so that they span at least ``span_ns`` once there are enough)."""
        t = np.concatenate([self.t_ns, t_ns])
        lo = max(int(np.searchsorted(t, t[-1] - span_ns)) - 1, 0)
        return _ImuBuffer(t[lo:], np.vstack([self.gyro, gyro])[lo:],
                          np.vstack([self.accel, accel])[lo:])


def _timer(stage_ms: dict[str, float], name: str, t0: float) -> float:
    now = time.perf_counter()
    stage_ms[name] = stage_ms.get(name, 0.0) + (now - t0) * 1e3
    return now


def restoring_ratios(assoc: _Association, x: State, dirs: np.ndarray) -> np.ndarray:
    """For each pose displacement d (error order [dp, dtheta]): re-associate at x ⊞ ±d and
    compare the restoring gradient with the information H^T H claims at x,
    rho = d^T (g(+d) - g(-d)) / (2 d^T H^T H d), g = H^T r (degeneracy.py §4); 0 where H^T H
    claims nothing along d. ``assoc`` must hold its measurement at ``x``."""
    H0 = assoc.H[:, :6]
    rho = np.zeros(len(dirs))
    for k, d in enumerate(dirs):
        claimed = float(np.sum((H0 @ d) ** 2))
        if not claimed > 0:
            continue
        g = []
        for sgn in (1.0, -1.0):
            delta = np.zeros(DIM)
            delta[:6] = sgn * d
            H, r = assoc.measure(x.boxplus(delta), True)
            g.append(H[:, :6].T @ r)
        rho[k] = float(d @ (g[0] - g[1])) / (2.0 * claimed)
    return rho


def _rotation_data(motion: tuple | None) -> tuple | None:
    """The time offset's and the rotation's data (``TimeOffsetCheck.samples``) from the
    translation's (``TimeOffsetCheck.motion_samples``)."""
    return None if motion is None else (motion[0], motion[1], motion[3], motion[4])


def _information_update(P: np.ndarray, J: np.ndarray) -> np.ndarray:
    """``P`` after information ``J`` (6x6) on its pose block: ``(P⁻¹ + EᵀJE)⁻¹`` with E the pose
    block, in the form that needs no inverse of ``P``; symmetrised."""
    PE = P[:, :6]
    P = P - PE @ J @ np.linalg.solve(np.eye(6) + P[:6, :6] @ J, PE.T)
    return 0.5 * (P + P.T)


def _shared(cfg: Config) -> dict:
    """A deepcopy memo that keeps ``cfg`` and every dataclass inside it shared."""
    memo: dict = {}
    todo: list = [cfg]
    while todo:
        obj = todo.pop()
        if id(obj) in memo:
            continue
        memo[id(obj)] = obj
        todo.extend(v for f in dataclasses.fields(obj)
                    if dataclasses.is_dataclass(v := getattr(obj, f.name)))
    return memo


@dataclass
class _RestOnTrial:
    """A static start at the recording's start, before the LiDAR has checked its rest
    (``imu.rest_lidar_check``): the filter runs on, but its estimates are held back until
    ``registrar`` (the gyro unit check's LiDAR-only registrations) spans ``imu.init_window_s``;
    if they refute the rest, the Odometry goes back to ``snapshot`` and the scans since run
    again as a moving start."""

    snapshot: Odometry
    """This Odometry just before the static start (held scans shared, not copied)."""
    registrar: MovingInit
    t_init_ns: int
    inputs: list[list] = field(default_factory=list)
    """Per ``add_scan`` call since (the static start's own first): [points, t_ns, ring, the IMU
    chunks it merged, whether it raised InputError]."""
    estimates: list[Estimate] = field(default_factory=list)


class Odometry:
    """Faster-LIO-style iterated-ESKF LiDAR-inertial odometry with AdaLIO switching.

    Contract (notes/contracts.md): ``add_imu``, ``add_scan``, ``map_points``, ``initialized``,
    ``stage_ms_total``. World = IMU frame at init (or gravity-aligned, ``imu.gravity_align_world``).
    """

    def __init__(self, config: Config) -> None:
        if not isinstance(config, Config):
            raise ConfigError(f"Odometry takes a Config (adalio.load_config(...)), got "
                              f"{type(config).__name__}")
        self.cfg = config.validate()  # the checks load_config makes, for a Config edited since
        T = config.T_imu_lidar()
        self._R_LI = T[:3, :3].copy()
        self._t_LI = T[:3, 3].copy()
        self.initialized = False
        self._stages = tuple(k for k in STAGES if k != "moving" or config.map.remove_moving)
        """The stages this run times (STAGES, without 'moving' when map.remove_moving is off)."""
        self.stage_ms_total: dict[str, float] = dict.fromkeys(self._stages, 0.0)
        self.n_scans = 0
        self.n_skipped_scans = 0
        """Scans ending at or before the previous scan end (out of order): not processed."""
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._buf = _ImuBuffer(np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 3)))
        self._last_imu_t_ns: int | None = None
        self._rest_imu = _ImuBuffer(np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 3)))
        """The IMU samples (accelerometer scaled) of the last ``imu.init_window_s`` before the
        state's time, for the zero-velocity update's stillness test."""
        self.n_rest_updates = 0
        """Scans whose velocity was held at zero (imu.zero_velocity_update)."""
        self._rest_gate = imu.chi2_quantile(1.0 - config.imu.still_false_alarm, 3)
        """The zero-velocity update's chi-square gate (3 dof at imu.still_false_alarm)."""
        self._ivox = IVox.from_config(config.map)
        self._movers = MovingPoints.from_config(config.map) if config.map.remove_moving else None
        """Where the sweeps saw through, to keep moving things out (map.remove_moving)."""
        dense_m = config.output.dense_map_voxel_m
        self._dense = DenseMap(dense_m) if dense_m > 0 else None
        """Every still point of every scan at its updated pose (output.dense_map_voxel_m)."""
        self._detector = DegeneracyDetector(config.adaptive)
        self._q_diag = imu.process_noise(config.imu)
        self._noise_used = config.imu
        """The IMU config whose white-noise densities the filter uses (``_q_diag``): the
        configured one, the start's measurement (imu.noise_source), or what the run measured
        since (imu.track_noise_ratio)."""
        self._noise_start: ImuConfig | None = None
        """``_noise_used`` at the initialization, what a raise is told against."""
        self._track_imu = _ImuBuffer(np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 3)))
        """The IMU samples of the last TRACK_NOISE_WINDOW_S (imu.track_noise_ratio)."""
        self._noise_shown = (False, False)
        """Whether the gyro / the accelerometer has shown itself noisier than the start by
        imu.track_noise_ratio (further raises then follow the chi-square rule)."""
        self.noise_raises: list[tuple[int, float, float]] = []
        """(time ns, gyro density / the start's, accelerometer density / the start's) of each
        raise of the filter's white-noise densities by imu.track_noise_ratio."""
        self._weak_geometry = False
        self._state = State(R_LI=self._R_LI.copy(), t_LI=self._t_LI.copy())
        self._P = initial_covariance(config.filter.estimate_extrinsic)
        self._P_report: np.ndarray | None = None
        """The discounted covariance: the filter's, propagated alike, but updated only with the
        information the scene holds (:meth:`_update_report_covariance`); behind the reported
        sigmas with filter.sigmas_discount_normal_noise, and behind the robust kernel's spread
        whatever that flag says (so the flag never changes the trajectory); None until the
        anchor, or when neither needs it."""
        self._P_blind: np.ndarray | None = None
        """With filter.sigmas_height_blind: the covariance behind the reported sigmas, the
        discounted one's twin that takes no height from a height-blind scan
        (:meth:`_update_report_covariance`); None until the anchor, or without the flag."""
        self._t_state_ns = 0
        self._prev_sample: tuple[int, np.ndarray, np.ndarray] | None = None
        self._accel_scale = 1.0
        self._t_first_map_ns: int | None = None
        self._anchor_state: State | None = None
        """The state at ``_t_first_map_ns``: the pose that anchors the map and defines the world
        (the backfill's reversed pass is held to it, :meth:`_hold_to_anchor`)."""
        self._anchor_v_cov = np.zeros((3, 3))
        """The filter's velocity covariance at the anchor (:meth:`_hold_to_anchor`)."""
        self._rested_ns: list[tuple[int, int]] = []
        """While a backfill is pending: the spans ``[a, b)`` (ns) over which the sensor rested as
        this filter established it, the still window of a static initialization and each
        zero-velocity update's window (:meth:`_rest_update`); the backfill's reversed pass takes
        rest there without the velocity gate (``_rested_mirrored_ns``)."""
        self._rested_mirrored_ns: list[tuple[int, int]] = []
        """The backfill's reversed pass: the forward filter's rested spans in mirrored time,
        ``(mirror - b, mirror - a]``: a scan whose end (its forward start) lies in one is taken
        at rest wherever its IMU is still, whatever its own velocity says."""
        self._finest_cell_m = config.map.map_leaf_m
        """Finest cell any scan has used for insertion: the plane-extent test scales with it,
        since a map densified by degenerate scans holds neighbours that close everywhere."""
        self._last_cell_m = config.map.map_leaf_m
        """Map cell of the last scan inserted (a surface the map holds has a point within about
        one cell of any of its points: map.moving_body_m's test)."""
        self.init_report: InitReport | None = None
        """How the filter initialized (None until it has)."""
        self.lidar_view: LidarView | None = None
        """How the LiDAR's view lies against gravity, from the first map's scan (None until the
        filter initialized): does it see the horizontal ahead of its lean or behind it
        (:mod:`adalio.lio.lidar_view`)."""
        self._t_first_scan_ns: int | None = None
        self._scans_without_pose = 0
        """Scans handed to the initialization that left it uninitialized (no pose)."""
        self._span_s = 0.0
        """Time span (s) of the latest scan's points (filter.sigmas_deskew_noise)."""
        self._q_deskew: float | None = None
        """Gyro white-noise density² (rad²/s) the start measured (filter.sigmas_deskew_noise)."""
        self._refused_fits = 0
        self._closest_still: imu.StillnessTest | None = None
        self._moving: MovingInit | None = None
        self._gap_s = np.inf
        """IMU gap threshold (s): imu.gap_periods nominal periods, set at initialization."""
        self._imu_period_s = np.inf
        """The IMU's nominal sample period (s), measured at initialization."""
        self._q_gap = np.zeros(12)
        self._last_gap: tuple[int, float] | None = None
        """(start ns, length s) of the IMU gap bridged in the latest scan."""
        self._warned_gap_ns: int | None = None
        self._scan_intervals_ns: list[int] = []
        """The latest intervals between tracked scans' ends that were not LiDAR gaps."""
        self.lidar_gaps: list[tuple[int, float, float]] = []
        """(end of the scan before the gap ns, missing time s, the largest position standard
        deviation of the reported sigmas (scans.csv sigma_*) predicted at the scan after it, m)
        of every LiDAR gap (:meth:`_lidar_gap`)."""
        self._units_check: MovingInit | None = None
        """After a still start: LiDAR-only registrations, made without the gyro, to compare the
        gyro's rotation with (its unit; the gross rotation check)."""
        self._units_open = False
        """The gyro unit check is open (``_units_check`` registers for it)."""
        self._gross_open = False
        """The gross rotation check is open (``_units_check`` registers for it too)."""
        self._gross_t0_ns = 0
        """Where the gross rotation check started (the still start's scan, int64 ns)."""
        self.check_gross_rotation = True
        """False: no gross rotation check (``run_bag``'s passes, which read the fine checks'
        estimates with an extrinsic the gross check already passed)."""
        self.gross_rotation: GrossRotation | None = None
        """A LiDAR-IMU rotation error too large for the fine check, found by a registration
        without the gyro over the first seconds after a still start
        (:func:`adalio.lio.extrinsic_check.estimate_gross_rotation`;
        sensor.extrinsic_rotation_check); ``run_bag`` restarts with it, an own loop is warned.
        None: none found, or not checked."""
        self.gross_rotation_checked: GrossRotation | None = None
        """The gross check's last estimate when it closed finding no gross error (None: it
        could not estimate, did not run, or found one)."""
        self._on_trial: _RestOnTrial | None = None
        """A static start whose rest the LiDAR has yet to check (imu.rest_lidar_check)."""
        self._input: list | None = None
        """The ``add_scan`` call in progress: [points, t_ns, ring, IMU chunks merged]."""
        self._refuted_until_ns: int | None = None
        """Still windows of scans starting before this are refused: the LiDAR saw motion."""
        self.rest_refuted: RestCheck | None = None
        """The LiDAR check that last refused a still window (imu.rest_lidar_check): the IMU
        rested by its test while the scene moved (a constant velocity or rotation rate)."""
        sensor = config.sensor
        self._offset_check: TimeOffsetCheck | None = (
            TimeOffsetCheck() if (sensor.imu_time_offset_check or sensor.extrinsic_rotation_check
                                  or sensor.extrinsic_translation_check
                                  or sensor.gyro_scale_check) else None)
        """The gyro against the updates' LiDAR-only rotations, until the checks conclude
        (sensor.imu_time_offset_check, :mod:`adalio.lio.time_offset`;
        sensor.extrinsic_rotation_check, :mod:`adalio.lio.extrinsic_check`;
        sensor.extrinsic_translation_check, :mod:`adalio.lio.lever_arm`)."""
        self._offset_open = sensor.imu_time_offset_check
        self._rotation_open = sensor.extrinsic_rotation_check
        self._translation_open = sensor.extrinsic_translation_check
        self._scale_open = sensor.gyro_scale_check
        self._translation_judged_ns = 0
        self._offset_judged_ns = 0
        self.warn_time_offset = True
        """Warn when the check concludes on a significant offset (``run_bag`` acts instead)."""
        self.conclude_time_offset = True
        """False: the check only collects (``run_bag``'s passes read its estimate over the
        scans they run, :meth:`time_offset_estimate`)."""
        self.time_offset: TimeOffsetEstimate | None = None
        """The IMU time offset the check concluded on, left after sensor.imu_time_offset_s
        (None: not concluded, or the check is off); warned about when significant."""
        self.warn_extrinsic_rotation = True
        """Warn when the rotation check concludes on a significant rotation (``run_bag`` acts
        instead)."""
        self.extrinsic_rotation: RotationEstimate | None = None
        """The LiDAR-IMU rotation the check concluded on, left after sensor.T_imu_lidar's (None:
        not concluded, or the check is off); warned about when significant."""
        self.time_offset_unsettled: UnsettledCheck | None = None
        """The IMU time offset check closed without a conclusion (at ``MAX_SPAN_S``, or at the
        end of the data): sensor.imu_time_offset_s was used unchecked (None: it concluded, is
        still open, or is off)."""
        self.extrinsic_rotation_unsettled: UnsettledCheck | None = None
        """The same for the LiDAR-IMU rotation check: sensor.T_imu_lidar's rotation was used
        unchecked."""
        self.extrinsic_translation: TranslationEstimate | None = None
        """The correction of sensor.T_imu_lidar's translation the check concluded on (None: not
        concluded, or the check is off); never warned about (a hint: README, "LiDAR-IMU lever
        arm")."""
        self.extrinsic_translation_unsettled: UnsettledCheck | None = None
        """The translation check closed without a conclusion."""
        self.gyro_scale: GyroScaleEstimate | None = None
        """The gyro's scale error (the symmetric part of its sensitivity error left after
        sensor.gyro_sensitivity) the gyro scale check concluded on (None: not concluded, or the
        check is off; :mod:`adalio.lio.gyro_scale`); ``run_bag`` acts on a significant one."""
        self.gyro_scale_unsettled: UnsettledCheck | None = None
        """The gyro scale check closed without a conclusion."""
        self._rotation_M = error_second_moment(np.radians(sensor.extrinsic_rotation_sigma_deg))
        """The second moment of the extrinsic rotation's error (rad², IMU frame) behind its
        share of the reported sigmas (:meth:`_extrinsic_covariance`): the configured prior, then
        narrowed (or widened) by each estimate of the rotation check, concluded or not."""
        self._gyro_axes_M = error_second_moment(np.radians(sensor.gyro_axes_sigma_deg))
        """The gyro's axes against the IMU's frame (``sensor.gyro_axes_sigma_deg``): a turn of
        the trajectory's frame the rotation check cannot see, added to ``_rotation_M``."""
        self._translation_M = error_second_moment(sensor.extrinsic_translation_sigma_m)
        """The same for the lever arm (m²) and the lever arm check's estimates."""
        self._provenance = MapProvenance(config.filter.map_provenance_cell_m)
        self._W_map = np.zeros((6, 6))
        """World covariance the latest scan inherited from the map (filter.map_uncertainty)."""
        self._held_scans: list[tuple[np.ndarray, np.ndarray, tuple[int, int, int]]] = []
        """Preprocessed scans (LiDAR points, int64 ns, and the ``ScanStats`` counts of the
        points read: n_raw, n_stray, n_stray_dropped) read before the initialization, kept for
        the backfill (imu.backfill_s)."""
        self._held_imu: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._backfilled: list[Estimate] = []
        self._backfill_map = np.zeros((0, 3))
        """The backfill's map (world), part of ``map_points`` but not of the filter's map:
        the points the reversed pass's map gained from the held scans (:meth:`_map_gained`)."""
        self._backfill_returns = np.zeros(0, np.int64)
        """Of each backfill map point, how many of the scans' points reached its cell in the
        reversed pass's map (as ``IVox.points_with_returns``; for a point still waiting to
        enter that map, 1, as ``map_cloud`` counts the forward run's)."""
        self._backfill_on_plane = np.zeros(0, np.bool_)
        """Each backfill map point lies on a plane of the reversed pass's map
        (:meth:`_on_map_plane`)."""
        self._warned_no_ring: set[str] = set()
        self._ring_is_line = False
        """``add_scan`` was given Livox lines (``line``), not rings: only the stray test reads
        them."""
        self.local_surface_rows = [0, 0]
        """filter.local_surface_check: [rows dropped, rows matched or dropped] over the run."""

    # ------------------------------------------------------------------ public API
    @property
    def state(self) -> State:
        """A copy of the current filter state (world frame)."""
        return self._state.copy()

    @property
    def covariance(self) -> np.ndarray:
        return self._P.copy()

    def add_imu(self, t_ns, gyro_rad_s, accel_m_s2) -> None:
        """Buffer IMU samples: scalar ``t_ns`` with (3,) vectors or (N,) int64 with (N,3)."""
        t = np.atleast_1d(np.asarray(t_ns))

        def rows(v: object) -> np.ndarray | None:  # (N, 3), or (3,) for one sample; not (3, N)
            a = np.asarray(v, dtype=np.float64)
            return a.reshape(1, 3) if a.shape == (3,) else a if a.ndim == 2 and \
                a.shape[1] == 3 else None

        gyro, acc = rows(gyro_rad_s), rows(accel_m_s2)
        if t.ndim != 1 or not np.issubdtype(t.dtype, np.integer) or t.dtype.itemsize < 8:
            raise InputError(f"add_imu: t_ns must be int64 nanoseconds, got dtype {t.dtype} "
                             f"shape {t.shape} (a narrower integer cannot hold them)")
        if gyro is None or acc is None or gyro.shape[0] != t.size or acc.shape[0] != t.size:
            raise InputError(f"add_imu: expected gyro/accel of shape ({t.size}, 3), got "
                             f"{np.shape(gyro_rad_s)} and {np.shape(accel_m_s2)}")
        if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(acc))):
            raise InputError("add_imu: gyro/accel contain NaN or inf: drop those samples")
        if gyro.size and np.abs(gyro).max() > GYRO_RANGE_RAD_S:
            k = int(np.argmax(np.abs(gyro).max(axis=1)))
            raise InputError(f"the gyro reads {np.abs(gyro[k]).max():.0f} at t = "
                             f"{int(t[k]) * 1e-9:.3f} s, beyond any gyro's range in rad/s "
                             f"({GYRO_RANGE_RAD_S:g}): it reports deg/s; set sensor.gyro_unit: "
                             f"deg_s{API_UNITS}")
        t = t.astype(np.int64)
        if t.size == 0:
            return
        if np.any(np.diff(t) < 0) or (self._last_imu_t_ns is not None
                                       and t[0] < self._last_imu_t_ns):
            raise InputError(f"add_imu: IMU time goes backwards at t_ns={int(t.min())}: "
                             "samples must be added in time order")
        self._last_imu_t_ns = int(t[-1])
        self._pending.append((t, gyro.copy(), acc.copy()))
        if self._offset_check is not None:
            self._offset_check.add_imu(t, gyro, acc)

    @property
    def moving_points(self) -> tuple[int, int]:
        """map.remove_moving: (sweep points kept out as moving, points seen through) so far, by
        the forward filter (the backfill's reverse pass keeps its own; the backfilled scans'
        figures are in their ``stats.n_moving``, ``stats.n_seen_through``)."""
        m = self._movers
        return (0, 0) if m is None else (m.dropped, m.removed)

    def map_points(self, min_returns: int = 1) -> np.ndarray:
        """All map points (M,3) float64, world frame (the backfill's included; with
        map.remove_moving, those still waiting to enter it too); with ``min_returns`` > 1 only
        those of :meth:`map_cloud`."""
        return self.map_cloud(min_returns)[0]

    def map_cloud(self, min_returns: int = 1) -> tuple[np.ndarray, int]:
        """(map points (M,3) float64, world frame; how many were left out).

        With ``min_returns`` > 1 (``output.map_min_returns``), a point whose map cell
        (``map.map_leaf_m``) fewer than ``min_returns`` of the scans' downsampled points reached
        (:meth:`IVox.points_with_returns`) is kept only where it lies on a plane of the map
        (:meth:`_on_map_plane`): a stray return (dust, a ghost) is seen once and lies in free
        space, and a floor that a ring's circle sweeps over, cell after cell, is also seen once
        per cell, but as a plane. A point still waiting to enter the map (map.remove_moving)
        counts as reached once: it never entered the map (session 94: at the end of a dusty
        corridor's backfill all 50 lay off the scene; of the forward runs' 20 on two walks,
        11). The backfill's points
        (:meth:`_map_gained`) are judged by the same rule on the reversed pass's map."""
        pts, returns = self._ivox.points_with_returns(self._ivox.cell_m)
        waiting = self._waiting_points()
        judge = min_returns > 1 and self._ivox.cell_m > 0.0
        left_out = 0
        if judge:
            few = np.flatnonzero(returns < min_returns)
            few = few[~self._on_map_plane(pts[few])]
            keep = np.ones(pts.shape[0], np.bool_)
            keep[few] = False
            on_plane = self._on_map_plane(waiting, in_map=False)
            left_out = int(few.size + on_plane.size - np.count_nonzero(on_plane))
            pts, waiting = pts[keep], waiting[on_plane]
        pts = np.vstack([pts, waiting])
        if self._backfill_map.shape[0]:
            held = self._backfill_map
            if judge:
                keep = (self._backfill_returns >= min_returns) | self._backfill_on_plane
                left_out += int(keep.size - np.count_nonzero(keep))
                held = held[keep]
            pts = np.vstack([held, pts])
        return pts, left_out

    def _waiting_points(self) -> np.ndarray:
        """(W,3) the points still waiting to enter the map (map.remove_moving; none without)."""
        waiting = [] if self._movers is None else [h for h, _ in self._movers.waiting()]
        return np.vstack([np.zeros((0, 3)), *waiting])

    def _map_gained(self, before: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The reversed pass's map points that ``before`` (its map's points when it reached
        the held scans, having re-registered those since the initialization) lacks, with
        those still waiting to enter its map (map.remove_moving): (points (B,3) world, the
        returns of each point's cell (1 for a waiting one, as :meth:`map_cloud` counts it),
        each on a plane of this map), as ``_backfill_map``, ``_backfill_returns`` and
        ``_backfill_on_plane``. These are the held scans' points as the reversed pass's map
        took them (one per cell, moving things kept out) with what its own count and plane
        test say of them, so that the map written out judges them as it judges the forward
        run's (:meth:`map_cloud`). Before session 94 the backfill's map was every held scan's
        downsampled points, none left out: a moving start that waited 30 s through dust on 5
        % of the returns wrote a map 19 % off the scene, where the still start's was 7 %."""
        pts, returns = self._ivox.points_with_returns(self._ivox.cell_m)
        if pts.shape[0]:
            row = np.dtype((np.void, 3 * pts.dtype.itemsize))
            gained = ~np.isin(np.ascontiguousarray(pts).view(row).ravel(),
                              np.ascontiguousarray(before, dtype=pts.dtype).view(row).ravel())
            pts, returns = pts[gained], returns[gained]
        waiting = self._waiting_points()
        try:
            on_plane = np.concatenate([self._on_map_plane(pts),
                                       self._on_map_plane(waiting, in_map=False)])
        except Exception:  # noqa: BLE001  (the map written out, not the run: keep them all)
            on_plane = np.ones(pts.shape[0] + waiting.shape[0], np.bool_)
        returns = np.concatenate([returns, np.ones(waiting.shape[0], np.int64)])
        return np.vstack([pts, waiting]), returns, on_plane

    def dense_map_cloud(self, map_points: np.ndarray) -> tuple[np.ndarray, int]:
        """(dense map points (D,3) float64, world frame; how many were left out), with
        ``output.dense_map_voxel_m`` (:mod:`adalio.lio.dense_map`; none without it).

        A point is kept where ``map_points`` (:meth:`map_cloud`'s, the map written out) holds a
        point within ``map.map_leaf_m``: the filter's map has meanwhile lost what later sweeps
        saw through (people walking by) and left out the cells of stray returns, and the dense
        map loses the points there with them. A surface the sweeps registered fills the map's
        cells, so little of it goes (8-288 points of 0.2-0.4 million on clean walks, session
        93); an evicted part of the map (``map.capacity_voxels``) would go whole."""
        if self._dense is None or not len(self._dense):
            return np.zeros((0, 3)), 0
        pts = self._dense.points()
        ref = np.asarray(map_points, dtype=np.float64)
        ref = ref[np.all(np.isfinite(ref), axis=1)]
        if not ref.shape[0]:
            return np.zeros((0, 3)), pts.shape[0]
        d, _ = cKDTree(ref).query(pts, distance_upper_bound=self.cfg.map.map_leaf_m,
                                  workers=-1)
        near = np.isfinite(d)
        return pts[near], int(pts.shape[0] - np.count_nonzero(near))

    def _on_map_plane(self, points_world: np.ndarray, *, in_map: bool = True) -> np.ndarray:
        """(N,) bool: each map point lies on the plane its ``filter.knn_k`` nearest other map
        points fit, by the filter's own test of a plane (the general set's margin,
        ``filter.min_neighbors``, ``filter.plane_min_extent_fraction``; lio-design.md §6.2), and
        within that margin of it. The fit is PCA's whatever ``filter.plane_fit``: the least
        squares' ``a^T x = -1`` tilts a plane through the world's origin (the floor under a
        start). ``in_map`` False: points the map does not hold (its nearest are all others)."""
        if points_world.shape[0] == 0:
            return np.zeros(0, np.bool_)
        f, g = self.cfg.filter, self.cfg.adaptive.general
        skip = int(in_map)  # a map point is its own nearest
        nbrs, counts, _ = self._ivox.knn(points_world, f.knn_k + skip, f.knn_max_range_m)
        nbrs, counts = nbrs[:, skip:], np.maximum(counts - skip, 0)
        normals, d, valid = fit_planes(nbrs, counts, f.min_neighbors, g.plane_margin_m,
                                       "pca", f.plane_min_extent_fraction * self._ivox.cell_m)
        off = np.abs(np.einsum("ij,ij->i", np.nan_to_num(normals), points_world) + np.nan_to_num(d))
        return valid & (off <= g.plane_margin_m)

    def take_backfill(self) -> list[Estimate]:
        """Poses of the scans read before the initialization, in time order (the backfill,
        ``imu.backfill_s``), each stamped at the start of its scan; and the filter's estimates
        held back while the LiDAR checked a static start's rest (``imu.rest_lidar_check``),
        stamped at their scan's end as ``add_scan``'s are. Each handed out once; none while
        the check is pending (a refuted rest takes back what it gave the backfill)."""
        if self._on_trial is not None:
            return []
        out, self._backfilled = self._backfilled, []
        return out

    def add_scan(self, points_lidar: np.ndarray, t_ns: np.ndarray,
                 ring: np.ndarray | None = None,
                 line: np.ndarray | None = None) -> Estimate | None:
        """Process one sweep (§10) and return the IMU pose at the scan end.

        Give ``add_imu`` the samples up to the scan end and the first one after it first (as
        the ``Sequencer`` releases them): the interval the scan end falls in is then propagated
        at its mid-point rate, not the rate of the interval before.

        Returns None while initializing, for a scan with no point left after preprocessing, and
        for a scan ending at or before the previous one (counted in ``n_skipped_scans``).
        ``ring`` (N,) holds each point's ring id (``Scan.ring``), used by the stray test and
        ``filter.local_surface_check``. ``line`` (N,), for a cloud without rings, each point's
        Livox laser (``Scan.line``): the stray test reads a laser's points in firing order as
        it reads a ring's; nothing else takes it for a ring.
        Raises InputError for malformed arrays or per-point times spanning > 1 s. Once the
        filter has tracked ``imu.backfill_after_s``, the scans read before the initialization
        get their poses (``take_backfill``). After a static start at the recording's start,
        the estimates of its first ``imu.init_window_s`` or so are held back (None) until the
        LiDAR has checked the rest (``imu.rest_lidar_check``), then handed out by
        ``take_backfill``.
        """
        if ring is None and line is not None:  # the stray test's ids; local_surface: none
            ring, self._ring_is_line = line, True
        # [points, t_ns, ring, the IMU chunks it merged, raised]: a trial's replay record
        entry = [points_lidar, t_ns, ring, [], False]
        self._input = entry
        if self._on_trial is not None:
            self._keep_input(entry)
        try:
            est = self._add_scan(points_lidar, t_ns, ring)
        except InputError:
            entry[4] = True
            raise
        finally:
            self._input = None
        self._backfill_when_due(est)
        if self._on_trial is not None:
            est = self._judge_rest(est)
        return est

    def _backfill_when_due(self, est: Estimate | None) -> None:
        if (est is not None and self._held_scans and self._t_state_ns - self.init_report.t_ns
                >= round(self.cfg.imu.backfill_after_s * 1e9)):
            self._backfill()

    def _keep_input(self, entry: list) -> None:
        """Record an ``add_scan`` call for a trial's replay, its arrays copied (a caller may
        reuse its buffers)."""
        assert self._on_trial is not None
        for k in range(3):
            if entry[k] is not None:
                entry[k] = np.array(entry[k], copy=True)
        self._on_trial.inputs.append(entry)

    def _add_scan(self, points_lidar: np.ndarray, t_ns: np.ndarray,
                  ring: np.ndarray | None) -> Estimate | None:
        t_start = time.perf_counter()
        stage_ms: dict[str, float] = {}
        cfg = self.cfg
        stats = ScanStats()

        # 1. preprocess (§6.1): finite, blind, max range, decimation
        t0 = t_start
        pts, t_pts, full = self._preprocess(points_lidar, t_ns, ring, stats)
        self._merge_imu()
        t0 = _timer(stage_ms, "preprocess", t0)
        if pts.shape[0] == 0:
            return None
        t_b, t_e = int(t_pts.min()), int(t_pts.max())
        if t_e - t_b > MAX_SCAN_SPAN_NS:
            raise InputError(f"add_scan: per-point times span {(t_e - t_b) * 1e-9:.3f} s in one "
                             "sweep: check the point time unit/reference (sensor.point_time_*)")
        if self.initialized and t_e <= self._t_state_ns:
            self.n_skipped_scans += 1
            return None
        stats.t_ns = t_e
        self._span_s = (t_e - t_b) * 1e-9

        if self._units_check is not None:
            self._check_gyro_units(pts, t_pts, t_e)
        elif self._on_trial is not None:  # the unit check concluded; the rest check goes on
            self._feed(self._on_trial.registrar, pts, t_pts, t_e)
        # 2. initialization: static (§4), or in motion after imu.init_timeout_s without rest
        if not self.initialized:
            pts_e = self._try_initialize(pts, t_pts, t_b, t_e)
            t0 = _timer(stage_ms, "undistort", t0)
            if not self.initialized:
                self._scans_without_pose += 1
                self._hold(pts, t_pts, stats)
                self._accumulate(stage_ms)
                return None
        else:
            pts_e = None
        if self._held_scans:  # tracked since the initialization, until the backfill runs
            self._hold(pts, t_pts, stats)
        if pts_e is not None:
            return self._first_map(pts_e, t_e, stats, stage_ms, t_start, t0)

        # 3-4. propagate with pose records, undistort to the scan end (§5)
        t_prev = self._t_state_ns
        surface = None
        if full is None:
            pts_e = self._propagate_and_undistort(pts, t_pts, t_e)
        else:  # every point in range, for the local surfaces; the decimated ones as usual
            pts_all, t_all, ring_all, rows = full
            pts_all_e = self._propagate_and_undistort(pts_all, t_all, t_e)
            pts_e = pts_all_e.take(rows, axis=0)
            surface = LocalSurface(pts_all, pts_all_e, ring_all, rows,
                                   cfg.filter.local_surface_window_ring_spacings)
        if cfg.imu.zero_velocity_update:
            stats.rest_update = self._rest_update(t_e)
        t0 = _timer(stage_ms, "undistort", t0)
        if self._last_gap is not None:
            stats.imu_gap_s = self._last_gap[1]
        if self._t_first_map_ns is not None:
            stats.lidar_gap_s = self._lidar_gap(t_prev, t_e)

        # 5. first scan after init: whole scan into the map, no update (§4)
        if self._t_first_map_ns is None:
            return self._first_map(pts_e, t_e, stats, stage_ms, t_start, t0)

        # 5b. points on moving things out of the map and of this scan (map.remove_moving)
        image = None
        if self._movers is not None:
            image, still = self._drop_moving(pts_e, t_e, stats)
            if not still.all():
                pts_e = np.compress(still, pts_e, axis=0)
                if surface is not None:
                    surface = LocalSurface(pts_all, pts_all_e, ring_all, rows[still],
                                           cfg.filter.local_surface_window_ring_spacings)
            t0 = _timer(stage_ms, "moving", t0)

        # 6. downsample with the general leaf, degeneracy check, switch parameters (§6.1, §9)
        general = cfg.adaptive.general
        down_general, voxel_of_point = voxel_downsample_with_index(pts_e, general.voxel_size_m)
        t0 = _timer(stage_ms, "downsample", t0)
        decision = self._detector.check(down_general, weak_geometry=self._weak_geometry)
        params = decision.params
        t0 = _timer(stage_ms, "degeneracy", t0)
        leaf_m = params.voxel_size_m
        down = down_general
        if leaf_m != general.voxel_size_m:
            down, voxel_of_point = voxel_downsample_with_index(pts_e, leaf_m)
        t0 = _timer(stage_ms, "downsample", t0)
        x_pred, P_pred = self._state, self._P
        cell_m = self._map_cell(params.voxel_size_m)
        after_gap = self._after_gap(stats)
        assoc = _Association(down, self._ivox, cfg, params.search_radius_m, params.plane_margin_m,
                             min(cell_m, self._finest_cell_m),
                             self._local_planes(surface, down, voxel_of_point),
                             self._prior_pose_cov, after_gap)
        projector = None
        if cfg.adaptive.mode == "adaptive+" and decision.degenerate:
            down, assoc, leaf_m, projector, stats.min_restoring = self._refine(
                pts_e, down, assoc, leaf_m, params, surface, after_gap)
            stats.held_directions = 6 - int(np.linalg.matrix_rank(projector, tol=1e-6))
        t0 = _timer(stage_ms, "degeneracy", t0)

        # 7. iterated ESKF update (§6.4)
        loc: Localizability | None = None
        if down.shape[0] >= MIN_POINTS_FOR_UPDATE:
            result = iterated_update(
                x_pred, P_pred, assoc.measure, cfg.filter, projector,
                assoc.noise_terms if cfg.filter.errors_in_variables else None)
            stats.height_blind = self._update_report_covariance(x_pred, result.state, assoc,
                                                                projector)
            self._state, self._P = result.state, result.P
            if self._offset_check is not None and result.lidar_normal is not None:
                self._check_time_offset(t_e, result)
            stats.iterations = result.iterations
            stats.n_searches = assoc.n_searches
            stats.n_matched = int(assoc.H.shape[0])
            if assoc.local is not None:
                self.local_surface_rows[0] += assoc.n_disagree
                self.local_surface_rows[1] += assoc.n_disagree + stats.n_matched
            loc = localizability(assoc.H[:, :6], cfg.filter.laser_point_cov,
                                 observability=False)
            stats.eigenvalues = loc.eigenvalues
            stats.weakest_direction = loc.weakest
            stats.degeneracy_score = loc.score
        else:
            stats.degeneracy_score = 1.0
        self._weak_geometry = bool(cfg.adaptive.use_localizability_trigger and loc is not None
                                   and loc.translation_ratio < cfg.adaptive.min_eigen_ratio)
        t0 = _timer(stage_ms, "update", t0)

        # 8. map insertion with the updated pose (§7)
        s = self._state
        p_world = points_to_world(down, s.R, s.p, s.R_LI, s.t_LI)
        inserted = down.shape[0] >= MIN_POINTS_FOR_UPDATE
        if image is not None:  # map.remove_moving: near moving things, points wait
            self._movers.add_sweep(image, *s.lidar_pose(), t_e)
            for pts, cell in self._movers.matured(t_e):
                self._movers.stored(pts[self._ivox.add_points(pts, cell)], t_e)
            if inserted:
                now = self._movers.admit(p_world[self._ivox.would_store(p_world, cell_m)],
                                         cell_m, t_e)
                self._movers.stored(now[self._ivox.add_points(now, cell_m)], t_e)
        elif inserted:
            self._ivox.add_points(p_world, cell_m)
        if inserted:
            self._finest_cell_m = min(self._finest_cell_m, cell_m)
            self._last_cell_m = cell_m
            if self._dense is not None:  # the scan's still points, not only the downsampled
                self._dense.add(points_to_world(pts_e, s.R, s.p, s.R_LI, s.t_LI))
        if cfg.filter.map_uncertainty and loc is not None:
            self._W_map = self._provenance.map_covariance(s.p, assoc.nearest[assoc.selected])
        W_world = self._world_covariance(extrinsic=False)
        if cfg.filter.map_uncertainty:
            self._provenance.add_scan(s.p, W_world, p_world if inserted else p_world[:0])
        W_ext = self._extrinsic_covariance()
        W_world = W_world + W_ext
        stats.sigma_extrinsic_m = float(np.sqrt(max(np.max(np.diag(W_ext)[:3]), 0.0)))
        stats.var_extrinsic_world = np.clip(np.diag(W_ext), 0.0, None)
        t0 = _timer(stage_ms, "map", t0)

        stats.n_down, stats.n_down_general = int(down.shape[0]), int(down_general.shape[0])
        stats.n_near, stats.degenerate, stats.trigger = (decision.n_near, decision.degenerate,
                                                         decision.trigger)
        stats.voxel_size_m, stats.search_radius_m = leaf_m, params.search_radius_m
        stats.plane_margin_m = params.plane_margin_m
        return self._emit(stats, stage_ms, t_start, p_world, W_world)

    # ------------------------------------------------------------------ stages
    def _drop_moving(self, pts_e: np.ndarray, t_e: int,
                     stats: ScanStats) -> tuple[SweepImage, np.ndarray]:
        """The sweep's range images, and which of its points are still (``lio/moving.py``): map
        points it sees through leave the map first, at the predicted pose. Not after a gap,
        whose prediction may be decimetres off: seen from there the whole map would look seen
        through and the sweep in free space; every point is still."""
        s = self._state
        image = self._movers.image(pts_e)
        if self._after_gap(stats):
            return image, np.ones(pts_e.shape[0], np.bool_)
        stats.n_seen_through = self._movers.carve(self._ivox, image, *s.lidar_pose(), t_e)
        moving = self._movers.moving(points_to_world(pts_e, s.R, s.p, s.R_LI, s.t_LI), t_e,
                                     self._ivox, self._last_cell_m)
        stats.n_moving = int(moving.sum())
        return image, ~moving

    def _preprocess(self, points_lidar, t_ns, ring, stats: ScanStats):
        """§6.1 steps 1-2. Returns (points, t_ns, full): ``full`` is None, or with
        ``filter.local_surface_check`` and a ring per point, (every point in range, their
        t_ns, their rings, the rows of them that are the decimated ``points``). Sets the
        points read in ``stats``: ``n_raw`` (the finite ones), ``n_stray``, ``n_stray_dropped``."""
        pts = np.asarray(points_lidar)
        t = np.asarray(t_ns)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"add_scan: points_lidar must have shape (N, 3), got {pts.shape}")
        if (t.shape != (pts.shape[0],) or not np.issubdtype(t.dtype, np.integer)
                or t.dtype.itemsize < 8):
            raise InputError(f"add_scan: t_ns must be (N,) int64 absolute nanoseconds matching "
                             f"the {pts.shape[0]} points, got dtype {t.dtype} shape {t.shape} "
                             "(a narrower integer cannot hold them)")
        pre = self.cfg.preprocess
        pts = np.ascontiguousarray(pts, dtype=np.float64)
        t = np.ascontiguousarray(t, dtype=np.int64)
        local = self.cfg.filter.local_surface_check and self.initialized
        if ring is not None:
            ring = np.asarray(ring)
            if ring.shape != (pts.shape[0],) or not np.issubdtype(ring.dtype, np.integer):
                ids = ("line", "Livox laser ids") if self._ring_is_line else ("ring", "ring ids")
                raise InputError(f"add_scan: {ids[0]} must be (N,) integer {ids[1]} matching "
                                 f"the {pts.shape[0]} points, got dtype {ring.dtype} shape "
                                 f"{ring.shape}")
        n_stray = n_dropped = 0
        span = ring_id_span(ring)
        if not rings_testable(span):  # no rings, one ring id, or ids of no LiDAR
            if pre.drop_stray_returns and pts.shape[0]:  # the option warns; the share is default
                why = ("carry no ring field" if ring is None else "hold one ring id" if span == 1
                       else f"hold ring ids spread over {span} values")
                self._warn_no_ring("preprocess.drop_stray_returns", "no return is dropped as stray",
                                   why)
        else:  # counted always; dropped with the option, or where more than the share
            # the finite points (a column at a time: numpy's all(axis=1) over three columns
            # took 0.9 of 3.4 ms per 63k-point sweep), gathered only when some are not
            finite_xyz = np.isfinite(pts)
            finite = finite_xyz[:, 0] & finite_xyz[:, 1] & finite_xyz[:, 2]
            if finite.all():
                rows_f = None
                code = stray_codes(pts, t, ring.astype(np.int64), pre.stray_tolerance_m,
                                   pre.stray_tolerance_rel, self._ring_is_line)
            else:
                rows_f = np.flatnonzero(finite)
                code = stray_codes(pts.take(rows_f, axis=0), t[rows_f],
                                   ring[rows_f].astype(np.int64),
                                   pre.stray_tolerance_m, pre.stray_tolerance_rel,
                                   self._ring_is_line)
            n_stray = int((code == STRAY).sum())
            if n_stray and (pre.drop_stray_returns
                            or n_stray > pre.stray_drop_share * code.size):
                # a dirty sweep: also the points an adjacent ring supports, as many of them
                # are stray returns that met another by chance, or a neighbour of one
                drop = code != CONTINUED
                keep = np.ones(pts.shape[0], bool)
                keep[drop if rows_f is None else rows_f[drop]] = False
                pts, t, ring = np.compress(keep, pts, axis=0), t[keep], ring[keep]
                n_dropped = int(drop.sum())
        rows, dec, n_raw = _range_gate_rows(pts, pre.blind_m, pre.max_range_m,
                                            pre.point_filter_num)
        stats.n_raw = int(n_raw) + n_dropped  # the points read: those dropped as stray too
        stats.n_stray, stats.n_stray_dropped = n_stray, n_dropped
        keep = rows[dec]
        full = None
        if local:
            if ring is None or self._ring_is_line:
                self._warn_no_ring("filter.local_surface_check", "no row is checked")
            else:
                full = (pts.take(rows, axis=0), t[rows],
                        np.clip(ring[rows], 0, 65535).astype(np.uint16), np.flatnonzero(dec))
        # the rows of an (N, 3) array by take / compress: numpy's fancy and boolean indexing of
        # one took 3-4 times as long (0.84 against 0.22 ms for a 63k-point sweep's mask)
        return pts.take(keep, axis=0), t[keep], full

    def _warn_no_ring(self, key: str, consequence: str, why: str = "carry no ring field") -> None:
        if key not in self._warned_no_ring:
            self._warned_no_ring.add(key)
            warnings.warn(f"{key} is on but the scans {why}: {consequence}", stacklevel=5)

    def _merge_imu(self) -> None:
        if not self._pending:
            return
        if self._on_trial is not None and self._input is not None:
            self._input[3].extend(self._pending)
        if (not self.initialized or self._held_scans) and self.cfg.imu.backfill_s > 0:
            self._held_imu.extend(self._pending)
        b = self._buf
        self._buf = _ImuBuffer(np.concatenate([b.t_ns] + [p[0] for p in self._pending]),
                               np.concatenate([b.gyro] + [p[1] for p in self._pending]),
                               np.concatenate([b.accel] + [p[2] for p in self._pending]))
        self._pending.clear()

    def _first_map(self, pts_e: np.ndarray, t_e: int, stats: ScanStats,
                   stage_ms: dict[str, float], t_start: float, t0: float) -> Estimate:
        """The first scan after init goes into the map whole, with no update (§4)."""
        s = self._state
        self.lidar_view = lidar_view(pts_e, s.R @ s.R_LI, s.g)
        p_world = points_to_world(pts_e, s.R, s.p, s.R_LI, s.t_LI)
        stored = self._ivox.add_points(p_world)
        if self._dense is not None:
            self._dense.add(p_world)
        if self._movers is not None:  # the anchor's map is the world: no probation
            self._movers.add_sweep(self._movers.image(pts_e), *s.lidar_pose(), t_e)
            self._movers.stored(p_world[stored], t_e)
        self._t_first_map_ns = t_e
        self._anchor_state = s.copy()
        self._anchor_v_cov = self._P[V, V].copy()
        # This pose anchors the map, so it defines the world: no error relative to it.
        self._W_map = np.zeros((6, 6))
        self._provenance.add_scan(s.p, np.zeros((6, 6)), p_world)
        if self._keeps_discounted_P:
            # the discounted covariance (reported sigmas, robust kernel) starts here: no position
            # or yaw error at the anchor (the filter's own P keeps Faster-LIO's initial one)
            self._P_report = anchored_covariance(s.R, self._P)
            if self._keeps_blind_P:
                self._P_blind = self._P_report.copy()
        _timer(stage_ms, "map", t0)
        g = self.cfg.adaptive.general
        stats.n_down = stats.n_down_general = int(pts_e.shape[0])
        stats.voxel_size_m, stats.search_radius_m = g.voxel_size_m, g.search_radius_m
        stats.plane_margin_m = g.plane_margin_m
        est = self._emit(stats, stage_ms, t_start, p_world)
        # This pose anchors the map, so it defines the world: no error relative to it.
        stats.sigma_p_world_m, stats.sigma_rot_world_deg = np.zeros(3), np.zeros(3)
        return est

    # ------------------------------------------------------------------ backfill
    @property
    def backfill_pending(self) -> bool:
        """Scans read before the initialization wait for the backfill (``take_backfill``)."""
        return bool(self._held_scans)

    def finish(self) -> None:
        """End of the data: run a pending backfill now, from the latest state; the sensor
        checks still open conclude if they have seen ``END_MIN_SPAN_S`` of updates and their
        estimates are conclusive, else they close unsettled (:attr:`time_offset_unsettled`,
        :attr:`extrinsic_rotation_unsettled`, :attr:`extrinsic_translation_unsettled`)."""
        self.conclude_rest_check()  # the data ended before the rest check's span
        gap = self._last_gap
        if gap is not None and self._warned_gap_ns != gap[0]:  # still open: the IMU ended
            self._warned_gap_ns = gap[0]
            import warnings

            warnings.warn(f"the IMU data end at t = {gap[0] * 1e-9:.3f} s, {gap[1]:.2f} s before "
                          "the last scan's end: the scans after it were posed by the "
                          "constant-velocity motion model alone (scans.csv column imu_gap; "
                          "adalio run leaves such scans out)", stacklevel=2)
        if self._held_scans and self.initialized:
            self._backfill()
        if self._gross_open and self._units_check is not None:
            self._judge_gross_rotation(self._units_check, self._gross_t0_ns, last=True)
        self._gross_open = False
        chk = self._offset_check
        if chk is not None:
            span = chk.span_s
            motion = chk.motion_samples() if span >= END_MIN_SPAN_S else None  # gathered once
            data = _rotation_data(motion)
            if self._offset_open:
                self._conclude_time_offset(
                    None if data is None else estimate_offset(*data, span), span)
            if self._rotation_open:
                self._conclude_rotation(self._rotation_from(data, span), span, last=True)
            if self._translation_open:
                self._conclude_translation(self._translation_from(motion, span), span)
            if self._scale_open:
                self._conclude_scale(self._scale_from(data, span), span)
        self._offset_check = None

    def time_offset_estimate(self) -> TimeOffsetEstimate | None:
        """The IMU time offset check's conclusion, or its estimate so far (None: too few
        updates, or the check is off)."""
        if self.time_offset is not None or self._offset_check is None or not self._offset_open:
            return self.time_offset
        return self._offset_check.estimate()

    def extrinsic_rotation_estimate(self) -> RotationEstimate | None:
        """The LiDAR-IMU rotation check's conclusion, or its estimate so far (None: too few
        updates, too little rotation, the check is off, or a gross error stopped it)."""
        if (self.extrinsic_rotation is not None or self._offset_check is None
                or not self._rotation_open):
            return self.extrinsic_rotation
        chk = self._offset_check
        return self._rotation_from(chk.samples(), chk.span_s)

    def gyro_scale_estimate(self) -> GyroScaleEstimate | None:
        """The gyro scale check's conclusion, or its estimate so far (None: too few updates,
        too little rotation about some axis, or the check is off)."""
        if self.gyro_scale is not None or self._offset_check is None or not self._scale_open:
            return self.gyro_scale
        chk = self._offset_check
        return self._scale_from(chk.samples(), chk.span_s)

    def _scale_from(self, data: tuple | None, span_s: float) -> GyroScaleEstimate | None:
        """The gyro scale check's estimate from the checks' data, as :meth:`_rotation_from`,
        over the scan pairs whose LiDAR-only orientations are known well
        (``TimeOffsetCheck.rotation_sds``)."""
        if data is None or self._offset_check is None:
            return None
        return estimate_gyro_scale(*data, self._offset_found_s, span_s,
                                   rot_sd_rad=self._offset_check.rotation_sds())

    def _lidar_rotation_sd(self, result: UpdateResult) -> float:
        """The standard deviation (rad) of the update's LiDAR-only orientation about its
        weakest axis: ``filter.laser_point_cov`` over the rotation block of the registration's
        information, translation marginalised (NaN without rows)."""
        if result.lidar_normal is None:
            return float("nan")
        A = result.lidar_normal[0]
        try:
            info = A[3:, 3:] - A[3:, :3] @ np.linalg.solve(A[:3, :3], A[:3, 3:])
        except np.linalg.LinAlgError:
            return float("inf")
        weakest = float(np.linalg.eigvalsh(0.5 * (info + info.T))[0])
        return float(np.sqrt(self.cfg.filter.laser_point_cov / weakest)) if weakest > 0 else \
            float("inf")

    def _conclude_scale(self, est: GyroScaleEstimate | None, span_s: float) -> None:
        """Close the gyro scale check on ``est``: its conclusion (``run_bag`` acts on a
        significant one), or unsettled (:attr:`gyro_scale_unsettled`). Unlike the rotation
        check's, its last look (``MAX_SPAN_S`` or the end of the data) asks the same precision
        of a significant estimate (``SIGMA_SIGNIFICANT``): where the LiDAR registers the
        rotation too weakly to measure the scales to it (a spiral shaft: a rotational
        information a hundredth of the hall's), the estimate's bias outgrows its deviation."""
        self._scale_open = False
        if est is None or not est.conclusive:
            if self.conclude_time_offset:
                self.gyro_scale_unsettled = UnsettledCheck(
                    span_s, est, gave_up=span_s >= MAX_SPAN_S)
            return
        self.gyro_scale = est

    def _rotation_from(self, data: tuple | None, span_s: float) -> RotationEstimate | None:
        """The rotation check's estimate from the checks' data (``TimeOffsetCheck.samples``),
        the gyro's lateness taken as the time offset concluded on (none: 0)."""
        if data is None:
            return None
        return estimate_rotation(*data, self._offset_found_s, span_s)

    @property
    def _offset_found_s(self) -> float:
        """The IMU time offset the check concluded on (0 until it does): the lateness the
        rotation and lever arm checks take the gyro's and accelerometer's stamps to have."""
        return self.time_offset.offset_s if self.time_offset is not None else 0.0

    def _hold(self, pts: np.ndarray, t_pts: np.ndarray, stats: ScanStats) -> None:
        """Keep a scan for the backfill: before the initialization the latest
        ``imu.backfill_s`` of them (points as float32, with the counts of the points read that
        its backfilled row reports), after it every scan until the backfill runs; and the IMU
        samples they span."""
        keep_s = self.cfg.imu.backfill_s
        if not keep_s > 0:
            return
        self._held_scans.append((pts.astype(np.float32), t_pts.copy(),
                                 (stats.n_raw, stats.n_stray, stats.n_stray_dropped)))
        if self.initialized:
            return
        horizon = int(t_pts.max()) - round(keep_s * 1e9)
        while len(self._held_scans) > 1 and int(self._held_scans[0][1].min()) < horizon:
            self._held_scans.pop(0)
        t_from = int(self._held_scans[0][1].min()) - round(self.cfg.imu.init_window_s * 1e9)
        while len(self._held_imu) > 1 and int(self._held_imu[1][0][0]) <= t_from:
            self._held_imu.pop(0)

    def _backfill(self) -> None:
        """Poses for the scans read before the initialization: the filter run backwards in
        time from its latest state, with its map, through the scans since the first one held
        (``take_backfill``; README, Initialization, *Backfill*).

        Time reversal maps the same kinematics onto itself: with mirrored times
        ``t' = c - t``, a gyro reading ``-omega``, the same specific force, velocity ``-v`` and
        gyro bias ``-b_g`` (their covariance rows and columns negated likewise), position,
        attitude, accelerometer bias and gravity unchanged. So a copy of this filter, handed
        the mirrored state and data, runs the reverse pass; the pose it reports at the end of
        a mirrored scan is the pose at that scan's start. It re-registers the scans since the
        initialization against the map they built (their forward poses stand), then continues
        into the held ones, whose poses and points (``map_points``) it adds. The forward run
        is the same with or without the backfill.
        """
        held, chunks = self._held_scans, self._held_imu
        self._held_scans, self._held_imu = [], []
        t_init, t_now = self.init_report.t_ns, self._t_state_ns
        scans = [(p, t, n) for p, t, n in held if int(t.max()) < t_now]
        if not scans or not any(int(t.max()) < t_init for _, t, _ in scans) or not chunks:
            return
        t_imu = np.concatenate([c[0] for c in chunks])
        gyro = np.concatenate([c[1] for c in chunks])
        acc = np.concatenate([c[2] for c in chunks])
        mirror = t_now + int(scans[0][1].min())
        rev = self._reversed_copy(mirror)
        self._rested_ns = []  # handed over to the reversed pass
        k = int(np.argmin(np.abs(t_imu - t_now)))
        rev._prev_sample = (mirror - t_now, -gyro[k], acc[k].copy())
        before = t_imu < t_now
        rev.add_imu(mirror - t_imu[before][::-1], -gyro[before][::-1], acc[before][::-1])
        out: list[Estimate] = []
        stopped = ""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an IMU gap's time would be a mirrored one
            anchored = False
            tracked: np.ndarray | None = None
            for pts, t_pts, read in reversed(scans):
                if (not anchored and self._anchor_state is not None
                        and int(t_pts.max()) <= self._t_first_map_ns):
                    anchored = True
                    rev._hold_to_anchor(self._anchor_state, mirror - self._t_first_map_ns,
                                        self._anchor_v_cov)
                # the dense map takes the held scans' points at their backfilled poses, not
                # those of the scans since the initialization again (the forward run's stand)
                held_scan = int(t_pts.max()) < t_init
                rev._dense = self._dense if held_scan else None
                if held_scan and tracked is None:  # what the map holds before the held scans
                    tracked = rev._ivox.points()
                try:
                    est = rev.add_scan(pts, mirror - t_pts)
                except InputError as exc:
                    stopped = (f"the backfill stopped at the scan starting at "
                               f"t = {int(t_pts.min()) * 1e-9:.3f} s: {exc}")
                    break
                if est is None or int(t_pts.max()) >= t_init:
                    continue
                st = est.stats
                st.t_ns = mirror - st.t_ns
                st.backfill = True
                st.n_raw, st.n_stray, st.n_stray_dropped = read  # the points read, not held
                out.append(Estimate(
                    t_ns=st.t_ns, T_world_imu=est.T_world_imu,
                    velocity_world_m_s=-est.velocity_world_m_s,
                    gyro_bias_rad_s=-est.gyro_bias_rad_s, accel_bias_m_s2=est.accel_bias_m_s2,
                    gravity_world_m_s2=est.gravity_world_m_s2, cov_diag=est.cov_diag,
                    stats=st, points_world=est.points_world))
        if stopped:
            warnings.warn(stopped, stacklevel=3)
        self._backfilled = sorted(self._backfilled + out[::-1], key=lambda e: int(e.t_ns))
        if out and tracked is not None:
            self._backfill_map, self._backfill_returns, self._backfill_on_plane = (
                rev._map_gained(tracked))
        self._accumulate(rev.stage_ms_total)
        self.init_report.backfilled = len(out)

    def _hold_to_anchor(self, anchor: State, t_anchor_ns: int,
                        anchor_v_cov: np.ndarray) -> None:
        """The reversed pass, on reaching the anchor's time (mirrored ``t_anchor_ns``), told
        the anchor's position and yaw: they define the world, so they are known exactly there
        (:func:`adalio.lio.state.anchored_covariance`). Without this the reversed pass carries
        whatever it drifted re-registering the scans since the initialization into the held
        scans, a jump at the seam (14-35 cm along a robot's corridor on the XT-32 at 512
        columns, README, Initialization, *Backfill*). A Kalman update with
        ``H = [I on p; (Rᵀe_z)ᵀ on θ]`` and a vanishing noise, so the correction reaches the
        velocity and biases through their correlations; the anchor's velocity carries its
        position over the gap between the two times (one point period between scans). Roll
        and pitch are left to the reversed pass: gravity defines them, and its estimate there
        has had the whole tracked stretch.

        The same update is also told the anchor's velocity (mirrored: ``-v``) with the forward
        filter's covariance of it there (``anchor_v_cov``): what the initialization measured
        before the anchor (a still window's zero, a moving start's fit), independent of the
        scans after it that the reversed pass has used. Told the position alone, a reversed
        pass that had drifted along a corridor's weak axis turned the position's correction
        into a velocity through their correlation, and carried it into the held scans (a
        still start given 1.7 m/s, its held poses a metre off: README, *Backfill*)."""
        x = self._state
        dt_s = (self._t_state_ns - t_anchor_ns) * 1e-9  # mirrored time runs backwards
        p_anchor = anchor.p - anchor.v * dt_s
        up_body = x.R[2, :]  # Rᵀ e_z: a small world yaw is up_body · δθ
        H = np.zeros((7, DIM))
        H[0:3, P_] = np.eye(3)
        H[3, TH] = up_body
        H[4:7, V] = np.eye(3)
        r = np.empty(7)
        r[0:3] = p_anchor - x.p
        r[3] = so3.log(anchor.R @ x.R.T)[2]
        r[4:7] = -anchor.v - x.v
        noise = np.zeros((7, 7))
        noise[0:4, 0:4] = ANCHOR_VARIANCE * np.eye(4)
        noise[4:7, 4:7] = anchor_v_cov + ANCHOR_VARIANCE * np.eye(3)
        K, self._P = joseph_update(self._P, H, noise)
        self._state = x.boxplus(K @ r)
        for name in ("_P_report", "_P_blind"):
            P = getattr(self, name)
            if P is not None:
                setattr(self, name, joseph_update(P, H, noise)[1])

    def _reversed_copy(self, mirror_ns: int) -> Odometry:
        """This filter (state, covariance, map) in mirrored time ``mirror_ns - t``, without IMU
        data or held scans (``_backfill``). In mode ``adaptive`` the copy leaves its rows
        unweighted (``filter.robust_kernel`` ``auto`` resolves to ``none`` there, as in
        ``adaptive+``). Run back through a stretch whose axis the LiDAR cannot restore (a
        Mid-360 in the corridor, for 35 s before a moving start), the pass with the Huber kernel
        slowed from the walk's 1 m/s to a standstill, 10 m off with σ 15 cm; without it, it kept
        the velocity. Session 96 ran the copy in ``adaptive+`` instead, which drops the kernel
        too but also holds the stairwell's height at the IMU's prediction: the XT-32's
        stairwell starts lost 4-39 cm by it (README, Initialization, *Backfill*). ``fixed``
        keeps its kernel: there the stairwell's reversed pass needs it (a mean of 8.9 → 71 cm
        without). The forward run keeps the configured kernel."""
        rev = copy.copy(self)
        for name in ("_ivox", "_detector", "_provenance"):  # what add_scan changes in place
            setattr(rev, name, copy.deepcopy(getattr(self, name)))
        cfg = self.cfg
        if self._movers is not None:  # its own sweeps and young map points, in mirrored time:
            # shared, they would reach the forward run's next scans (its sweep at a mirrored
            # time taken for the one a lookback earlier, its points for the map's)
            rev._movers = MovingPoints.from_config(cfg.map)
        kernel = cfg.filter.robust_kernel
        if kernel == "auto" and cfg.adaptive.mode == "adaptive":
            kernel = "none"
        rev.cfg = replace(cfg, preprocess=replace(cfg.preprocess, point_filter_num=1),
                          imu=replace(cfg.imu, backfill_s=0.0),
                          filter=replace(cfg.filter, robust_kernel=kernel))
        x = self._state
        rev._state = State(p=x.p.copy(), R=x.R.copy(), R_LI=x.R_LI.copy(), t_LI=x.t_LI.copy(),
                           v=-x.v, b_g=-x.b_g, b_a=x.b_a.copy(), g=x.g.copy(),
                           g_anchor=x.g_anchor)
        flip = np.ones(DIM)
        flip[V] = flip[BG] = -1.0
        rev._P = self._P * np.outer(flip, flip)
        if self._P_report is not None:
            rev._P_report = self._P_report * np.outer(flip, flip)
        if self._P_blind is not None:
            rev._P_blind = self._P_blind * np.outer(flip, flip)
        rev._t_state_ns = mirror_ns - self._t_state_ns
        rev._rested_ns = []
        rev._rested_mirrored_ns = [(mirror_ns - b, mirror_ns - a) for a, b in self._rested_ns]
        rev._buf = _ImuBuffer(np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 3)))
        rev._rest_imu = rev._track_imu = rev._buf
        rev.noise_raises = []
        rev._noise_shown = (False, False)
        rev._pending, rev._last_imu_t_ns = [], None
        rev._held_scans, rev._held_imu, rev._backfilled = [], [], []
        rev._on_trial = rev._input = None
        rev._backfill_map = np.zeros((0, 3))
        rev._last_gap = rev._warned_gap_ns = rev._units_check = rev._offset_check = None
        rev._units_open = rev._gross_open = False
        rev._scan_intervals_ns, rev.lidar_gaps = [], []
        rev.stage_ms_total = dict.fromkeys(self._stages, 0.0)
        return rev

    def _try_initialize(self, pts: np.ndarray, t_pts: np.ndarray, t_b_ns: int,
                        t_e_ns: int) -> np.ndarray | None:
        """Static init over ``imu.init_window_s`` before the scan start if the IMU rests there
        (§4); otherwise the scan feeds the moving-start initializer (``motion_init.py``), which
        takes over once ``imu.init_timeout_s`` has passed since the first scan. Returns the
        deskewed scan when a moving start completed on it (it becomes the first map)."""
        cfg = self.cfg.imu
        b = self._buf
        if self._t_first_scan_ns is None:
            self._t_first_scan_ns = t_b_ns
        window = imu.stillness_window(b.t_ns, t_b_ns, cfg.init_window_s)
        if window is not None:
            test = imu.stillness_test(b.t_ns[window], b.gyro[window], b.accel[window], cfg)
            close = self._closest_still
            if close is None or not (max(close.gyro_ratio, close.accel_ratio)
                                     <= max(test.gyro_ratio, test.accel_ratio)):
                self._closest_still = test
            verdict, check = self._rest_verdict(t_b_ns) if test.still else ("refuted", None)
            if verdict != "refuted":
                snapshot = self._snapshot() if verdict == "unknown" else None
                self._static_initialize(window, t_b_ns, test)
                if check is not None:
                    self.init_report.lidar_rest = check.verdict()
                if snapshot is not None:
                    assert self._units_check is not None and self._input is not None
                    self._on_trial = _RestOnTrial(snapshot, self._units_check, t_b_ns)
                    self._keep_input(self._input)
                return None
        timeout_ns = round(cfg.init_timeout_s * 1e9)
        if self._moving is None:
            self._moving = MovingInit(self.cfg, self._R_LI, self._t_LI)
        self._feed(self._moving, pts, t_pts, t_e_ns)
        keep_from = int(np.searchsorted(b.t_ns, t_b_ns - round(cfg.init_window_s * 1e9)))
        self._buf = _ImuBuffer(b.t_ns[keep_from:], b.gyro[keep_from:], b.accel[keep_from:])
        if t_e_ns - self._t_first_scan_ns < timeout_ns:
            return None
        self._judge_gyro_units(self._moving, np.zeros(3))
        fit = self._moving.solve()
        if fit is None:
            if not self._moving.waiting:  # waiting for the nested window is no refusal
                self._refused_fits += 1
            return None
        return self._moving_initialize(fit)

    def _rest_verdict(self, t_b_ns: int) -> tuple[str, RestCheck | None]:
        """What the LiDAR says of a still window ending at ``t_b_ns`` (imu.rest_lidar_check),
        and the check that said it (None where none was made): 'refuted' (refused before, or
        the moving start's registrations over the window moved), 'confirmed' (they rested, or
        the check is off), 'unknown' (too few registrations: the recording's start; the scans
        after it decide, :meth:`_judge_rest`)."""
        cfg = self.cfg.imu
        if not cfg.rest_lidar_check:
            return "confirmed", None
        if self._refuted_until_ns is not None and t_b_ns <= self._refuted_until_ns:
            return "refuted", None
        if self._moving is not None:
            lo = t_b_ns - round(cfg.init_window_s * 1e9)
            check = lidar_rest_check([r for r in self._moving.scans if r.t_ns >= lo], cfg)
            if check is not None:
                if check.refuted:
                    self.rest_refuted = check
                    return "refuted", check
                return "confirmed", check
        return "unknown", None

    def _snapshot(self) -> Odometry:
        """A copy of this Odometry to go back to; its config is this one's (a caller may edit
        it in place), and the scans and IMU chunks held for the backfill are shared (never
        changed in place), not copied."""
        held, held_imu = self._held_scans, self._held_imu
        self._held_scans, self._held_imu = [], []
        try:
            snap = copy.deepcopy(self, _shared(self.cfg))
        finally:
            self._held_scans, self._held_imu = held, held_imu
        snap._held_scans, snap._held_imu = list(held), list(held_imu)
        return snap

    def conclude_rest_check(self) -> None:
        """End a pending LiDAR check of a static start's rest (imu.rest_lidar_check) with the
        registrations so far, so that ``take_backfill`` hands out what it held back (``finish``
        does this; ``run_bag`` calls it on Ctrl-C)."""
        if self._on_trial is not None:
            est = self._resolve_rest(None)
            assert est is None

    def _judge_rest(self, est: Estimate | None) -> Estimate | None:
        """A static start on trial: hold ``est`` back until the LiDAR-only registrations span
        ``imu.init_window_s`` (or three times that has passed), then judge the rest."""
        trial = self._on_trial
        assert trial is not None
        if est is not None:
            trial.estimates.append(est)
        regs = trial.registrar.scans
        window_ns = round(self.cfg.imu.init_window_s * 1e9)
        if not ((regs and regs[-1].t_ns - regs[0].t_ns >= window_ns)
                or self._t_state_ns - trial.t_init_ns >= 3 * window_ns):
            return None
        return self._resolve_rest(est)

    def _resolve_rest(self, est: Estimate | None) -> Estimate | None:
        """Conclude the trial: on rest (or too few registrations to judge), hand out the
        estimates held back (the latest as ``add_scan``'s result when it is ``est``, the rest
        by ``take_backfill``); on motion, go back to the state before the static start and run
        the scans since again, the still window refused, so they feed the moving start."""
        trial, self._on_trial = self._on_trial, None
        assert trial is not None
        check = lidar_rest_check(trial.registrar.scans, self.cfg.imu)
        if check is None or not check.refuted:
            if self.init_report is not None:
                self.init_report.lidar_rest = (
                    check.verdict() if check is not None else
                    "the LiDAR could not check it (too few registered scans)")
            held = trial.estimates
            if held and held[-1] is est:
                self._backfilled.extend(held[:-1])
                return est
            self._backfilled.extend(held)
            return None
        live = self.__dict__.copy()
        self.__dict__.clear()
        self.__dict__.update(trial.snapshot.__dict__)
        # what was said stays said, and the IMU's time order is the live one's
        for name, value in live.items():
            if name.startswith("_warned"):
                setattr(self, name, value)
        self._last_imu_t_ns = live["_last_imu_t_ns"]
        pending = live["_pending"]
        if self._offset_check is not None:  # the samples add_imu handed it since the snapshot
            for chunk in [c for entry in trial.inputs for c in entry[3]] + pending:
                self._offset_check.add_imu(*chunk)
        self.rest_refuted = check
        self._refuted_until_ns = max(int(np.max(e[1])) for e in trial.inputs if not e[4])
        for entry in trial.inputs:
            points, t_ns, ring, chunks, raised = entry
            self._pending = list(chunks)
            self._input = entry
            try:
                e = self._add_scan(points, t_ns, ring)
            except InputError:
                if not raised:  # the same scan passed before; it cannot fail now unannounced
                    raise
                continue  # it raised for the caller already (an InputError the caller took)
            finally:
                self._input = None
            self._backfill_when_due(e)
            if e is not None:
                self._backfilled.append(e)
        self._pending = pending
        return None

    def _wait_fields(self, t_init_ns: int) -> dict:
        """The InitReport fields on how long the run went without a pose, and why (called
        before the moving-start registrar is dropped)."""
        return {"wait_s": (t_init_ns - self._t_first_scan_ns) * 1e-9,
                "scans_without_pose": self._scans_without_pose,
                "refused_fits": self._refused_fits,
                "last_refusal": self._moving.failure if self._refused_fits else ""}

    def _static_initialize(self, window: slice, t_b_ns: int, test: imu.StillnessTest) -> None:
        cfg = self.cfg.imu
        b = self._buf
        init = imu.static_init(b.gyro[window], b.accel[window], cfg)
        self._accel_scale = init.accel_scale
        g = init.gravity_world_m_s2
        self._state = State(R=init.R_world_imu, R_LI=self._R_LI.copy(), t_LI=self._t_LI.copy(),
                            b_g=init.gyro_bias_rad_s, g=g, g_anchor=so3.anchor_frame(g))
        self._P = initial_covariance(self.cfg.filter.estimate_extrinsic)
        if cfg.rest_prior:
            var_g, var_a = imu.rest_mean_variances(b.gyro[window],
                                                   b.accel[window] * init.accel_scale,
                                                   imu.block_samples(cfg, test.rate_hz))
            self._P = condition_on_rest(self._P, self._state, var_g, var_a)
        self._t_state_ns = t_b_ns
        last = window.stop - 1
        self._prev_sample = (int(b.t_ns[last]), b.gyro[last].copy(), b.accel[last].copy())
        used = self._use_measured_noise(test)
        self._set_gap_model(b.t_ns[window])
        self._buf = _ImuBuffer(b.t_ns[window.stop:], b.gyro[window.stop:], b.accel[window.stop:])
        self._rest_imu = _ImuBuffer(b.t_ns[window], b.gyro[window],
                                    b.accel[window] * init.accel_scale)
        self._add_rested(int(b.t_ns[window][0]), t_b_ns)  # the held scans there rested
        wait = self._wait_fields(t_b_ns)
        self._moving = None
        self.initialized = True
        self._units_check = MovingInit(self.cfg, self._R_LI, self._t_LI, use_gyro=False)
        self._units_open = True
        self._gross_open = (self.cfg.sensor.extrinsic_rotation_check
                            and self.check_gross_rotation and self._offset_check is not None)
        self._gross_t0_ns = t_b_ns
        acc_mean = b.accel[window].mean(axis=0)
        self.init_report = InitReport(
            method="static", t_ns=t_b_ns, gyro_bias_rad_s=init.gyro_bias_rad_s.copy(),
            gravity_imu_m_s2=init.R_world_imu.T @ g, gravity_world_m_s2=g.copy(),
            window_s=test.window_s,
            accel_norm_m_s2=float(np.linalg.norm(acc_mean)),
            gyro_noise_rad_s_sqrt_hz=test.gyro_noise_rad_s_sqrt_hz,
            accel_noise_m_s2_sqrt_hz=test.accel_noise_m_s2_sqrt_hz,
            noise_used=imu.noise_used(cfg, used), generic_noise=imu_noise_is_generic(cfg),
            detail=test.describe(), **wait)

    def _use_measured_noise(
            self, measured: imu.StillnessTest | imu.NoiseMeasurement | None) -> ImuConfig:
        """The IMU config whose white-noise densities the filter uses from here on, by
        ``imu.noise_source`` (``imu.measured_noise_config``), its process noise set; the
        configured one with ``config`` or when nothing was ``measured``."""
        cfg = self.cfg.imu
        if cfg.noise_source == "config" or measured is None:
            return cfg
        density = float(measured.gyro_noise_rad_s_sqrt_hz)
        self._q_deskew = density**2 if np.isfinite(density) and density > 0 else None
        used = imu.measured_noise_config(
            cfg, measured, only_if_noisier=cfg.noise_source == "at_least_config")
        self._q_diag = imu.process_noise(used)
        self._noise_used = self._noise_start = used
        return used

    def _moving_initialize(self, fit) -> np.ndarray:
        """Hand the moving-start fit (``motion_init.MovingInitResult``) over to the filter."""
        cfg = self.cfg.imu
        b = self._buf
        R_align = np.eye(3)
        if cfg.gravity_align_world:
            R_align = imu.static_init(np.zeros((1, 3)), -fit.gravity_world_m_s2[None],
                                      cfg).R_world_imu
        g = R_align @ fit.gravity_world_m_s2
        self._state = State(R=R_align @ fit.R_world_imu, p=R_align @ fit.p_world_imu_m,
                            v=R_align @ fit.v_world_m_s, R_LI=self._R_LI.copy(),
                            t_LI=self._t_LI.copy(), b_g=fit.gyro_bias_rad_s.copy(), g=g,
                            g_anchor=so3.anchor_frame(g))
        self._P = handover_covariance(fit, R_align, self.cfg.filter.estimate_extrinsic)
        m = self._moving
        held = m.imu_t_ns <= fit.t_ns
        # measured whatever imu.noise_source says, so the report has it as a still start's does
        measured = imu.moving_noise(m.imu_t_ns[held], m.gyro[held], m.accel[held])
        used = self._use_measured_noise(measured)
        self._t_state_ns = fit.t_ns
        self._set_gap_model(m.imu_t_ns)
        last = max(int(np.searchsorted(b.t_ns, fit.t_ns, side="right")) - 1, 0)
        self._prev_sample = (int(b.t_ns[last]), b.gyro[last].copy(), b.accel[last].copy())
        self._buf = _ImuBuffer(b.t_ns[last + 1:], b.gyro[last + 1:], b.accel[last + 1:])
        wait = self._wait_fields(fit.t_ns)
        self._moving = None
        self.initialized = True
        self.init_report = InitReport(
            method="moving", t_ns=fit.t_ns, gyro_bias_rad_s=fit.gyro_bias_rad_s.copy(),
            gravity_imu_m_s2=fit.R_world_imu.T @ fit.gravity_world_m_s2,
            gravity_world_m_s2=g.copy(), window_s=fit.window_s, noise_used=imu.noise_used(cfg, used),
            gyro_noise_rad_s_sqrt_hz=(float("nan") if measured is None
                                      else measured.gyro_noise_rad_s_sqrt_hz),
            accel_noise_m_s2_sqrt_hz=(float("nan") if measured is None
                                      else measured.accel_noise_m_s2_sqrt_hz),
            generic_noise=imu_noise_is_generic(self.cfg.imu),
            detail=(f"{fit.n_scans} scans over {fit.window_s:.1f} s, position residual "
                    f"{fit.residual_m * 100:.1f} cm RMS, unconstrained |g| "
                    f"{fit.gravity_norm_fit_m_s2:.2f} m/s^2"),
            lidar_rest="" if self.rest_refuted is None else self.rest_refuted.verdict(), **wait)
        return fit.points_lidar_end

    def _check_gyro_units(self, pts: np.ndarray, t_pts: np.ndarray, t_e_ns: int) -> None:
        """After a still start, register the next scans LiDAR-only (without the gyro) until they
        have turned enough to judge the gyro's unit (or UNITS_CHECK_S passed), and until the gross
        rotation check concludes (``GROSS_SPAN_S``)."""
        chk = self._units_check
        assert chk is not None
        self._feed(chk, pts, t_pts, t_e_ns)
        if self._units_open:
            done = self._judge_gyro_units(chk, self.init_report.gyro_bias_rad_s)
            if done or (chk.scans and (chk.scans[-1].t_ns - chk.scans[0].t_ns) * 1e-9
                        > UNITS_CHECK_S):
                self._units_open = False
        if self._gross_open:
            self._judge_gross_rotation(chk, t_e_ns, last=False)
        if not (self._units_open or self._gross_open):
            self._units_check = None

    def _judge_gross_rotation(self, chk: MovingInit, t_e_ns: int, *, last: bool) -> None:
        """Once ``GROSS_SPAN_S`` have passed since the still start (``last``: the data ended,
        with ``GROSS_MIN_SPAN_S`` of gyro-free registrations), the gross rotation check
        concludes: a gross error (:attr:`gross_rotation`) where its estimate is one
        (``GrossRotation.gross``) and the fine check's estimate so far is significant too (the
        filter's own data contradict the configured rotation, whose size they cannot tell), or
        where it is beyond doubt (``GrossRotation.certain``); else it closes
        (:attr:`gross_rotation_checked`). The fine checks conclude only then."""
        if not (last or (t_e_ns - self._gross_t0_ns) * 1e-9 >= GROSS_SPAN_S):
            return
        self._gross_open = False
        span = (chk.scans[-1].t_ns - chk.scans[0].t_ns) * 1e-9 if chk.scans else 0.0
        if span < GROSS_MIN_SPAN_S:
            return
        est = self._gross_estimate(chk)
        fine = self.extrinsic_rotation_estimate() if est is not None and est.gross else None
        if est is None or not est.gross or not (
                est.certain or (fine is not None and fine.significant)):
            self.gross_rotation_checked = est
            return
        if fine is not None and fine.significant:
            est.fine_rad, est.fine_sigma_rad = fine.angle_rad, fine.sigma_rad
        self.gross_rotation = est
        self._offset_check = None  # the fine checks read the wrong axes: they stop here
        if self.warn_extrinsic_rotation:
            import warnings

            warnings.warn(f"the LiDAR-IMU rotation is off by {est.text()}: {est.evidence()}; "
                          "check sensor.T_imu_lidar's rotation (or the axes' order in a "
                          "quaternion: x y z w; run_bag restarts with the rotation found)",
                          stacklevel=4)

    def _gross_estimate(self, chk: MovingInit) -> GrossRotation | None:
        """The gross rotation check's estimate from the gyro-free registrations of ``chk`` and
        the gyro the fine checks hold."""
        assert self._offset_check is not None
        t_imu, gyro, _ = self._offset_check.imu_samples()
        scans = [s for s in chk.scans if t_imu.size and s.t_ns >= t_imu[0]]
        if len(scans) < 2:
            return None
        t0 = scans[0].t_ns
        t_scan = np.array([(s.t_ns - t0) * 1e-9 for s in scans])
        return estimate_gross_rotation(t_scan, np.stack([s.R for s in scans]),
                                       (t_imu - t0) * 1e-9, gyro, float(t_scan[-1]))

    def _feed(self, registrar: MovingInit, pts: np.ndarray, t_pts: np.ndarray,
              t_e_ns: int) -> None:
        """Hand a LiDAR-only registrar the buffered IMU samples up to the scan end, then the
        scan."""
        b = self._buf
        n_use = int(np.searchsorted(b.t_ns, t_e_ns, side="right"))
        registrar.add_imu(b.t_ns[:n_use], b.gyro[:n_use], b.accel[:n_use])
        registrar.add_scan(pts, t_pts)

    def _judge_gyro_units(self, chk: MovingInit, b_g: np.ndarray) -> bool:
        """Compare the gyro's rotation with the LiDAR-registered one: 0.5-2x is rad/s (done),
        28-115x is deg/s (error); anything else waits for more rotation."""
        ratio, angle = chk.rotation_ratio(b_g)
        if not angle >= UNITS_CHECK_ANGLE_RAD:
            return False
        if 0.5 < ratio < 2.0:
            return True
        if DEG_PER_RAD / 2 < ratio < DEG_PER_RAD * 2:
            raise InputError(f"the gyro's rotation is {ratio:.0f}x the LiDAR-registered "
                             "rotation over the first scans: it reports deg/s; set "
                             f"sensor.gyro_unit: deg_s{API_UNITS}")
        return False  # undecided: more rotation needed

    def _check_time_offset(self, t_e_ns: int, result: UpdateResult) -> None:
        """Feed the update's LiDAR-only orientation to the IMU time offset check; every
        ``TIME_OFFSET_JUDGE_NS`` from ``MIN_SPAN_S`` on, conclude once its estimate is precise
        (``SIGMA_DONE_S``) or significant at ``SIGMA_SIGNIFICANT_S``, or stop after
        ``MAX_SPAN_S``; never with ``conclude_time_offset`` off."""
        chk = self._offset_check
        assert chk is not None
        step = result.lidar_step
        assert step is not None
        chk.add_scan(t_e_ns, result.lidar_from.R @ so3.exp(step[3:6].copy()),
                     result.lidar_from.p + step[:3],
                     self._lidar_rotation_sd(result) if self._scale_open else np.nan)
        span = chk.span_s
        if span < MIN_SPAN_S or t_e_ns - self._offset_judged_ns < TIME_OFFSET_JUDGE_NS:
            return
        if not self.conclude_time_offset or self._gross_open:
            return  # the fine checks wait for the gross one
        self._offset_judged_ns = t_e_ns
        translation_due = self._translation_open and (
            t_e_ns - self._translation_judged_ns >= TRANSLATION_JUDGE_NS or span >= MAX_SPAN_S)
        if not (self._offset_open or self._rotation_open or self._scale_open
                or translation_due):
            return  # only the lever arm check is open, and it estimates every 10 s
        motion = chk.motion_samples()  # the checks' data, gathered once
        data = _rotation_data(motion)
        if self._offset_open:
            est = None if data is None else estimate_offset(*data, span)
            if (est is not None and est.conclusive) or span >= MAX_SPAN_S:
                # unsettled at MAX_SPAN_S: too little change of the rotation rate, or noise
                self._conclude_time_offset(est, span)
        if self._rotation_open:
            rot = self._rotation_from(data, span)
            if rot is not None:  # zero stays zero with the prior at 0
                self._rotation_M = error_second_moment(  # the estimate sees part of it
                    np.radians(self.cfg.sensor.extrinsic_rotation_sigma_deg),
                    rot.rotvec_rad / SEEN_SHARE, rot.cov_rad2 / SEEN_SHARE**2)
            if (rot is not None and rot.conclusive) or span >= MAX_SPAN_S:
                # unsettled at MAX_SPAN_S: too little rotation about two axes, or noise
                self._conclude_rotation(rot, span, last=span >= MAX_SPAN_S)
        if self._scale_open:
            sc = self._scale_from(data, span)
            if (sc is not None and sc.conclusive) or span >= MAX_SPAN_S:
                self._conclude_scale(sc, span)
        if translation_due:
            self._translation_judged_ns = t_e_ns
            tr = self._translation_from(motion, span)
            if tr is not None:
                self._translation_M = error_second_moment(
                    self.cfg.sensor.extrinsic_translation_sigma_m, tr.horizontal_m,
                    tr.horizontal_cov_m2)
            if (tr is not None and tr.conclusive) or span >= MAX_SPAN_S:
                self._conclude_translation(tr, span)
        if not (self._offset_open or self._rotation_open or self._translation_open
                or self._scale_open):
            self._offset_check = None

    def _translation_from(self, data: tuple | None,
                          span_s: float) -> TranslationEstimate | None:
        """The translation check's estimate from ``TimeOffsetCheck.motion_samples``, the IMU's
        stamps corrected by the time offset concluded on, the filter's gravity."""
        if data is None:
            return None
        return estimate_translation(*data, self._state.g, self._offset_found_s, span_s)

    def _conclude_translation(self, est: TranslationEstimate | None, span_s: float) -> None:
        """Close the translation check on ``est``: its conclusion (said, not warned about), or
        unsettled (:attr:`extrinsic_translation_unsettled`)."""
        self._translation_open = False
        if est is None or not est.conclusive:
            if self.conclude_time_offset:
                self.extrinsic_translation_unsettled = UnsettledCheck(
                    span_s, est, gave_up=span_s >= MAX_SPAN_S)
            return
        self.extrinsic_translation = est

    def _conclude_rotation(self, est: RotationEstimate | None, span_s: float, *,
                           last: bool = False) -> None:
        """Close the rotation check on ``est`` (over ``span_s`` of updates): its conclusion,
        warned about when significant, or unsettled (:attr:`extrinsic_rotation_unsettled`).
        ``last``: the check's last look (``MAX_SPAN_S`` or the end of the data), where a
        significant estimate concludes with a larger deviation
        (``RotationEstimate.conclusive_at_last``: ``run_bag`` weighs the value it finds by its
        noise, so an imprecise one is not applied whole)."""
        self._rotation_open = False
        if est is None or not (est.conclusive_at_last if last else est.conclusive):
            if self.conclude_time_offset:  # not in run_bag's passes, which read the estimate
                self.extrinsic_rotation_unsettled = UnsettledCheck(
                    span_s, est, gave_up=span_s >= MAX_SPAN_S)
            return
        self.extrinsic_rotation = est
        if est.significant and self.warn_extrinsic_rotation:
            warnings.warn(f"the LiDAR-IMU rotation in sensor.T_imu_lidar disagrees with the "
                          f"data: against the rotation the LiDAR alone registers over "
                          f"{est.span_s:.0f} s, the gyro's axes are turned at least "
                          f"{np.degrees(est.angle_rad):.2f} deg (+-"
                          f"{np.degrees(est.sigma_rad):.2f}) about {est.axis_text()} (this "
                          "estimate sees about two thirds of it): check the extrinsic's "
                          "rotation (adalio run finds and applies it itself)", stacklevel=3)

    def _conclude_time_offset(self, est: TimeOffsetEstimate | None, span_s: float) -> None:
        """Close the IMU time offset check on ``est`` (over ``span_s`` of updates): its
        conclusion, warned about when significant, or unsettled (:attr:`time_offset_unsettled`)."""
        self._offset_open = False
        if est is None or not est.conclusive:
            if self.conclude_time_offset:
                self.time_offset_unsettled = UnsettledCheck(
                    span_s, est, gave_up=span_s >= MAX_SPAN_S)
            return
        self.time_offset = est
        if est.significant and self.warn_time_offset:
            late = "late" if est.offset_s > 0 else "early"
            warnings.warn(f"the gyro's timing disagrees with the LiDAR's: against the rotation "
                          f"the LiDAR alone registers over {est.span_s:.0f} s, the IMU's stamps "
                          f"run at least {abs(est.offset_s) * 1e3:.1f} ms "
                          f"(+-{est.sigma_s * 1e3:.1f}) {late} beyond sensor.imu_time_offset_s "
                          f"({self.cfg.sensor.imu_time_offset_s:g} s) (this estimate sees about "
                          "half of an offset): move sensor.imu_time_offset_s by it and run "
                          "again until this warning stops (adalio run does so itself; the bag "
                          "Sequencer applies the setting, Odometry.add_imu takes stamps as "
                          "they are)",
                          stacklevel=3)

    def _set_gap_model(self, t_ns: np.ndarray) -> None:
        """Nominal IMU period from the initialization samples, and the gap threshold."""
        dt = np.diff(t_ns)
        period_s = float(np.median(dt[dt > 0])) * 1e-9 if np.any(dt > 0) else np.inf
        self._imu_period_s = period_s
        self._gap_s = self.cfg.imu.gap_periods * period_s
        self._q_gap = imu.gap_noise(self.cfg.imu, self._q_diag, period_s)

    def _find_gap(self, imu_tau: np.ndarray, tau_end: float, t_ref: int) -> None:
        """Record (and warn once about, or refuse beyond imu.max_gap_s) an IMU gap in this scan."""
        tail = tau_end > imu_tau[-1]
        edges = np.append(imu_tau, tau_end) if tail else imu_tau
        lengths = np.diff(edges)
        hit = np.flatnonzero((lengths > self._gap_s) & (edges[1:] > 0.0))
        if hit.size == 0:
            self._last_gap = None
            return
        k = int(hit[np.argmax(lengths[hit])])
        start_ns = t_ref + round(edges[k] * 1e9)
        length_s = float(lengths[k])
        ongoing = tail and k == len(edges) - 2  # full length known once the IMU resumes
        self._last_gap = (start_ns, length_s)
        if length_s > self.cfg.imu.max_gap_s:
            raise InputError(f"IMU gap of {'at least ' if ongoing else ''}{length_s:.2f} s after "
                             f"t = {start_ns * 1e-9:.3f} s is longer than imu.max_gap_s "
                             f"({self.cfg.imu.max_gap_s:g} s): the motion model cannot bridge "
                             "it; split the bag there or raise imu.max_gap_s")
        if not ongoing and self._warned_gap_ns != start_ns:
            self._warned_gap_ns = start_ns
            import warnings

            warnings.warn(f"IMU gap of {length_s:.2f} s after t = {start_ns * 1e-9:.3f} s: "
                          "bridged with a constant-velocity motion model, the LiDAR carries "
                          "the pose (scans.csv column imu_gap)", stacklevel=3)

    def _lidar_gap(self, t_prev_ns: int, t_e_ns: int) -> float:
        """The LiDAR time missing before this scan (s; 0 = none), recorded and warned about
        (the first gap; the others are counted in ``lidar_gaps``).

        A gap is an interval between two tracked scans' ends longer than 1.5 nominal periods
        (at least one sweep missing), the nominal period being the median of the last
        :data:`SCAN_PERIOD_WINDOW` intervals that were not gaps (before three of them, the scan's
        own span). The missing time is the interval less one period. Across it the IMU alone
        carried the state, so the prediction the scan corrects may be decimetres off
        (``filter.gate_sigmas`` lets the update see it)."""
        interval = t_e_ns - t_prev_ns
        seen = self._scan_intervals_ns
        period = float(np.median(seen)) if len(seen) >= 3 else self._span_s * 1e9
        if not period > 0 or interval <= LIDAR_GAP_PERIODS * period:
            seen.append(interval)
            del seen[:-SCAN_PERIOD_WINDOW]
            return 0.0
        missing_s = (interval - period) * 1e-9
        sigma_m = float(np.sqrt(np.linalg.eigvalsh(self._world_covariance()[:3, :3])[-1]))
        self.lidar_gaps.append((t_prev_ns, missing_s, sigma_m))
        if len(self.lidar_gaps) == 1:
            warnings.warn(f"no scan for {missing_s:.2f} s after t = {t_prev_ns * 1e-9:.3f} s (a "
                          "LiDAR gap): the IMU alone carried the pose across it, the position "
                          f"sigma grew to {sigma_m:.2g} m (scans.csv column lidar_gap; further "
                          "gaps are counted)", stacklevel=4)
        return missing_s

    @property
    def had_points(self) -> bool:
        """A scan with points left after preprocessing has reached the initialization."""
        return self._t_first_scan_ns is not None

    @property
    def init_blocked_by_scans(self) -> bool:
        """The moving start could not register enough scans for a fit because they had too few
        points once downsampled (the scans, not the IMU, kept the filter from starting)."""
        return self._moving is not None and self._moving.starved

    def init_failure(self) -> str:
        """Why the filter has not initialized yet (for the error of a run with no pose)."""
        cfg = self.cfg.imu
        parts = []
        if self.rest_refuted is not None:
            parts.append("the rig moved from the start: the IMU rested by its test (a constant "
                         "velocity looks like rest to it) while the LiDAR registered "
                         + self.rest_refuted.describe() + ", so no static start")
        elif not self.had_points:
            pass  # said below: no scan with points
        elif self._closest_still is None:
            parts.append(f"no scan had {cfg.init_window_s:g} s of IMU data before it")
        else:
            parts.append("no still window (closest: " + self._closest_still.describe() + ")")
        if not self.had_points:
            parts.append("no scan with points arrived")
        elif self._moving is not None:
            waited_s = (self._moving.last_t_ns - self._t_first_scan_ns) * 1e-9
            if waited_s < cfg.init_timeout_s:
                parts.append(f"the scans end {waited_s:.1f} s after the first one, before "
                             f"imu.init_timeout_s ({cfg.init_timeout_s:g} s) allows a moving start")
            else:
                parts.append(f"moving start not possible: {self._moving.failure}")
        return "; ".join(parts)

    def _propagate_and_undistort(self, pts: np.ndarray, t_pts: np.ndarray,
                                 t_e_ns: int) -> np.ndarray:
        """Forward propagation to the scan end with pose records, then undistortion (§5)."""
        b = self._buf
        n_use = int(np.searchsorted(b.t_ns, t_e_ns, side="right"))
        # the first sample after the scan end too, when it is in: the last interval's mid-point
        # input, not the rate of the interval before held over it (a rotation-scale bias of
        # 0.6 % at 100 Hz, README "Other IMU rates"); it stays in the buffer for the next scan
        n_pass = min(n_use + 1, b.t_ns.size)
        t_prev, gyro_prev, acc_prev = self._prev_sample
        t_ref = self._t_state_ns
        imu_tau = np.empty(n_pass + 1)
        imu_tau[0] = (t_prev - t_ref) * 1e-9
        imu_tau[1:] = (b.t_ns[:n_pass] - t_ref) * 1e-9
        gyro = np.vstack([gyro_prev[None], b.gyro[:n_pass]])
        acc = np.vstack([acc_prev[None], b.accel[:n_pass]]) * self._accel_scale
        tau_end = max((t_e_ns - t_ref) * 1e-9, 0.0)
        self._find_gap(imu_tau[:n_use + 1], tau_end, t_ref)  # on the scan's own samples
        P = np.hstack([m for m in (self._P, self._P_report, self._P_blind) if m is not None])
        self._state, P, rec = imu.propagate(self._state, P, imu_tau, gyro, acc, 0.0, tau_end,
                                            self._q_diag, self.cfg.imu.noise_discretization,
                                            self._gap_s, self._q_gap)
        self._P = P[:, :DIM].copy()
        if self._P_report is not None:  # the same propagation, along the same state
            self._P_report = P[:, DIM:2 * DIM].copy()
        if self._P_blind is not None:
            self._P_blind = P[:, 2 * DIM:].copy()
        if n_use:
            self._keep_rest_samples(b.t_ns[:n_use], b.gyro[:n_use],
                                    b.accel[:n_use] * self._accel_scale)
            self._track_noise(b.t_ns[:n_use], b.gyro[:n_use], b.accel[:n_use] * self._accel_scale)
            self._prev_sample = (int(b.t_ns[n_use - 1]), b.gyro[n_use - 1].copy(),
                                 b.accel[n_use - 1].copy())
            self._buf = _ImuBuffer(b.t_ns[n_use:], b.gyro[n_use:], b.accel[n_use:])
        self._t_state_ns = max(t_e_ns, t_ref)
        s = self._state
        return imu.undistort(pts, (t_pts - t_ref) * 1e-9, rec, s.R, s.p, s.R_LI, s.t_LI)

    def _track_noise(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """imu.track_noise_ratio: after each scan, measure the white-noise densities over the
        IMU samples of the last ``TRACK_NOISE_WINDOW_S`` (:func:`imu.moving_noise`); a sensor's
        density more than the ratio times the one the filter uses becomes the filter's from here
        on (its process noise, the gap model's and the undistortion sigma's gyro density),
        recorded in :attr:`noise_raises`. Once a sensor has been raised, a later window raises
        it again wherever it shows it noisier beyond doubt (the still start's chi-square rule,
        :func:`imu.measured_noise_config`), so that the density follows the shaking up instead
        of stopping at the first window that crossed the ratio. A scan with an IMU gap starts
        the window again (a gap's second differences are no noise)."""
        ratio = self.cfg.imu.track_noise_ratio
        if not ratio > 0 or self.cfg.imu.noise_source == "config":
            return
        if self._last_gap is not None:
            self._track_imu = _ImuBuffer(t_ns[:0], gyro[:0], accel[:0])
            return
        window_ns = round(TRACK_NOISE_WINDOW_S * 1e9)
        b = self._track_imu = self._track_imu.last(t_ns, gyro, accel, window_ns)
        if b.t_ns.size < 2 or b.t_ns[-1] - b.t_ns[0] < window_ns:
            return
        measured = imu.moving_noise(b.t_ns, b.gyro, b.accel)
        if measured is None:
            return
        used = self._noise_used
        now = imu.measured_noise_config(used, measured)
        sure = imu.measured_noise_config(used, measured, only_if_noisier=True)
        # a sensor's first raise needs the ratio (a clean IMU's windows never reach it); once it
        # has shown itself noisier than the start, the start's chi-square rule follows it up
        first = max(ratio * ratio, 1.0)  # in variance
        up_g = (sure.gyro_cov > used.gyro_cov if self._noise_shown[0]
                else now.gyro_cov > first * used.gyro_cov)
        up_a = (sure.accel_cov > used.accel_cov if self._noise_shown[1]
                else now.accel_cov > first * used.accel_cov)
        if not (up_g or up_a):
            return
        self._noise_shown = (self._noise_shown[0] or up_g, self._noise_shown[1] or up_a)
        used = dataclasses.replace(used, gyro_cov=now.gyro_cov if up_g else used.gyro_cov,
                                   accel_cov=now.accel_cov if up_a else used.accel_cov)
        self._noise_used = used
        self._q_diag = imu.process_noise(used)
        self._q_gap = imu.gap_noise(self.cfg.imu, self._q_diag, self._imu_period_s)
        if up_g:
            self._q_deskew = float(measured.gyro_noise_rad_s_sqrt_hz) ** 2
        start = self._noise_start or self.cfg.imu
        self.noise_raises.append((int(b.t_ns[-1]), float(np.sqrt(used.gyro_cov / start.gyro_cov)),
                                  float(np.sqrt(used.accel_cov / start.accel_cov))))

    def _keep_rest_samples(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Append samples to the rest window and drop those older than ``imu.init_window_s``."""
        self._rest_imu = self._rest_imu.last(t_ns, gyro, accel,
                                             round(self.cfg.imu.init_window_s * 1e9))

    def _rest_update(self, t_e_ns: int) -> bool:
        """imu.zero_velocity_update: if the IMU rested over the last ``imu.init_window_s``
        before the scan end, take a zero velocity there as a measurement (state.
        ``rest_velocity_update``), unless the filter's velocity refutes rest against the
        discounted covariance's spread (a cruise at constant velocity reads as rest to an IMU).
        The discounted covariance takes the same information: rest is real information, not a
        plane's. The backfill's reversed pass skips that gate where the forward filter
        established rest (``_rested_mirrored_ns``): there the velocity it carried back through
        the scans it re-registered is what is in doubt, not the rest. True if taken."""
        cfg = self.cfg.imu
        r = self._rest_imu
        window = imu.stillness_window(r.t_ns, t_e_ns, cfg.init_window_s)
        if window is None or r.t_ns[-1] < t_e_ns - round(imu.MAX_REST_LAG_S * 1e9):
            return False
        test = imu.stillness_test(r.t_ns[window], r.gyro[window], r.accel[window], cfg)
        if not test.still:
            return False
        var_v = (cfg.still_accel_floor_m_s2 * cfg.still_block_s) ** 2
        # the gate asks the discounted covariance (the sigmas'): a filter sure of a velocity
        # that only faked information supports (a drift the rows cannot see) must not refuse
        # the rest that would correct it
        # the backfill's reversed pass, where the forward filter established rest: its own
        # velocity, carried back through what it re-registered, must not refuse it
        rested = any(lo < t_e_ns <= hi for lo, hi in self._rested_mirrored_ns)
        out = rest_velocity_update(self._P, self._state.v, var_v,
                                   np.inf if rested else self._rest_gate, self._discounted_P)
        if out is None:
            return False
        dx, self._P, _ = out
        self._state = self._state.boxplus(dx)
        if self._P_report is not None:
            self._P_report = rest_velocity_covariance(self._P_report, var_v)
        if self._P_blind is not None:
            self._P_blind = rest_velocity_covariance(self._P_blind, var_v)
        self.n_rest_updates += 1
        if self._held_scans:  # a backfill is pending: where its reversed pass may take rest
            self._add_rested(int(r.t_ns[window][0]), t_e_ns)
        return True

    def _add_rested(self, a_ns: int, b_ns: int) -> None:
        """Record ``[a_ns, b_ns)`` as rested (``_rested_ns``), merged with the last span."""
        spans = self._rested_ns
        if spans and a_ns <= spans[-1][1]:
            spans[-1] = (spans[-1][0], max(spans[-1][1], b_ns))
        else:
            spans.append((a_ns, b_ns))

    def _refine(self, pts_e, down, assoc, leaf_m, params, surface, after_gap):
        """AdaLIO+ (degeneracy.py §3-4): halve the leaf while the translation information is weak
        and within the point budget, then restrict the update to observable pose directions.
        Returns (down, assoc, leaf_m, projector, smallest restoring ratio or NaN)."""
        ada = self.cfg.adaptive
        x = self._state
        assoc_cell = min(self._map_cell(params.voxel_size_m), self._finest_cell_m)

        def probe(a: _Association) -> Localizability:
            a.measure(x, True)
            return localizability(a.H[:, :6], self.cfg.filter.laser_point_cov, a.points_body(x))

        loc = probe(assoc)
        while loc.translation_ratio < ada.min_eigen_ratio and leaf_m / 2 >= ada.min_voxel_size_m:
            finer, voxel_of_point = voxel_downsample_with_index(pts_e, leaf_m / 2)
            if finer.shape[0] > ada.point_budget:
                break
            leaf_m, down = leaf_m / 2, finer
            assoc = _Association(down, self._ivox, self.cfg, params.search_radius_m,
                                 params.plane_margin_m, assoc_cell,
                                 self._local_planes(surface, down, voxel_of_point),
                                 self._prior_pose_cov, after_gap)
            loc = probe(assoc)
        if ada.probe_directions > 0 and assoc.H.shape[0]:
            dirs = weak_directions(loc, ada.probe_directions, ada.probe_step_m)
            rho = restoring_ratios(assoc, x, dirs)
            projector = consistent_projector(loc, ada.observable_eigen_ratio, dirs, rho,
                                             ada.min_restoring_ratio, not ada.hold_horizontal,
                                             self._up_world(x))
            return down, assoc, leaf_m, projector, float(rho.min())
        projector = observable_projector(loc, ada.observable_eigen_ratio, not ada.hold_horizontal,
                                         self._up_world(x))
        return down, assoc, leaf_m, projector, float("nan")

    def _local_planes(self, surface: LocalSurface | None, down: np.ndarray,
                      voxel_of_point: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The scan's own plane at each downsampled point (filter.local_surface_check), or
        None without a surface."""
        if surface is None:
            return None
        return surface.normals(down, voxel_of_point, self.cfg.filter.local_surface_max_patch_m)

    def _map_cell(self, voxel_size_m: float) -> float:
        leaf = self.cfg.map.map_leaf_m
        return min(leaf, voxel_size_m) if self.cfg.map.cell_follows_voxel else leaf

    def _accumulate(self, stage_ms: dict[str, float]) -> None:
        for k, v in stage_ms.items():
            self.stage_ms_total[k] = self.stage_ms_total.get(k, 0.0) + v

    @property
    def _keeps_discounted_P(self) -> bool:
        """The discounted covariance is kept for the reported sigmas or the robust kernel."""
        return (self.cfg.filter.sigmas_discount_normal_noise
                or robust_kernel_name(self.cfg) != "none")

    @property
    def _keeps_blind_P(self) -> bool:
        """The height-blind twin is kept for the reported sigmas."""
        f = self.cfg.filter
        return f.sigmas_height_blind and f.sigmas_discount_normal_noise

    @property
    def _discounted_P(self) -> np.ndarray:
        return self._P if self._P_report is None else self._P_report

    @property
    def _sigmas_P(self) -> np.ndarray:
        """The covariance the reported sigmas come from: the discounted covariance once it
        exists, with ``filter.sigmas_discount_normal_noise`` (its height-blind twin with
        ``filter.sigmas_height_blind``); else the filter's."""
        if self._P_blind is not None:
            return self._P_blind
        return self._discounted_P if self.cfg.filter.sigmas_discount_normal_noise else self._P

    @staticmethod
    def _after_gap(stats: ScanStats) -> bool:
        """The scan follows a LiDAR gap or bridges an IMU gap: its prediction was carried without
        the LiDAR (or without the IMU) and may be decimetres off (``filter.gate_sigmas``)."""
        return stats.lidar_gap_s > 0.0 or stats.imu_gap_s > 0.0

    @property
    def _prior_pose_cov(self) -> np.ndarray:
        """(6,6) the predicted pose covariance of the robust kernel and the gate: the discounted
        one's pose block (the filter's before the anchor)."""
        return self._discounted_P[:6, :6]

    @staticmethod
    def _up_world(x: State) -> np.ndarray:
        """The world's unit up (against the state's gravity): the world is the IMU frame at
        the start, so its z is vertical only for an IMU mounted z-up or z-down."""
        return -x.g / np.linalg.norm(x.g)

    def _update_report_covariance(self, x_pred: State, x_post: State, assoc: _Association,
                                  projector: np.ndarray | None) -> bool:
        """While it is kept (:attr:`_keeps_discounted_P`), the discounted covariance (behind the
        reported sigmas and the robust kernel) takes the scan's information less what the
        normals' noise fakes
        (:func:`normal_noise_information`), kept between nothing and the claim
        (:func:`real_information`), in the information form of the filter's final step (``P⁺ = (P⁻¹ + EᵀJE)⁻¹`` with E the pose
        block, at the same SO(3) reprojection). The filter itself is unchanged. Its
        height-blind twin (``filter.sigmas_height_blind``) takes the same information, with
        the world height marginalised out where :func:`height_blind` says the scan holds
        none. Returns whether the twin took the scan as height-blind."""
        f = self.cfg.filter
        if not self._keeps_discounted_P:
            return False
        P = self._discounted_P
        Jr = _reprojection(x_post.boxminus(x_pred))
        P = Jr @ P @ Jr.T
        P_blind = None if self._P_blind is None else Jr @ self._P_blind @ Jr.T
        H = assoc.H[:, :6]
        height_blind = False
        if H.shape[0]:
            fake = normal_noise_information(assoc.points_lidar, assoc.selected, x_post.R,
                                            x_post.R_LI, x_post.t_LI, assoc.normals,
                                            assoc.neighbours, assoc.counts, assoc.row_weights)
            claimed = H.T @ H
            if projector is not None:
                claimed = projector.T @ claimed @ projector
                fake = projector.T @ fake @ projector
            up = self._up_world(x_post)
            J, blind = real_information_and_height_blind(claimed, f.laser_point_cov * fake, up)
            J /= f.laser_point_cov
            height_blind = bool(blind and P_blind is not None)
            P = _information_update(P, J)
            if P_blind is not None:
                P_blind = _information_update(
                    P_blind, without_direction(J, height_direction(up)) if blind else J)
        self._P_report = 0.5 * (P + P.T)
        if P_blind is not None:
            self._P_blind = P_blind
        return height_blind

    def _deskew_covariance(self) -> np.ndarray:
        """The latest scan's undistortion rotation noise (``map_uncertainty.deskew_covariance``),
        zero without ``filter.sigmas_deskew_noise``. The gyro's white noise is the one the
        start measured (still window or moving start), not floored by the configured value,
        which may be a generic process noise (FAST-LIO's 0.1 in the ``dt2`` form is 0.17° per
        0.1 s sweep, 80 times the HILTI BMI085's); with ``imu.noise_source: config`` or
        nothing measured, the configured one. In the ``dt2`` form the configured value is per
        sample, so the density² is it times the nominal sample period (measured at
        initialization, as for the gaps' bias walks; the configured rate if none was)."""
        if not self.cfg.filter.sigmas_deskew_noise:
            return np.zeros((6, 6))
        q = self._q_deskew
        if q is None:
            q = float(self._q_diag[0])
            if self.cfg.imu.noise_discretization != "dt":
                period_s = self._imu_period_s
                q *= period_s if np.isfinite(period_s) else 1.0 / self.cfg.sensor.imu_rate_hz
        return deskew_covariance(q, self._span_s)

    def _world_covariance(self, extrinsic: bool = True) -> np.ndarray:
        """6x6 world covariance of the pose: the filter's (or, with
        ``filter.sigmas_discount_normal_noise``, the one behind the reported sigmas), combined
        with the map's if ``filter.map_uncertainty`` (``map_uncertainty.world_covariance``),
        plus the scan's undistortion rotation (``filter.sigmas_deskew_noise``) outside that
        combination: the gyro noise of this sweep is independent of the map's error and of the
        registration's bias, which the combination's bound is for; and, with ``extrinsic``,
        the extrinsic's own (:meth:`_extrinsic_covariance`), which the map's provenance must
        not carry (it is the same error for every scan)."""
        W = pose_covariance_world(self._state.R, self._sigmas_P)
        f = self.cfg.filter
        if f.map_uncertainty:
            W = world_covariance(W, self._W_map, f.map_error_correlated)
        W = W + self._deskew_covariance()
        return W + self._extrinsic_covariance() if extrinsic else W

    def _extrinsic_covariance(self) -> np.ndarray:
        """The world covariance an error of ``T_imu_lidar`` puts into the pose against the
        first one (:mod:`adalio.lio.extrinsic_sigma`): ``sensor.extrinsic_rotation_sigma_deg``
        and ``sensor.extrinsic_translation_sigma_m`` as the priors, narrowed by the rotation
        and the lever arm checks' latest estimates (the latter across the rig's vertical only);
        ``sensor.gyro_axes_sigma_deg`` added to the rotation's, never narrowed.
        Zero before the first pose and with both priors at 0."""
        return self._extrinsic_covariance_at(self._state.R, self._state.p)

    def _extrinsic_covariance_at(self, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        """:meth:`_extrinsic_covariance` of poses of attitude ``R`` (..., 3, 3) at ``p``
        (..., 3): (..., 6, 6), zeros before the first pose."""
        anchor = self._anchor_state
        if anchor is None:
            return np.zeros(np.shape(p)[:-1] + (6, 6))
        return (extrinsic_rotation_covariance(self._rotation_M + self._gyro_axes_M, anchor.R,
                                              R, p - anchor.p)
                + extrinsic_translation_covariance(self._translation_M, anchor.R, R))

    def extrinsic_variance(self, T_world_imu: np.ndarray) -> np.ndarray:
        """(N, 6) the diagonal of the world covariance an error of ``T_imu_lidar`` puts into
        poses ``T_world_imu`` (N, 4, 4) against the first one, by the extrinsic checks'
        estimates as they stand now (:meth:`_extrinsic_covariance`): position variances (m²),
        then those of small rotations about the world axes (rad²). The error is the same for
        every scan, so what the checks know at a run's end holds for the scans before it too:
        ``run_bag`` widens each ``scans.csv`` row's sigmas by what this adds over the row's own
        ``ScanStats.var_extrinsic_world``. Zeros before the first pose."""
        T = np.asarray(T_world_imu, dtype=np.float64).reshape(-1, 4, 4)
        W = self._extrinsic_covariance_at(T[:, :3, :3], T[:, :3, 3])
        return np.clip(np.diagonal(W, axis1=-2, axis2=-1), 0.0, None)

    def _emit(self, stats: ScanStats, stage_ms: dict[str, float], t_start: float,
              p_world: np.ndarray, W_world: np.ndarray | None = None) -> Estimate:
        """The scan's estimate; ``W_world``: :meth:`_world_covariance` if already computed."""
        self._accumulate(stage_ms)
        self.n_scans += 1
        stats.stage_ms = {k: stage_ms.get(k, 0.0) for k in STAGES}
        stats.wall_ms = (time.perf_counter() - t_start) * 1e3
        s = self._state
        stats.sigma_p_world_m, stats.sigma_rot_world_deg = sigmas_from_world_covariance(
            self._world_covariance() if W_world is None else W_world)
        return Estimate(t_ns=stats.t_ns, T_world_imu=s.T_world_imu(), velocity_world_m_s=s.v.copy(),
                        gyro_bias_rad_s=s.b_g.copy(), accel_bias_m_s2=s.b_a.copy(),
                        gravity_world_m_s2=s.g.copy(), cov_diag=np.diag(self._P).copy(),
                        stats=stats, points_world=p_world)
