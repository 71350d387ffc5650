"""``run_bag``: bag → sequencer → :class:`adalio.lio.Odometry` → writers.

Writes into ``out_dir``: ``trajectory.tum`` (IMU pose in the world frame, stamped at each scan
end, rows flushed as produced), ``scans.csv`` (one row per estimated scan; the backfill's rows
for the scans read before the initialization come later, and both files are sorted by time at
the end), ``map.ply`` or ``map.pcd`` (world-frame map, metres) and ``config.yaml`` (the
effective config, with the extrinsic actually used). The map and config are also written when
the run stops early (Ctrl-C, a damaged bag), so partial outputs stay valid.
"""

from __future__ import annotations

import contextlib
import copy
import signal
import statistics
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Self

import numpy as np
from scipy.spatial.transform import Rotation

from adalio.config import RANGES, Config, validate_sensitivity, validate_transform
from adalio.errors import AdalioError, BagError, ConfigError, InputError
from adalio.io.bag import Bag, chain_transform
from adalio.io.sequencer import IMU_WINDOW_NS, Sequencer, SequencerStats
from adalio.io.writers import (
    REPORT_FILES,
    ScansCsvWriter,
    TumWriter,
    rewrite_sigmas,
    scan_sigmas,
    sort_rows_by_time,
    write_map,
)
from adalio.types import Estimate, ImuBatch

if TYPE_CHECKING:
    from adalio.lio import Odometry

DEFAULT_SIGMA_WARN_M = 0.10
"""``run --sigma-warn-m``: a position standard deviation above this (m) is named in the summary."""


STRAY_NOTE_SHARE = 0.01
"""With ``preprocess.drop_stray_returns`` off, the run summary notes the stray returns kept when
they are at least this share of the points read (README, *Stray returns*): half the default
``preprocess.stray_drop_share``, where sweeps of ghosts on 2 % of the returns keep theirs (their
shaft walks 17-33 cm, 4-7 cm with the share at 1 %); a real construction site's sweep 1.35 %."""


@dataclass
class TimeOffsetCalibration:
    """How ``run_bag`` found the IMU time offset before restarting (``RunResult``)."""

    offset_s: float
    """The ``sensor.imu_time_offset_s`` the run restarted with."""
    configured_s: float
    """The one the configuration gave."""
    detected_s: float
    """The first run's estimate of the offset left (it sees about half of an offset)."""
    residual_s: float
    """The least offset a pass left (about zero); ``offset_s`` is one more step of the search
    from there."""
    passes: list[tuple[float, float]]
    """(offset tried s, offset left s) of each pass over the first scans."""
    n_scans: int
    """Scans each pass read (the first run's, up to the check's conclusion)."""


@dataclass
class RotationCalibration:
    """How ``run_bag`` found the LiDAR-IMU rotation before restarting (``RunResult``)."""

    correction_rad: np.ndarray
    """(3,) the rotation vector ``θ`` applied on the left of the configured rotation
    (``R ← Exp(θ) R``, IMU frame): the passes' value (``found_rad``) weighed against how well
    it is known and ``sensor.extrinsic_rotation_sigma_deg`` (the posterior mean,
    :func:`adalio.lio.extrinsic_sigma.posterior`; ``found_rad`` itself with a configured 0)."""
    T_imu_lidar: np.ndarray
    """(4,4) the extrinsic the run restarted with."""
    detected_rad: np.ndarray
    """The first run's estimate of the rotation left (it sees about two thirds of it)."""
    residual_rad: float
    """The least rotation a pass left (rad); ``correction_rad`` is one more step of the search
    from there."""
    passes: list[tuple[np.ndarray, np.ndarray]]
    """(correction tried, rotation left) rotation vectors (rad) of each pass."""
    n_scans: int
    """Scans each pass read (the first run's, up to the check's conclusion)."""
    sigma_rad: float = 0.0
    """The largest standard deviation (rad) of the value found (``found_rad``), which the
    restarted run's ``sensor.extrinsic_rotation_sigma_deg`` is at least: the rotation left after
    ``correction_rad`` was up to 2.8 times it where the first estimate concluded on a noisy
    excursion (session 63; the restarted sigmas still held). Not the posterior's own
    covariance, which understates it where the rotation is comparable to the noise (a widened
    prior is an estimate too)."""
    found_rad: np.ndarray | None = None
    """(3,) the rotation vector the passes found (before it was weighed, ``correction_rad``)."""

    @property
    def angle_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(self.correction_rad)))


@dataclass
class GyroScaleCalibration:
    """How ``run_bag`` found the gyro's scale error before restarting (``RunResult``)."""

    correction: np.ndarray
    """(6,) the symmetric correction's entries xx, xy, xz, yy, yz, zz (fractions) applied on
    the right of the configured sensitivity (:func:`adalio.lio.gyro_scale.
    corrected_sensitivity`)."""
    gyro_sensitivity: np.ndarray
    """(3,3) the ``sensor.gyro_sensitivity`` the run restarted with."""
    detected: np.ndarray
    """(6,) the estimate that started the search (it sees part of the error)."""
    residual: float
    """The least largest entry a pass left; ``correction`` is one more step from there."""
    passes: list[tuple[np.ndarray, np.ndarray]]
    """(correction tried, scale error left) of each pass."""
    n_scans: int

    @property
    def largest_pct(self) -> float:
        """The correction's largest entry, in percent."""
        return float(100 * np.abs(self.correction).max())

    def text(self) -> str:
        """The correction as :func:`adalio.lio.gyro_scale.scale_text` says it."""
        from adalio.lio.gyro_scale import scale_text

        return scale_text(self.correction)


@dataclass
class RunResult:
    """What :func:`run_bag` produced."""

    out_dir: Path
    trajectory_path: Path
    scans_csv_path: Path
    map_path: Path
    config_path: Path
    n_scans: int
    n_degenerate: int
    wall_s: float
    ms_per_scan_median: float
    stage_ms: dict[str, float]
    interrupted: bool
    degenerate_ranges_s: list[tuple[float, float]] = field(default_factory=list)
    """(start, end) seconds since the first estimated scan of consecutive degenerate scans."""
    n_held: int = 0
    """adaptive+: scans with at least one pose direction held at the IMU prediction."""
    held_ranges_s: list[tuple[float, float]] = field(default_factory=list)
    """(start, end) seconds of consecutive scans with a held direction, like the above."""
    lidar_topic: str = ""
    imu_topic: str = ""
    extrinsic_source: str = ""
    time_spec: str = ""
    sequencer: SequencerStats | None = None
    n_scans_in: int = 0
    """Scans handed to the estimator (including those consumed by initialization)."""
    n_height_blind: int = 0
    """filter.sigmas_height_blind: scans whose height the sigmas leave to the IMU (scans.csv
    height_blind)."""
    height_blind_ranges_s: list[tuple[float, float]] = field(default_factory=list)
    """(start, end) seconds of consecutive height-blind scans."""
    sigma_warn_m: float = DEFAULT_SIGMA_WARN_M
    sigma_warn_ranges_s: list[tuple[float, float]] = field(default_factory=list)
    """(start, end) seconds of consecutive scans whose largest position standard deviation
    (scans.csv sigma_x/y/z_m) exceeds ``sigma_warn_m``."""
    n_sigma_warn: int = 0
    sigma_warn_extrinsic_m: float = 0.0
    """Over the scans beyond ``sigma_warn_m``, the largest position standard deviation (m)
    that the LiDAR-IMU extrinsic's own uncertainty alone gives them
    (``sensor.extrinsic_rotation_sigma_deg``, ``sensor.extrinsic_translation_sigma_m``): how
    much of the warning a better known extrinsic would take away."""
    imu_saturation: list[tuple[Any, float]] = field(default_factory=list)
    """(:class:`adalio.io.imu_range.Saturation`, its first sample's time in s since the first
    estimated scan) of each IMU axis that read the end of its range (``Sequencer.range_monitor``)."""
    lidar_gaps: list[tuple[float, float, float]] = field(default_factory=list)
    """(start s since the first estimated scan, missing time s, the largest position sigma
    predicted at the scan after it, m) of each LiDAR gap (``Odometry.lidar_gaps``; scans.csv
    lidar_gap)."""
    noise_raises: list[tuple[float, float, float]] = field(default_factory=list)
    """(s since the first estimated scan, gyro density / the start's, accelerometer density /
    the start's) of each raise of the filter's IMU white-noise densities while the run went on
    (imu.track_noise_ratio, ``Odometry.noise_raises``): the IMU noisier than at the start."""
    init_report: Any = None
    """:class:`adalio.types.InitReport` of the estimator (None if it never initialized)."""
    local_surface_rows: tuple[int, int] = (0, 0)
    """filter.local_surface_check: (rows dropped, rows matched or dropped) over the run."""
    moving_points: tuple[int, int, int] = (0, 0, 0)
    """map.remove_moving: (sweep points kept out of the update and the map, map points and
    points waiting to enter it seen through, scans with points kept out) over the rows written:
    the sums of scans.csv's ``n_moving`` and ``n_seen_through`` and its rows with ``n_moving``
    above 0, the backfilled rows included (not the backfill's re-registration of scans the
    forward run had posed, whose rows it does not write)."""
    stray_points: tuple[int, int] = (0, 0)
    """(stray returns, points read) over the rows written: the sums of scans.csv's ``n_stray``
    and ``n_raw`` (``adalio.lio.stray``; no stray return is counted without rings)."""
    stray_dropped: bool = False
    """preprocess.drop_stray_returns: the stray returns were dropped, not only counted."""
    stray_drops: tuple[int, int, int] = (0, 0, 0)
    """(points dropped as stray, scans that dropped them, stray returns kept in the other
    scans) over the rows written: the sum of scans.csv's ``n_stray_dropped``, its rows above 0,
    and the sum of ``n_stray`` in its rows at 0. A scan drops them with
    preprocess.drop_stray_returns, or where they are more than preprocess.stray_drop_share of
    its points."""
    stray_dropped_ranges_s: list[tuple[float, float]] = field(default_factory=list)
    """(start, end) seconds of consecutive scans that dropped their stray returns."""
    stray_drop_share: float = 1.0
    """preprocess.stray_drop_share of the run."""
    map_left_out: tuple[int, int] = (0, 0)
    """(map points left out of the map written, map points): those whose cell fewer than
    ``output.map_min_returns`` of the scans' points reached (``Odometry.map_cloud``)."""
    map_min_returns: int = 1
    """output.map_min_returns of the run."""
    dense_map_path: Path | None = None
    """``map_dense.ply`` / ``.pcd`` (output.dense_map_voxel_m; None: not written)."""
    dense_map_voxel_m: float = 0.0
    """output.dense_map_voxel_m of the run."""
    dense_map_points: tuple[int, int] = (0, 0)
    """(dense map points written, points left out of it: none of the map written out within
    map.map_leaf_m of them; ``Odometry.dense_map_cloud``)."""
    moving_body: bool = False
    """map.moving_body_m > 0: the points kept out include those on the same body as a point in
    free space or one seen through (``lio/moving.py``)."""
    time_offset: Any = None
    """:class:`adalio.lio.time_offset.TimeOffsetEstimate` the IMU time offset check concluded
    on in this run (left after ``sensor.imu_time_offset_s``), or None."""
    stopped_for_time_offset: bool = False
    """The run stopped where the IMU time offset check concluded, for :func:`run_bag` to
    restart it (never in what ``run_bag`` returns, unless a Ctrl-C came meanwhile)."""
    time_offset_found: TimeOffsetCalibration | None = None
    """When the check found the IMU's stamps off and the run restarted: how the offset was
    found (the run's ``config.yaml`` holds it as ``sensor.imu_time_offset_s``)."""
    extrinsic_rotation: Any = None
    """:class:`adalio.lio.extrinsic_check.RotationEstimate` the LiDAR-IMU rotation check
    concluded on in this run (left after ``sensor.T_imu_lidar``'s rotation), or None."""
    stopped_for_extrinsic_rotation: bool = False
    """The run stopped where the rotation check concluded, for :func:`run_bag` to restart it."""
    extrinsic_rotation_found: RotationCalibration | None = None
    """When the check found the extrinsic's rotation off and the run restarted: how it was
    found (the run's ``config.yaml`` holds the corrected ``sensor.T_imu_lidar``)."""
    extrinsic_rotation_gross: Any = None
    """:class:`adalio.lio.extrinsic_check.GrossRotation`: the gross rotation check found the
    extrinsic's rotation too far off for the fine check, and the run stopped there for
    :func:`run_bag` to restart with it (``extrinsic_rotation_gross_found``)."""
    extrinsic_rotation_gross_found: Any = None
    """The gross rotation error the run restarted with (its ``config.yaml`` holds the corrected
    ``sensor.T_imu_lidar``; the fine check then went on from it)."""
    extrinsic_rotation_gross_refuted: tuple[Any, Any] | None = None
    """(the gross rotation the gross check found, the fine check's estimate over the same first
    scans with it corrected) where that estimate was no smaller than before the correction:
    the correction was refused and the run went on from the configured rotation
    (``run_bag``)."""
    extrinsic_rotation_gross_checked: Any = None
    """The gross rotation check's last estimate where it found no gross error (None: it could
    not estimate, or did not run: a moving start, or the rotation check off)."""
    lidar_view: Any = None
    """:class:`adalio.lio.lidar_view.LidarView`: how the LiDAR's spin axis leans from the
    vertical and whether its beams see the horizontal ahead of the lean or behind it (None: no
    filter pose)."""
    gyro_scale: Any = None
    """:class:`adalio.lio.gyro_scale.GyroScaleEstimate` the gyro scale check concluded on in
    this run (left after ``sensor.gyro_sensitivity``), or None."""
    stopped_for_gyro_scale: bool = False
    """The run stopped where the gyro scale check concluded, for :func:`run_bag` to restart
    it."""
    gyro_scale_found: GyroScaleCalibration | None = None
    """When the check found the gyro's scale factors off and the run restarted: how (the run's
    ``config.yaml`` holds the corrected ``sensor.gyro_sensitivity``)."""
    gyro_scale_unsettled: Any = None
    """The gyro scale check closed without a conclusion (``sensor.gyro_sensitivity`` used
    unchecked)."""
    gyro_scale_so_far: Any = None
    """Where the run stopped for another check while the gyro scale check was still open: its
    estimate there (:func:`run_bag` searches the scale when it is significant)."""
    time_offset_unsettled: Any = None
    """:class:`adalio.types.UnsettledCheck`: the IMU time offset check closed without a
    conclusion in this run, so ``sensor.imu_time_offset_s`` was used unchecked (None: it
    concluded, or is off)."""
    extrinsic_rotation_unsettled: Any = None
    """The same for the LiDAR-IMU rotation check (``sensor.T_imu_lidar``'s rotation)."""
    extrinsic_translation: Any = None
    """:class:`adalio.lio.lever_arm.TranslationEstimate` the LiDAR-IMU translation check
    concluded on (the correction ``sensor.T_imu_lidar``'s translation needs), or None."""
    extrinsic_translation_unsettled: Any = None
    """The same for the translation check, closed without a conclusion."""
    calibration_wall_s: float = 0.0
    """When the run restarted with a corrected time offset or rotation: the wall time before
    the restart (the first run and the passes that found the value); ``wall_s`` is the
    restarted run's."""
    compiled: bool = False
    """The run began on a cold numba cache (the first after an install or an update of adalio):
    its wall time and stage times include the one-time compilation of the kernels."""


def default_out_dir(bag_path: str | Path, root: str | Path = "runs") -> Path:
    """``runs/<bag-stem>``, or ``runs/<bag-stem>_<k>`` with the first free k."""
    stem = Path(str(bag_path).rstrip("/")).name
    for suffix in (".bag", ".mcap", ".db3"):
        stem = stem.removesuffix(suffix)
    base = Path(root) / (stem or "run")
    if not base.exists():
        return base
    k = 1
    while (base.parent / f"{base.name}_{k}").exists():
        k += 1
    return base.parent / f"{base.name}_{k}"


def resolve_extrinsic(bag: Bag, lidar_topic: str, imu_topic: str,
                      config: Config) -> tuple[np.ndarray, str]:
    """T_imu_lidar per ``sensor.extrinsic_source`` and a description of where it came from."""
    source = config.sensor.extrinsic_source
    if source == "config":
        return config.T_imu_lidar(), "config"
    edges = bag.static_transforms()
    if not edges:
        if source == "tf_static":
            raise BagError(f"sensor.extrinsic_source is tf_static but {bag.path} has no "
                           "/tf_static transforms; give --extrinsic or set it to config")
        return config.T_imu_lidar(), "config"
    imu_msg = bag.first_message(imu_topic)
    cloud_msg = bag.first_message(lidar_topic)
    imu_frame = imu_msg.header.frame_id if imu_msg is not None else ""
    lidar_frame = cloud_msg.header.frame_id if cloud_msg is not None else ""
    T = None
    if imu_frame and lidar_frame and imu_frame.lstrip("/") != lidar_frame.lstrip("/"):
        T = chain_transform(edges, imu_frame, lidar_frame)
    if T is None:
        if source == "tf_static":
            raise BagError(f"/tf_static in {bag.path} has no chain from '{imu_frame}' (IMU) to "
                           f"'{lidar_frame}' (LiDAR); give --extrinsic or set "
                           "sensor.extrinsic_source to config")
        return config.T_imu_lidar(), "config"
    try:
        T = validate_transform(T, f"/tf_static {imu_frame}<-{lidar_frame}")
    except ConfigError as exc:
        raise BagError(str(exc)) from None
    return T, f"tf_static ({imu_frame} <- {lidar_frame})"


def _extrinsic_known_late(odom: Odometry, scans_csv: Path, t_ns: list[int],
                          poses: list[np.ndarray], sigmas: list[np.ndarray],
                          var_ext: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, int]:
    """Widen the sigmas of ``scans.csv``'s rows (written in the order of ``t_ns``, before
    :func:`sort_rows_by_time`) to what the extrinsic checks know at the run's end.

    A wrong ``T_imu_lidar`` puts the same error into every scan (:mod:`adalio.lio.
    extrinsic_sigma`), but each row's share of it (``ScanStats.var_extrinsic_world``) came
    from the checks' estimates at that scan: the backfilled scans and the first ones after
    the start were written before the checks had seen much (a rotation 5° off, found 2.95° ±
    0.35 after 27 s, left 32-41 % of the scans within 3σ). Each row's variances gain what
    :meth:`Odometry.extrinsic_variance` at the end adds over the row's own share; never
    narrowed (a row's sigmas, once written, are only widened). Returns the widened sigmas (N,
    6), each row's extrinsic share of its widened position sigma (m, the larger of the two
    variances) and the rows rewritten (0: the file is as written, the first two not used)."""
    sig = np.asarray(sigmas, dtype=np.float64).reshape(-1, 6)
    row_var = np.asarray(var_ext, dtype=np.float64).reshape(-1, 6)
    end_var = odom.extrinsic_variance(np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4))
    add = np.clip(end_var - row_var, 0.0, None)
    wide = sig.copy()
    wide[:, :3] = np.sqrt(sig[:, :3] ** 2 + add[:, :3])
    wide[:, 3:] = np.degrees(np.sqrt(np.radians(sig[:, 3:]) ** 2 + add[:, 3:]))
    grown = np.flatnonzero(np.any(wide > sig * (1.0 + 1e-4), axis=1))  # NaN stays NaN
    n = rewrite_sigmas(scans_csv, np.asarray(t_ns, dtype=np.int64), wide, grown) \
        if grown.size else 0
    return wide, np.sqrt(np.max(np.maximum(row_var, end_var)[:, :3], axis=1)), n


def _flag_ranges(times_ns: list[int], flags: list[bool]) -> list[tuple[float, float]]:
    """(start, end) seconds since ``times_ns[0]`` of each run of consecutive flagged scans."""
    if not times_ns:
        return []
    t0 = times_ns[0]
    out: list[tuple[float, float]] = []
    start = None
    for i, (t, d) in enumerate(zip(times_ns, flags, strict=True)):
        if d and start is None:
            start = t
        if start is not None and (not d or i == len(flags) - 1):
            end = t if d else times_ns[i - 1]
            out.append(((start - t0) * 1e-9, (end - t0) * 1e-9))
            start = None
    return out


class GracefulStop:
    """First Ctrl-C sets ``requested`` (the run stops after the current scan, so no interrupt
    lands inside a numba kernel; ``adalio batch`` stops at its next look at the bags, so none
    lands in a library's ``__del__``, which would swallow it); a second one raises
    KeyboardInterrupt at once."""

    def __init__(self) -> None:
        self.requested = False
        self._old: Any = None

    def _handler(self, signum: int, frame: Any) -> None:
        if self.requested:
            signal.default_int_handler(signum, frame)
        self.requested = True

    def __enter__(self) -> Self:
        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._handler)
            # a Ctrl-C that an import swallowed earlier (_adalio_entry.StickyInterrupt)
            self.requested = bool(getattr(self._old, "received", False))
        return self

    def __exit__(self, *exc: object) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
            self._old = None


def progress_bar(enabled: bool, unit: str, field: str, console: Any = None) -> Any:
    """A rich progress bar over ``unit`` (scans, bags) with the task field ``field`` shown."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(TextColumn(f"[bold]{unit}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn(f"{{task.fields[{field}]}}"), TimeElapsedColumn(),
                    TextColumn("eta"), TimeRemainingColumn(), disable=not enabled,
                    transient=False, console=console)


_MEASURED_CHECKS = (
    ("imu_time_offset", "time_offset", "left", "s",
     lambda e: round(float(e.offset_s), 6), lambda e: round(float(e.sigma_s), 6)),
    ("extrinsic_rotation", "extrinsic_rotation", "left", "deg",
     lambda e: [round(float(v), 4) for v in np.degrees(e.rotvec_rad)],
     lambda e: round(float(np.degrees(e.sigma_rad)), 4)),
    ("extrinsic_translation", "extrinsic_translation", "correction", "m",
     lambda e: [round(float(v), 4) for v in e.horizontal_m], lambda e: round(e.sigma_m, 4)),
    ("gyro_scale", "gyro_scale", "left", "pct",
     lambda e: [round(float(v) * 100, 3) for v in e.s], lambda e: round(e.sigma * 100, 3)),
)
"""``config.yaml``'s ``measured:`` keys of the sensor checks: (key prefix, the odometry's
attribute, the concluded value's word, unit, the value, its sigma)."""


def _config_text(cfg: Config, odom: Any) -> str:
    """The effective config, plus what initialization measured (``measured:``, read back as
    information only)."""
    text = cfg.to_yaml()
    report = getattr(odom, "init_report", None)
    measured = report.to_dict() if report is not None else {}
    # what each sensor check concluded (left after the config's value, or the lever arm's
    # correction); then, for those that closed unsettled, after how long and at which estimate
    for name, attr, word, unit, value, sigma in _MEASURED_CHECKS:
        est = getattr(odom, attr, None)
        if est is not None:
            measured[f"{name}_{word}_{unit}"] = value(est)
            measured[f"{name}_{word}_sigma_{unit}"] = sigma(est)
    for name, attr, _, unit, value, sigma in _MEASURED_CHECKS:
        check = getattr(odom, f"{attr}_unsettled", None)
        if check is not None:  # used as configured: the check could not settle it
            measured[f"{name}_unsettled_after_s"] = round(float(check.span_s), 1)
            if check.estimate is not None:
                measured[f"{name}_unsettled_{unit}"] = value(check.estimate)
                measured[f"{name}_unsettled_sigma_{unit}"] = sigma(check.estimate)
    view = getattr(odom, "lidar_view", None)
    if view is not None:  # the spin axis's lean from the vertical, the beams' elevations
        measured["lidar_tilt_deg"] = round(view.tilt_deg, 2)
        measured["lidar_beams_deg"] = [round(view.up_deg, 2), round(view.down_deg, 2)]
    if measured:
        import yaml

        text += yaml.safe_dump({"measured": measured}, sort_keys=False,
                               default_flow_style=None)
    return text


def _no_pose_reason(odom: Any, n_in: int, lidar_topic: str, imu_topic: str, out: Path,
                    n_late: int = 0, start_s: float = 0.0,
                    bag_s: float = float("inf")) -> str:
    """One line for a run that produced no pose: what was seen and what to change.
    ``n_late``: scans the sequencer skipped as arriving after the IMU window; ``start_s``,
    ``bag_s``: where the run started in the bag, and the bag's length."""
    late = (f"; {n_late} scans of {lidar_topic} arrived more than "
            f"{IMU_WINDOW_NS * 1e-9:g} s after their IMU samples and were skipped (the bag's "
            "receive times of the clouds lag the IMU's)") if n_late else ""
    if n_in == 0 and start_s > 0 and start_s >= bag_s:
        return (f"no pose: --start-s {start_s:g} is at or beyond the end of the bag "
                f"({bag_s:.1f} s long) (partial outputs in {out})")
    if n_in == 0:
        return (f"no pose: no scan of {lidar_topic} reached the estimator{late}; check the topic "
                f"with 'adalio info' (partial outputs in {out})")
    if late and not odom.initialized:
        return (f"no pose from {n_in} scans: the estimator never initialized{late} (partial "
                f"outputs in {out})")
    if not odom.initialized and not odom.had_points:
        return (f"no pose from {n_in} scans of {lidar_topic}: every scan was empty after "
                f"preprocessing (no point within preprocess.blind_m .. max_range_m); check "
                f"those, and the points with `adalio info --sample 1` (partial outputs in {out})")
    if not odom.initialized and odom.rest_refuted is not None:
        return (f"no pose from {n_in} scans: the estimator never initialized: "
                f"{odom.init_failure()}. Start the recording with the rig at rest (a robot "
                "standing still for imu.init_window_s), or include more of it: the moving "
                f"start waits for geometry that fixes the velocity (partial outputs in {out})")
    if not odom.initialized and odom.init_blocked_by_scans:
        return (f"no pose from {n_in} scans: the estimator never initialized: "
                f"{odom.init_failure()}. Check the scans of {lidar_topic}: too few of them "
                "keep the 50 points a moving start needs to register one, once downsampled "
                "(preprocess.blind_m, max_range_m, point_filter_num, "
                "adaptive.general.voxel_size_m; `adalio info --sample 1` shows the points) "
                f"(partial outputs in {out})")
    if not odom.initialized:
        return (f"no pose from {n_in} scans: the estimator never initialized: "
                f"{odom.init_failure()}. Check {imu_topic} (rate, units, stamps); a still start "
                "needs imu.init_window_s of rest, a moving start imu.init_timeout_s of "
                f"registered scans (partial outputs in {out})")
    return (f"no pose from {n_in} scans of {lidar_topic}: every scan was empty after "
            f"preprocessing or out of order; check preprocess.blind_m / max_range_m "
            f"(partial outputs in {out})")


def remove_stale_outputs(out: Path, map_format: str, dense_map: bool = False) -> None:
    """Remove what an earlier run left in ``out`` that this one does not overwrite: the map in
    the other format, a dense map in the other format or, without ``dense_map``, in any, and a
    report (``report.md``, ``metrics.json``, its figures), which would otherwise describe the
    earlier run beside this one's files. Nothing else in the folder is touched."""
    maps = [f"{stem}.{f}" for stem in ("map", "map_dense") for f in ("ply", "pcd")
            if f != map_format or (stem == "map_dense" and not dense_map)]
    for name in maps + list(REPORT_FILES):
        if (out / name).is_file():
            (out / name).unlink()


def run_bag(bag_path: str | Path, config: Config, out_dir: str | Path, *,
            progress: bool = True, max_scans: int | None = None,
            map_format: str | None = None, on_scan: Callable[[int], None] | None = None,
            on_estimate: Callable[[Estimate], None] | None = None,
            start_s: float = 0.0, sigma_warn_m: float = DEFAULT_SIGMA_WARN_M,
            parallel_compile: bool = True,
            on_compile: Callable[[], None] | None = None) -> RunResult:
    """Run the estimator over a bag and write the results into ``out_dir``.

    ``start_s`` skips the bag's first seconds (the run then starts wherever the sensor is, at
    rest or moving). ``on_scan(n)`` is called after each scan handed to the estimator (n counts
    them); ``on_estimate(est)`` after each estimate is written (e.g. a live view). An exception
    either raises stops the run like an error would (KeyboardInterrupt = Ctrl-C). Evaluation
    against a ground truth is separate: :func:`adalio.eval.report.make_report` on ``out_dir``.
    ``parallel_compile``: on a cold numba cache, compile the update's kernels in a helper process
    meanwhile (:mod:`adalio.lio.warmup`; off for runs that already share the cores).
    ``on_compile()`` is called once the first scan is decoded, before it is handed to the
    estimator, if the kernels will compile during this run (a cold numba cache;
    ``RunResult.compiled``): an input error in the bag or its first cloud comes before it.
    """
    if not isinstance(config, Config):
        raise ConfigError(f"run_bag takes a Config (adalio.load_config('hilti2022') or "
                          f"load_config(config_file=...)), got {type(config).__name__} "
                          f"{config!r:.60}")
    cfg = copy.deepcopy(config)
    if map_format is not None:
        cfg.output.map_format = map_format
    cfg.validate()
    if max_scans is not None and max_scans < 1:
        raise ConfigError(f"--max-scans must be >= 1 (got {max_scans})")
    if not start_s >= 0:
        raise ConfigError(f"--start-s must be >= 0 seconds (got {start_s})")
    if not sigma_warn_m > 0:
        raise ConfigError(f"--sigma-warn-m must be > 0 metres (got {sigma_warn_m})")
    try:
        import adalio.lio  # noqa: F401
    except ImportError:
        raise AdalioError("the estimator (adalio.lio.Odometry) is not available in this "
                          "install; update adalio") from None

    if not (cfg.sensor.imu_time_offset_check or cfg.sensor.extrinsic_rotation_check
            or cfg.sensor.gyro_scale_check):
        return _run_once(bag_path, cfg, Path(out_dir), progress=progress, max_scans=max_scans,
                         on_scan=on_scan, on_estimate=on_estimate, start_s=start_s,
                         sigma_warn_m=sigma_warn_m, parallel_compile=parallel_compile,
                         on_compile=on_compile, restart_on_offset=False)
    kwargs: dict[str, Any] = {"progress": progress, "max_scans": max_scans, "on_scan": on_scan,
                              "on_estimate": on_estimate, "start_s": start_s,
                              "sigma_warn_m": sigma_warn_m}
    seen: set[str] = set()
    t_start = time.perf_counter()
    with _said_once(seen, again=False):
        first = _run_once(bag_path, cfg, Path(out_dir), parallel_compile=parallel_compile,
                          on_compile=on_compile, restart_on_offset=True, **kwargs)
    gross = first.extrinsic_rotation_gross
    if gross is None or first.interrupted:
        return _run_checked(bag_path, cfg, out_dir, first, seen, t_start, **kwargs)
    configured_sigma_deg = cfg.sensor.extrinsic_rotation_sigma_deg
    # the rotation is too far off for the fine checks, whose first run read it through the
    # wrong axes: everything starts again from the rotation the gross check found
    corrected = copy.deepcopy(cfg)
    T = np.asarray(cfg.sensor.T_imu_lidar, dtype=np.float64)
    T[:3, :3] = gross.correction @ T[:3, :3]
    corrected.sensor.T_imu_lidar = T.tolist()
    corrected.sensor.extrinsic_source = "config"
    corrected.sensor.extrinsic_rotation_sigma_deg = restarted_rotation_sigma_deg(
        cfg.sensor.extrinsic_rotation_sigma_deg, gross.sigma_rad)
    if np.isfinite(gross.fine_rad):  # backed by the fine check: it must see less after it
        try:
            _, left, _ = _calibration_pass(bag_path, corrected, first.n_scans_in,
                                           kwargs["start_s"])
        except KeyboardInterrupt:  # the first run's outputs stand
            first.interrupted = True
            return first
        if left is not None and not left.angle_rad < gross.fine_rad:
            # the gyro-free registration was biased, not the rotation grossly off (a Mid-360
            # along a corridor: 12-15 deg whatever the error, session 93), and a small error
            # made the fine check significant: its passes go on from the configured rotation
            warnings.warn(f"a LiDAR registration that never used the gyro put the LiDAR-IMU "
                          f"rotation {gross.text()} off, but with that correction the filter's "
                          f"LiDAR-only rotation disagrees with the gyro more over the same first "
                          f"{first.n_scans_in} scans ({np.degrees(left.angle_rad):.2f} deg "
                          f"against {np.degrees(gross.fine_rad):.2f} deg): the correction was "
                          "refused, and the configured sensor.T_imu_lidar's rotation is checked "
                          "finely instead", stacklevel=2)
            res = _run_without_gross(bag_path, cfg, out_dir, first, seen, t_start, **kwargs)
            res.extrinsic_rotation_gross_refuted = (gross, left)
            return res
    cfg = corrected
    warnings.warn(f"the LiDAR-IMU rotation is off by {gross.text()}: {gross.evidence()}; the "
                  "run restarted with the rotation found (then "
                  "checked finely; the corrected sensor.T_imu_lidar is in its config.yaml: "
                  "set it in your config, or check the axes' order in a quaternion: x y z w)",
                  stacklevel=2)
    res = _run_without_gross(bag_path, cfg, out_dir, first, seen, t_start,
                             configured_sigma_deg=configured_sigma_deg, **kwargs)
    res.extrinsic_rotation_gross_found = gross
    return res


def _run_without_gross(bag_path: str | Path, cfg: Config, out_dir: str | Path,
                       first: RunResult, seen: set[str], t_start: float, *,
                       configured_sigma_deg: float | None = None, **kwargs: Any) -> RunResult:
    """:func:`run_bag` after its first run ``first`` stopped on a gross rotation error: the run
    again from ``cfg`` (the rotation found, or the configured one where the correction was
    refused) without the gross check, then the fine checks' passes (:func:`_run_checked`)."""
    with _said_once(seen, again=True):
        second = _run_once(bag_path, cfg, Path(out_dir), parallel_compile=False,
                           on_compile=None, restart_on_offset=True, check_gross=False, **kwargs)
    res = second if second.interrupted else _run_checked(
        bag_path, cfg, out_dir, second, seen, t_start,
        configured_sigma_deg=configured_sigma_deg, **kwargs)
    res.calibration_wall_s = res.calibration_wall_s or (  # 0: the fine checks did not restart
        time.perf_counter() - t_start - res.wall_s)
    res.compiled = first.compiled
    return res


def _run_checked(bag_path: str | Path, cfg: Config, out_dir: str | Path, first: RunResult,
                 seen: set[str], t_start: float, *, configured_sigma_deg: float | None = None,
                 **kwargs: Any) -> RunResult:
    """:func:`run_bag` after its first run ``first`` (stopped where a check concluded, or
    whole): the passes that find what the checks found off, and the restart with it.
    ``configured_sigma_deg``: after a gross rotation error, the configured
    ``sensor.extrinsic_rotation_sigma_deg`` (``cfg`` holds the gross estimate's deviation, the
    prior of the fine passes; a rotation they find sets the restart's from the configured one)."""
    progress, start_s = kwargs["progress"], kwargs["start_s"]
    est, rot = first.time_offset, first.extrinsic_rotation
    scale = first.gyro_scale if first.gyro_scale is not None else first.gyro_scale_so_far
    offset_off = est is not None and est.significant
    if first.interrupted or not (offset_off or (rot is not None and rot.significant)
                                 or (scale is not None and scale.significant
                                     and scale.conclusive)):
        return first
    found: TimeOffsetCalibration | None = None
    found_rot: RotationCalibration | None = None
    found_scale: GyroScaleCalibration | None = None
    try:
        if offset_off:
            found, rot_after, scale_after = _find_time_offset(
                bag_path, cfg, first.n_scans_in, start_s, est.offset_s, progress)
            if found is not None:
                cfg.sensor.imu_time_offset_s = found.offset_s
                rot = rot_after  # the rotation with the gyro's stamps corrected
                scale = scale_after if scale_after is not None else scale
        n_rot = first.n_scans_in
        n_scale = max(first.n_scans_in, round(SCALE_SPAN_S * cfg.sensor.lidar_rate_hz))
        if scale is not None and scale.significant and (
                not scale.conclusive or found is not None):  # the first run stopped for
            # another check, or its estimate ran with the IMU's stamps off (a lag reads as a
            # scale: 30 ms late gave -14 %): estimated again over the scale's span
            _, _, scale = _calibration_pass(bag_path, cfg, n_scale, start_s)
        if scale is not None and scale.significant and scale.conclusive:  # before the
            # rotation: a scale error turns the rotation check's estimate too (the scale
            # check's fit holds both)
            n_rot = n_scale
            found_scale, rot_after = _find_gyro_scale(bag_path, cfg, n_rot, start_s, scale,
                                                      progress)
            if found_scale is not None:
                cfg.sensor.gyro_sensitivity = found_scale.gyro_sensitivity.tolist()
                rot = rot_after
        if rot is not None and rot.significant:
            found_rot = _find_rotation(bag_path, cfg, n_rot, start_s, rot, progress)
            if found_rot is not None:
                cfg.sensor.T_imu_lidar = found_rot.T_imu_lidar.tolist()
                cfg.sensor.extrinsic_source = "config"
    except KeyboardInterrupt:  # the first run's outputs stand
        first.interrupted = True
        return first
    if offset_off and found is None:
        late = "late" if est.offset_s > 0 else "early"
        warnings.warn(f"the gyro's timing disagrees with the LiDAR's: the IMU's stamps run at "
                      f"least {abs(est.offset_s) * 1e3:.1f} ms {late} against the rotation the "
                      "LiDAR alone registers, but re-running the first scans found no value; "
                      "set sensor.imu_time_offset_s if you know the offset", stacklevel=3)
    if found is not None:
        late = "late" if found.offset_s > found.configured_s else "early"
        warnings.warn(f"the gyro's timing disagrees with the LiDAR's: the IMU's stamps run "
                      f"{abs(found.offset_s - found.configured_s) * 1e3:.1f} ms {late} against "
                      f"the rotation the LiDAR alone registers (found over the first "
                      f"{found.n_scans} scans in {len(found.passes)} passes); the run restarted "
                      f"with sensor.imu_time_offset_s: {found.offset_s:.4f} (set it in your "
                      "config to start with it)", stacklevel=3)
    if found_rot is not None:
        cfg.sensor.extrinsic_rotation_sigma_deg = restarted_rotation_sigma_deg(
            cfg.sensor.extrinsic_rotation_sigma_deg if configured_sigma_deg is None
            else configured_sigma_deg, found_rot.sigma_rad)
        if gyro_uncalibrated(found_scale, scale):
            # the rotation found may be the gyro's own axes' misalignment rather than the
            # extrinsic's: the trajectory's frame then follows the gyro's axes, off the IMU's
            # by up to the whole correction, which no check can see
            cfg.sensor.gyro_axes_sigma_deg = restarted_gyro_axes_sigma_deg(
                cfg.sensor.gyro_axes_sigma_deg, float(np.linalg.norm(found_rot.correction_rad)))
        warnings.warn(f"the LiDAR-IMU rotation disagrees with the data: the gyro turns about "
                      f"axes {found_rot.angle_deg:.2f} deg away from those the LiDAR alone "
                      f"registers (found over the first {found_rot.n_scans} scans in "
                      f"{len(found_rot.passes)} passes); the run restarted with the corrected "
                      f"sensor.T_imu_lidar (in its config.yaml; set it in your config to start "
                      "with it)", stacklevel=3)
    if found_scale is not None:
        warnings.warn(f"the gyro's scale factors disagree with the data: against the rates the "
                      f"LiDAR alone registers, the gyro reads {found_scale.text()} off (found "
                      f"over the first {found_scale.n_scans} scans in "
                      f"{len(found_scale.passes)} passes); the run restarted with the corrected "
                      f"sensor.gyro_sensitivity (in its config.yaml; calibrate the IMU's "
                      f"intrinsics, or set it in your config to start with it)", stacklevel=3)
    if found is None and found_rot is None and found_scale is None and not (
            first.stopped_for_time_offset or first.stopped_for_extrinsic_rotation
            or first.stopped_for_gyro_scale):
        return first
    t_restart = time.perf_counter()
    with _said_once(seen, again=True):
        res = _run_once(bag_path, cfg, Path(out_dir), parallel_compile=False, on_compile=None,
                        restart_on_offset=False, warn_checks=False, check_gross=False, **kwargs)
    left = res.time_offset
    if found is not None and left is not None and left.significant:  # one restart only
        late = "late" if left.offset_s > 0 else "early"
        warnings.warn(f"after the restart with sensor.imu_time_offset_s: "
                      f"{cfg.sensor.imu_time_offset_s:.4f}, the IMU's stamps still run at least "
                      f"{abs(left.offset_s) * 1e3:.1f} ms (+-{left.sigma_s * 1e3:.1f}) {late} "
                      f"against the LiDAR-registered rotation over {left.span_s:.0f} s (too "
                      "little rotation change to settle it, or the offset drifts): move "
                      "sensor.imu_time_offset_s by at least that and run again",
                      stacklevel=3)
    rot_left = res.extrinsic_rotation
    if rot_left is not None and rot_left.significant:
        warnings.warn(f"after the restart, the gyro's axes are still turned at least "
                      f"{np.degrees(rot_left.angle_rad):.2f} deg (+-"
                      f"{np.degrees(rot_left.sigma_rad):.2f}) about {rot_left.axis_text()} "
                      f"against the rotation the LiDAR alone registers over "
                      f"{rot_left.span_s:.0f} s: check sensor.T_imu_lidar's rotation",
                      stacklevel=3)
    scale_left = res.gyro_scale
    if found_scale is not None and scale_left is not None and scale_left.significant:
        warnings.warn(f"after the restart, the gyro still reads {scale_left.text()} off against "
                      f"the rates the LiDAR alone registers over {scale_left.span_s:.0f} s: "
                      f"calibrate the IMU's intrinsics (sensor.gyro_sensitivity)", stacklevel=3)
    res.time_offset_found = found
    res.extrinsic_rotation_found = found_rot
    res.gyro_scale_found = found_scale
    res.calibration_wall_s = t_restart - t_start
    res.compiled = first.compiled
    return res


SCALE_SPAN_S = 30.0
"""The passes that find the gyro's scale error run over at least this many seconds of scans
(the first run's, if longer): over the first 10 s of the hall its estimate missed an entry by
7 deviations, over 20-40 s it is within 0.1-0.6 % of each (session 64)."""


def restarted_rotation_sigma_deg(configured_deg: float, found_sigma_rad: float) -> float:
    """The restarted run's ``sensor.extrinsic_rotation_sigma_deg`` after a found rotation: at
    least the found value's deviation, within what the config allows (its ``config.yaml`` must
    load again); a configured 0 (the sigmas without the extrinsic's term) stays 0."""
    if not configured_deg > 0:
        return configured_deg
    top = RANGES["sensor.extrinsic_rotation_sigma_deg"].hi
    return min(max(configured_deg, round(float(np.degrees(found_sigma_rad)), 3)), top)


def gyro_uncalibrated(found_scale: GyroScaleCalibration | None, scale: Any) -> bool:
    """The gyro's scale was found off and corrected (``found_scale``), or its check's estimate
    (``scale``, a :class:`adalio.lio.gyro_scale.GyroScaleEstimate` or None) is significantly off
    where the check could not settle it: either way the gyro is uncalibrated, and a rotation
    the rotation check found may be its axes' (``restarted_gyro_axes_sigma_deg``). Before
    session 94 only the first counted: with 2 % per entry, the scale 2.3 % (+-0.32) unsettled
    and 1.5 deg applied to the extrinsic, a hall walk kept 28-62 % of its scans within 3 sigma
    along one axis, 100 % since."""
    return found_scale is not None or (scale is not None and bool(scale.significant))


def restarted_gyro_axes_sigma_deg(configured_deg: float, correction_rad: float) -> float:
    """The restarted run's ``sensor.gyro_axes_sigma_deg`` after a rotation found together with a
    gyro scale error: at least the rotation applied, within what the config allows."""
    top = RANGES["sensor.gyro_axes_sigma_deg"].hi
    return min(max(configured_deg, round(float(np.degrees(correction_rad)), 3)), top)


def _significant(odom: Any, check: str) -> bool:
    """Whether the odometry's check ``check`` (``time_offset``, ``extrinsic_rotation``)
    concluded on a significant value."""
    est = getattr(odom, check, None)
    return est is not None and est.significant


def _calibration_off(odom: Any) -> bool:
    """A check concluded that the IMU time offset, the LiDAR-IMU rotation or the gyro's scale
    is off."""
    return (_significant(odom, "time_offset") or _significant(odom, "extrinsic_rotation")
            or _significant(odom, "gyro_scale")
            or getattr(odom, "gross_rotation", None) is not None)


@contextlib.contextmanager
def _said_once(seen: set[str], *, again: bool) -> Iterator[None]:
    """Warnings shown meanwhile: their texts noted in ``seen`` (the first run), or, with
    ``again`` (the restarted run), only those not in ``seen`` shown (said once is enough)."""
    shown = warnings.showwarning

    def show(message: Any, *args: Any, **kwargs: Any) -> None:
        if again and str(message) in seen:
            return
        seen.add(str(message))
        shown(message, *args, **kwargs)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = shown


def _find_time_offset(bag_path: str | Path, cfg: Config, n_scans: int, start_s: float,
                      detected_s: float, progress: bool
                      ) -> tuple[TimeOffsetCalibration | None, Any, Any]:
    """Re-run the first ``n_scans`` scans with corrected IMU stamps until the check finds no
    offset left (:func:`adalio.lio.time_offset.next_offset`); None if no pass estimated one.
    The value: one more step of the search from every pass (the last pass's offset left is
    below significance but not zero; between two passes of opposite signs the step
    interpolates), or, if an earlier pass left less, that pass's offset. Also the rotation
    check's and the gyro scale check's estimates of the last pass (None: none)."""
    from adalio.lio.time_offset import MAX_PASSES, next_offset

    base = cfg.sensor.imu_time_offset_s
    tried: list[tuple[float, float]] = [(0.0, detected_s)]
    passes: list[tuple[float, float]] = []
    rotation = scale = None
    with progress_bar(progress, "timing the IMU", "offset") as bar:
        task = bar.add_task("passes", total=MAX_PASSES, offset="")
        for _ in range(MAX_PASSES):
            trial = float(np.clip(base + next_offset(tried), -1.0, 1.0))
            c = copy.deepcopy(cfg)
            c.sensor.imu_time_offset_s = trial
            left, rotation, scale = _calibration_pass(bag_path, c, n_scans, start_s)
            bar.update(task, advance=1, offset=f"{trial * 1e3:+.1f} ms")
            if left is None:
                break
            tried.append((trial - base, left.offset_s))
            passes.append((trial, left.offset_s))
            if not left.significant:
                break
    if not passes:
        return None, None, None
    best, residual = min(passes, key=lambda p: abs(p[1]))
    if best == passes[-1][0]:  # the last pass left the least: one more step from all passes
        best = float(np.clip(base + next_offset(tried), -1.0, 1.0))
    return TimeOffsetCalibration(offset_s=round(best, 5), configured_s=base,
                                 detected_s=detected_s, residual_s=residual, passes=passes,
                                 n_scans=n_scans), rotation, scale


def _find_rotation(bag_path: str | Path, cfg: Config, n_scans: int, start_s: float,
                   detected: Any, progress: bool) -> RotationCalibration | None:
    """Re-run the first ``n_scans`` scans with the extrinsic's rotation corrected until what
    the check finds left is settled (``RotationEstimate.settled``; the corrections from
    :func:`adalio.lio.extrinsic_check.next_rotation`); None if no pass estimated one. The
    value found as :func:`_find_time_offset`'s: one more step from the pass that left the least,
    if it was the last, else that pass's correction. Its covariance is that pass's estimate's
    over the squared gain (the estimate's noise, read through the share of a rotation it sees;
    a gain above 1, a noisy secant, is read as 1: the estimate sees at most the whole rotation).
    The correction applied is its posterior mean under ``sensor.extrinsic_rotation_sigma_deg``
    (:func:`adalio.lio.extrinsic_sigma.posterior`, the prior widened to what the value makes
    most likely): a value that its own noise could have made is shrunk towards the configured
    rotation instead of applied whole (the passes find a rotation where the check's estimate is
    zero, and an estimate that concluded on a noisy excursion carries it into the value)."""
    from adalio.lio.extrinsic_check import MAX_PASSES, largest_sigma, next_rotation, pass_gain
    from adalio.lio.extrinsic_sigma import posterior

    T0 = np.asarray(cfg.sensor.T_imu_lidar, dtype=np.float64)
    tried: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros(3), detected.rotvec_rad)]
    passes: list[tuple[np.ndarray, np.ndarray]] = []
    covs: list[np.ndarray] = []

    def corrected(theta: np.ndarray) -> np.ndarray:
        T = T0.copy()
        T[:3, :3] = Rotation.from_rotvec(theta).as_matrix() @ T0[:3, :3]
        return T

    with progress_bar(progress, "aligning the IMU", "rotation") as bar:
        task = bar.add_task("passes", total=MAX_PASSES, rotation="")
        for _ in range(MAX_PASSES):
            trial = next_rotation(tried)
            c = copy.deepcopy(cfg)
            c.sensor.T_imu_lidar = corrected(trial).tolist()
            c.sensor.extrinsic_source = "config"
            _, left, _ = _calibration_pass(bag_path, c, n_scans, start_s)
            bar.update(task, advance=1,
                       rotation=f"{np.degrees(np.linalg.norm(trial)):.2f} deg")
            if left is None:
                break
            tried.append((trial, left.rotvec_rad))
            passes.append((trial, left.rotvec_rad))
            covs.append(left.cov_rad2)
            if left.settled:
                break
    if not passes:
        return None
    k = min(range(len(passes)), key=lambda i: float(np.linalg.norm(passes[i][1])))
    found = next_rotation(tried) if k == len(passes) - 1 else passes[k][0]
    cov = covs[k] / min(pass_gain(tried), 1.0) ** 2  # it sees at most the whole rotation
    best = found
    prior_rad = float(np.radians(cfg.sensor.extrinsic_rotation_sigma_deg))
    if prior_rad > 0:  # 0: the configured rotation's error is left out of the sigmas
        best, _ = posterior(prior_rad, found, cov)
    return RotationCalibration(correction_rad=best, T_imu_lidar=corrected(best),
                               detected_rad=detected.rotvec_rad,
                               residual_rad=float(np.linalg.norm(passes[k][1])), passes=passes,
                               n_scans=n_scans, sigma_rad=largest_sigma(cov), found_rad=found)


def _find_gyro_scale(bag_path: str | Path, cfg: Config, n_scans: int, start_s: float,
                     detected: Any, progress: bool) -> tuple[GyroScaleCalibration | None, Any]:
    """Re-run the first ``n_scans`` scans with the gyro's sensitivity corrected until what the
    gyro scale check finds left is settled (``GyroScaleEstimate.settled``; the corrections
    from :func:`adalio.lio.gyro_scale.next_scale`); the value as :func:`_find_rotation`'s (one
    more step from the pass that left the least, if it was the last). None if no pass
    estimated one, the value is below ``MIN_SCALE_ERROR`` (the first estimate was not the
    gyro's), or it is no sensitivity (``config.validate_sensitivity``). Also the
    rotation check's estimate of the pass that left the least (None: none)."""
    from adalio.lio.gyro_scale import (
        MAX_PASSES,
        MIN_SCALE_ERROR,
        corrected_sensitivity,
        next_scale,
    )

    S0 = np.asarray(cfg.sensor.gyro_sensitivity, dtype=np.float64)
    tried: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros(6), detected.s)]
    passes: list[tuple[np.ndarray, np.ndarray]] = []
    rotations: list[Any] = []
    with progress_bar(progress, "scaling the gyro", "scale") as bar:
        task = bar.add_task("passes", total=MAX_PASSES, scale="")
        for _ in range(MAX_PASSES):
            trial = next_scale(tried)
            c = copy.deepcopy(cfg)
            c.sensor.gyro_sensitivity = corrected_sensitivity(S0, trial).tolist()
            try:
                validate_sensitivity(c.sensor.gyro_sensitivity, "sensor.gyro_sensitivity")
            except ConfigError:
                break
            _, rotation, left = _calibration_pass(bag_path, c, n_scans, start_s)
            bar.update(task, advance=1, scale=f"{100 * np.abs(trial).max():.2f} %")
            if left is None:
                break
            rotations.append(rotation)
            tried.append((trial, left.s))
            passes.append((trial, left.s))
            if left.settled:
                break
    if not passes:
        return None, None
    k = min(range(len(passes)), key=lambda i: float(np.abs(passes[i][1]).max()))
    best = next_scale(tried) if k == len(passes) - 1 else passes[k][0]
    if np.abs(best).max() < MIN_SCALE_ERROR:  # the passes took the first estimate back
        return None, None
    S = corrected_sensitivity(S0, best)
    try:
        validate_sensitivity(S, "sensor.gyro_sensitivity")
    except ConfigError:
        return None, None
    return GyroScaleCalibration(correction=best, gyro_sensitivity=S, detected=detected.s,
                                residual=float(np.abs(passes[k][1]).max()), passes=passes,
                                n_scans=n_scans), rotations[k]


def _sequencer(bag: Bag, lidar_topic: str, imu_topic: str, cfg: Config,
               start_s: float) -> Sequencer:
    """The bag's scans and IMU in processing order, from ``start_s`` seconds into it."""
    return Sequencer(bag, lidar_topic, imu_topic, cfg.sensor,
                     start_ns=bag.start_ns + round(start_s * 1e9) if start_s else None)


def _calibration_pass(bag_path: str | Path, cfg: Config, n_scans: int,
                      start_s: float) -> tuple[Any, Any, Any]:
    """The IMU time offset, the LiDAR-IMU rotation and the gyro's scale error the checks
    estimate over the first ``n_scans`` scans with ``cfg`` (each None: no estimate)."""
    from adalio.lio import Odometry

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with Bag(bag_path) as bag:
            lidar_topic, imu_topic = bag.select_topics(cfg.sensor)
            odom = Odometry(cfg)
            odom.warn_time_offset = odom.conclude_time_offset = False
            odom.warn_extrinsic_rotation = odom.check_gross_rotation = False
            seq = _sequencer(bag, lidar_topic, imu_topic, cfg, start_s)
            n = 0
            for item in seq:  # the first run's scans: every pass estimates over the same span
                if isinstance(item, ImuBatch):
                    odom.add_imu(item.t_ns, item.gyro_rad_s, item.accel_m_s2)
                    continue
                odom.add_scan(item.points_lidar, item.t_ns, item.ring, item.line)
                n += 1
                if n >= n_scans:
                    break
    return (odom.time_offset_estimate(), odom.extrinsic_rotation_estimate(),
            odom.gyro_scale_estimate())


def _run_once(bag_path: str | Path, cfg: Config, out: Path, *, progress: bool,
              max_scans: int | None, on_scan: Callable[[int], None] | None,
              on_estimate: Callable[[Estimate], None] | None, start_s: float,
              sigma_warn_m: float, parallel_compile: bool,
              on_compile: Callable[[], None] | None, restart_on_offset: bool,
              warn_checks: bool = True, check_gross: bool = True) -> RunResult:
    """One pass of :func:`run_bag` (``cfg`` validated). ``restart_on_offset``: stop once the
    IMU time offset check or the LiDAR-IMU rotation check concludes on a significant value
    (``RunResult.time_offset``, ``.extrinsic_rotation``); the caller restarts with the value
    found. ``warn_checks``: the estimator's own warnings about them (the caller words its own
    otherwise)."""
    from adalio.lio import Odometry, warmup

    bag = Bag(bag_path).open()
    # a cold numba cache (first run after an install): the update's kernels compile meanwhile in
    # a second process (adalio.lio.warmup); stopped when the run ends, whatever it has done
    compiled = warmup.cache_is_cold()
    helper = warmup.start() if parallel_compile and compiled else warmup.Warmup(None)
    try:
        lidar_topic, imu_topic = bag.select_topics(cfg.sensor)
        bag_s = bag.duration_s
        T_imu_lidar, ext_source = resolve_extrinsic(bag, lidar_topic, imu_topic, cfg)
        cfg.sensor.T_imu_lidar = T_imu_lidar.tolist()
        n_clouds = next((t.count for t in bag.topics() if t.name == lidar_topic), 0)
        total = min(n_clouds, max_scans) if max_scans else n_clouds
        out.mkdir(parents=True, exist_ok=True)
        dense = cfg.output.dense_map_voxel_m > 0
        remove_stale_outputs(out, cfg.output.map_format, dense)
        paths = {"trajectory": out / "trajectory.tum", "scans": out / "scans.csv",
                     "map": out / f"map.{cfg.output.map_format}", "config": out / "config.yaml",
                     "dense_map": out / f"map_dense.{cfg.output.map_format}" if dense else None}
        paths["config"].write_text(cfg.to_yaml())
        odom = Odometry(cfg)
        odom.warn_time_offset = warn_checks and not restart_on_offset
        odom.warn_extrinsic_rotation = warn_checks and not restart_on_offset
        odom.check_gross_rotation = check_gross
        seq = _sequencer(bag, lidar_topic, imu_topic, cfg, start_s)
        tum = TumWriter(paths["trajectory"])
        csvw = ScansCsvWriter(paths["scans"])
        wall_ms: list[float] = []
        est_t: list[int] = []
        degen: list[bool] = []
        held: list[bool] = []
        risky: list[bool] = []
        blind: list[bool] = []
        moved = [0, 0, 0]
        """Over the written rows: the sums of n_moving and n_seen_through, and the rows with
        n_moving above 0 (RunResult.moving_points)."""
        strays = [0, 0, 0, 0, 0]
        """Over the written rows: the sums of n_stray and n_raw (RunResult.stray_points), of
        n_stray_dropped, the rows that dropped points, and n_stray in the others
        (stray_drops)."""
        stray_drop: list[bool] = []
        risky_extrinsic_m = 0.0
        poses: list[np.ndarray] = []
        sigmas: list[np.ndarray] = []
        var_ext: list[np.ndarray] = []
        """Of the written rows, in their order: the pose, the six sigma columns and
        ``ScanStats.var_extrinsic_world`` (:func:`_extrinsic_known_late`)."""
        late = False
        """A backfilled row was written after later ones: the files are sorted at the end."""

        def write(e: Estimate, ms: float) -> None:
            nonlocal late, risky_extrinsic_m
            late = late or bool(est_t and int(e.t_ns) < est_t[-1])
            tum.write(e.t_ns, e.T_world_imu)
            stats = e.stats
            stats.t_ns = int(e.t_ns)
            if not stats.wall_ms:
                stats.wall_ms = ms
            csvw.write(stats)
            if not stats.backfill:  # estimates held back by the rest check come with ms 0
                wall_ms.append(ms or stats.wall_ms)
            est_t.append(int(e.t_ns))
            degen.append(bool(stats.degenerate))
            held.append(stats.held_directions > 0)
            risky.append(bool(np.nanmax(stats.sigma_p_world_m) > sigma_warn_m))
            poses.append(np.asarray(e.T_world_imu, dtype=np.float64))
            sigmas.append(scan_sigmas(stats))
            var_ext.append(np.resize(np.asarray(stats.var_extrinsic_world, float), 6))
            if risky[-1]:
                risky_extrinsic_m = max(risky_extrinsic_m, float(stats.sigma_extrinsic_m))
            blind.append(bool(stats.height_blind))
            moved[0] += int(stats.n_moving)
            moved[1] += int(stats.n_seen_through)
            moved[2] += int(stats.n_moving > 0)
            strays[0] += int(stats.n_stray)
            strays[1] += int(stats.n_raw)
            stray_drop.append(stats.n_stray_dropped > 0)
            if stray_drop[-1]:
                strays[2] += int(stats.n_stray_dropped)
                strays[3] += 1
            else:
                strays[4] += int(stats.n_stray)
            if on_estimate is not None:
                on_estimate(e)

        def flush_held() -> None:
            """On Ctrl-C: the estimates a pending rest check held back are written (with the
            check off they would have been already)."""
            odom.conclude_rest_check()
            for e in odom.take_backfill():
                write(e, 0.0)

        n_in = 0
        interrupted = False
        restart = False
        t_start = time.perf_counter()
        stop = GracefulStop()
        try:
            with stop, progress_bar(progress, "scans", "rate") as bar:
                task = bar.add_task("scans", total=total or None, rate="")
                for item in seq:
                    if stop.requested:
                        interrupted = True
                        break
                    if isinstance(item, ImuBatch):
                        odom.add_imu(item.t_ns, item.gyro_rad_s, item.accel_m_s2)
                        continue
                    if n_in == 0 and compiled and on_compile is not None:
                        on_compile()  # after the first cloud decoded: its input errors come first
                    t0 = time.perf_counter()
                    est = odom.add_scan(item.points_lidar, item.t_ns, item.ring, item.line)
                    ms = (time.perf_counter() - t0) * 1e3
                    n_in += 1
                    for e in odom.take_backfill():
                        write(e, 0.0)
                    if est is not None:
                        write(est, ms)
                    elapsed = time.perf_counter() - t_start
                    bar.update(task, advance=1, rate=f"{n_in / max(elapsed, 1e-9):.1f} scans/s")
                    if on_scan is not None:
                        on_scan(n_in)
                    if max_scans is not None and n_in >= max_scans:
                        break
                    if restart_on_offset and _calibration_off(odom):
                        restart = True
                        break
                if not interrupted and not restart:  # a pending backfill runs now (a Ctrl-C
                    odom.finish()                      # lets it finish)
                    for e in odom.take_backfill():
                        write(e, 0.0)
                elif interrupted:
                    flush_held()
        except KeyboardInterrupt:
            interrupted = True
            with contextlib.suppress(Exception), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                flush_held()
        except (BagError, InputError):
            # the input stops the run: the scans held for the backfill still get their poses
            # (from the state before the fault), as at the data's end; the error is raised as is
            with contextlib.suppress(Exception), warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the error says what happened
                odom.finish()
                for e in odom.take_backfill():
                    write(e, 0.0)
            raise
        finally:
            tum.close()
            csvw.close()
            with contextlib.suppress(Exception):  # never mask the error that stopped the run
                wide, ext_m, n_widened = _extrinsic_known_late(odom, paths["scans"], est_t,
                                                               poses, sigmas, var_ext)
                if n_widened:  # the summary's stretches by the sigmas written
                    risky = [bool(r) for r in np.nanmax(wide[:, :3], axis=1) > sigma_warn_m]
                    risky_extrinsic_m = float(np.max(ext_m[risky], initial=0.0))
            if late:
                with contextlib.suppress(Exception):  # never mask the error that stopped the run
                    sort_rows_by_time(paths["trajectory"], paths["scans"])
            pts, map_left_out = np.zeros((0, 3)), 0
            for k in dict.fromkeys((cfg.output.map_min_returns, 1)):  # all points if it fails
                try:
                    pts, map_left_out = odom.map_cloud(k)
                    break
                except Exception:  # noqa: BLE001, S112  (never mask the error that stopped the run)
                    continue
            map_counts = (map_left_out, len(pts) + map_left_out)
            dense_counts = (0, 0)
            if paths["dense_map"] is not None:  # before the map's own voxel filter thins it
                dense_pts, dense_left_out = np.zeros((0, 3)), 0
                with contextlib.suppress(Exception):  # never mask the error that stopped the run
                    dense_pts, dense_left_out = odom.dense_map_cloud(pts)
                write_map(paths["dense_map"], dense_pts, cfg.output.map_format)
                dense_counts = (len(dense_pts), dense_left_out)
            leaf = cfg.output.map_voxel_m
            if leaf > 0 and len(pts):
                from adalio.lio.voxel import voxel_downsample

                with contextlib.suppress(Exception):
                    pts = voxel_downsample(np.asarray(pts, dtype=np.float64), leaf)
            write_map(paths["map"], pts, cfg.output.map_format)
            paths["config"].write_text(_config_text(cfg, odom))
        wall_s = time.perf_counter() - t_start
    finally:
        helper.stop()
        bag.close()
    order = np.argsort(np.asarray(est_t, dtype=np.int64), kind="stable")
    est_t, degen, held, risky, blind, stray_drop = (
        [seq_[i] for i in order] for seq_ in (est_t, degen, held, risky, blind, stray_drop))
    result = RunResult(
        out_dir=out, trajectory_path=paths["trajectory"], scans_csv_path=paths["scans"],
        map_path=paths["map"], config_path=paths["config"], n_scans=len(est_t),
        n_degenerate=int(sum(degen)), wall_s=wall_s,
        ms_per_scan_median=statistics.median(wall_ms) if wall_ms else 0.0,
        stage_ms=dict(getattr(odom, "stage_ms_total", {}) or {}), interrupted=interrupted,
        degenerate_ranges_s=_flag_ranges(est_t, degen), n_held=int(sum(held)),
        held_ranges_s=_flag_ranges(est_t, held), lidar_topic=lidar_topic,
        imu_topic=imu_topic, extrinsic_source=ext_source,
        time_spec=seq.decoder.time_spec.describe() if seq.decoder.time_spec else "",
        sequencer=seq.stats, n_scans_in=n_in, init_report=odom.init_report,
        sigma_warn_m=sigma_warn_m, sigma_warn_ranges_s=_flag_ranges(est_t, risky),
        n_sigma_warn=int(sum(risky)), sigma_warn_extrinsic_m=risky_extrinsic_m,
        n_height_blind=int(sum(blind)),
        height_blind_ranges_s=_flag_ranges(est_t, blind), compiled=compiled,
        imu_saturation=[(sat, (sat.first_t_ns - est_t[0]) * 1e-9)
                        for sat in seq.range_monitor.found()] if est_t else [],
        lidar_gaps=[((t - est_t[0]) * 1e-9, gap_s, sigma_m)
                    for t, gap_s, sigma_m in odom.lidar_gaps] if est_t else [],
        noise_raises=[((t - est_t[0]) * 1e-9, g, a)
                      for t, g, a in getattr(odom, "noise_raises", [])] if est_t else [],
        local_surface_rows=tuple(getattr(odom, "local_surface_rows", (0, 0))),
        moving_points=tuple(moved),
        stray_points=(strays[0], strays[1]),
        stray_dropped=cfg.preprocess.drop_stray_returns,
        stray_drops=(strays[2], strays[3], strays[4]),
        map_left_out=map_counts, map_min_returns=cfg.output.map_min_returns,
        dense_map_path=paths["dense_map"], dense_map_points=dense_counts,
        dense_map_voxel_m=cfg.output.dense_map_voxel_m,
        stray_dropped_ranges_s=_flag_ranges(est_t, stray_drop),
        stray_drop_share=cfg.preprocess.stray_drop_share,
        moving_body=cfg.map.remove_moving and cfg.map.moving_body_m > 0.0,
        time_offset=getattr(odom, "time_offset", None),
        stopped_for_time_offset=restart and _significant(odom, "time_offset"),
        extrinsic_rotation=getattr(odom, "extrinsic_rotation", None),
        stopped_for_extrinsic_rotation=restart and _significant(odom, "extrinsic_rotation"),
        gyro_scale=getattr(odom, "gyro_scale", None),
        stopped_for_gyro_scale=restart and _significant(odom, "gyro_scale"),
        gyro_scale_unsettled=getattr(odom, "gyro_scale_unsettled", None),
        gyro_scale_so_far=(odom.gyro_scale_estimate() if restart and odom.gyro_scale is None
                           else None),
        time_offset_unsettled=getattr(odom, "time_offset_unsettled", None),
        extrinsic_rotation_unsettled=getattr(odom, "extrinsic_rotation_unsettled", None),
        extrinsic_translation=getattr(odom, "extrinsic_translation", None),
        extrinsic_translation_unsettled=getattr(odom, "extrinsic_translation_unsettled", None),
        extrinsic_rotation_gross=getattr(odom, "gross_rotation", None),
        extrinsic_rotation_gross_checked=getattr(odom, "gross_rotation_checked", None),
        lidar_view=getattr(odom, "lidar_view", None))
    if not est_t and not interrupted and not (restart_on_offset and _calibration_off(odom)):
        raise InputError(_no_pose_reason(odom, n_in, lidar_topic, imu_topic, out,
                                         seq.stats.scans_late, start_s, bag_s))
    return result
