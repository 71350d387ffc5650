"""``simulate``: scene + trajectory + LiDAR + IMU -> bag, ground truth, metadata and config.

Outputs in ``out_dir``: the bag (``<scene>.bag`` for ROS1, ``<scene>_ros2/`` or
``<scene>_mcap/`` for ROS2), ``gt.tum`` (IMU pose in the world = IMU frame at the first sample,
100 Hz, absolute seconds with 9 decimals), ``meta.json``, ``config.yaml`` (accepted by
``adalio run --config``) and ``scene.ply`` (the mesh in the scene frame; ``meta.json`` carries
``T_scene_world`` to place it). Time: int64 ns, starting at ``START_NS``. Deterministic for a seed.
"""

from __future__ import annotations

import errno
import json
import math
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
import yaml
from scipy.spatial.transform import Rotation

from adalio.config import preset_dict, validate_transform
from adalio.errors import InputError
from adalio.sim.bagout import FORMATS, POINT_STEP, SimBagWriter, bag_path_for
from adalio.sim.imu import GRAVITY_M_S2, ImuNoise, sensitivity_errors, synthesize_imu
from adalio.sim.lidar import (
    LIDAR_MODELS,
    LidarModel,
    Occluder,
    RayCaster,
    SweepSimulator,
    lidar_model,
)
from adalio.sim.people import People, check_people
from adalio.sim.scenes import build_scene
from adalio.sim.trajectory import HandheldMotion, Trajectory, check_pace, tilt_rig_lidar

SCENES = ("hall", "corridor", "spiral", "stairs_garage")
START_NS = 1_646_304_541_527_137_000
"""Sequence start (epoch ns), the first HILTI 2022 exp04 sweep."""
IMU_RATE_HZ = 400.0
"""The IMU's sample rate by default: the HILTI 2022 rig's BMI085."""
MIN_IMU_RATE_HZ = 20.0
MAX_IMU_RATE_HZ = 4000.0
"""The IMU rates ``simulate`` accepts: at least two samples per 10 Hz sweep, and well above the
100-1000 Hz that LiDAR-inertial rigs record (a sequence's IMU samples are held in memory whole)."""
MAX_IMU_TIME_OFFSET_S = 1.0
"""The IMU stamp offsets ``simulate`` writes (as ``sensor.imu_time_offset_s`` accepts)."""
MAX_IMU_SCALE_ERROR_PCT = 10.0
"""The IMU sensitivity errors ``simulate`` draws, at most (standard deviation per entry, %):
consumer MEMS datasheets give scale-factor tolerances and cross-axis sensitivities of 0.5-3 %."""
MAX_IMU_VIBRATION = 300.0
"""``--imu-vibration`` at most: 300 times the BMI085's white noise is about 6 m/s² RMS on each
accelerometer axis at 400 Hz, a legged robot's steps."""
VIBRATION_FULL_M_S = 0.3
"""The IMU's vibration grows with the rig's speed up to this (m/s), then stays at its full
strength: a robot's motors and legs shake it while it moves, not while it stands."""
MAX_LIDAR_TILT_DEG = 90.0
"""The LiDAR tilts ``simulate`` takes, either way: up to a spin axis lying horizontal."""
MAX_STRAY_FRACTION = 0.5
"""The shares of ghost and of dust returns ``simulate`` takes, each: at most every other
return."""
GT_RATE_HZ = 100.0
T_IMU_LIDAR_HILTI = [[0.0, -1.0, 0.0, -0.001], [-1.0, 0.0, 0.0, -0.00855],
                     [0.0, 0.0, -1.0, 0.055], [0.0, 0.0, 0.0, 1.0]]
"""HILTI 2022 PandarXT-32 -> BMI085 extrinsic (p_imu = R p_lidar + t)."""
MIN_CLEARANCE_M = 0.25
IMU_MESSAGE_BYTES = 600
"""Bytes a generated sequence takes per IMU sample, at most: an Imu message with its record,
index and database row takes 380 bytes in a ROS1 bag and 430-460 in a ROS2 one (measured; MCAP
compresses)."""
SWEEP_MESSAGE_BYTES = 4096
"""Bytes a sweep's message takes beside its points, at most (header, fields, record and index,
a database page)."""
SPARE_BYTES = 200_000_000
"""Room kept free beside a sequence's estimated size (ground truth, mesh, bag index, and the
other outputs of whatever else writes to the same disk meanwhile)."""
_POINT_TIME = {
    "hesai": {"point_time_field": "timestamp", "point_time_unit": "s",
              "point_time_reference": "absolute"},
    "ouster": {"point_time_field": "t", "point_time_unit": "ns", "point_time_reference": "relative"},
    "velodyne": {"point_time_field": "time", "point_time_unit": "s",
                 "point_time_reference": "relative"},
}
"""Each driver's per-point time field as the sequence's ``config.yaml`` names it (``livox``: none,
a ``CustomMsg`` carries its own point times)."""


def default_mounting(model: LidarModel) -> list[list[float]]:
    """The IMU-LiDAR mounting ``simulate`` gives ``model`` unless told one: a LiDAR with its
    own IMU (:attr:`~adalio.sim.lidar.LidarModel.builtin_imu`, the Livox models) that IMU where
    its preset's ``T_imu_lidar`` puts it, axes along the LiDAR's; the others the HILTI 2022 rig's
    (:data:`T_IMU_LIDAR_HILTI`: the LiDAR upside down over a separate IMU)."""
    if model.builtin_imu:
        T = preset_dict(model.preset)["sensor"]["T_imu_lidar"]
        return [[float(v) for v in row] for row in T]
    return T_IMU_LIDAR_HILTI


def sequence_bytes(n_scans: int, columns: int, channels: int, n_imu: int) -> int:
    """An upper bound of the disk space a sequence takes: every beam of every sweep returning
    (``POINT_STEP`` bytes a point, :data:`SWEEP_MESSAGE_BYTES` a sweep), every IMU sample
    (:data:`IMU_MESSAGE_BYTES`), plus :data:`SPARE_BYTES`."""
    return int(n_scans) * (columns * channels * POINT_STEP + SWEEP_MESSAGE_BYTES) \
        + int(n_imu) * IMU_MESSAGE_BYTES + SPARE_BYTES


def check_free_space(out_dir: Path, need_bytes: int, reserved_bytes: int = 0) -> None:
    """An ``OSError`` (ENOSPC, naming ``out_dir``) when its disk has less than ``need_bytes``
    free beyond ``reserved_bytes`` (what other writers in progress still need): before minutes of
    generation, not after, and with no partial bag left behind."""
    free = shutil.disk_usage(out_dir).free
    if free - reserved_bytes < need_bytes:
        held = (f", {reserved_bytes / 1e9:.1f} GB of it reserved by other generations in "
                "progress" if reserved_bytes else "")
        raise OSError(errno.ENOSPC, f"not enough free space: the sequence needs up to "
                      f"{need_bytes / 1e9:.1f} GB and the disk has {free / 1e9:.1f} GB "
                      f"free{held}", str(out_dir))


@dataclass
class SimResult:
    """Paths of a generated sequence."""

    bag_path: Path
    gt_path: Path
    meta_path: Path
    config_path: Path


def _ns_to_s_str(t_ns: int) -> str:
    return f"{t_ns // 1_000_000_000}.{t_ns % 1_000_000_000:09d}"


def check_imu_scale_error(pct: float) -> None:
    """``--imu-scale-error-pct`` within 0 .. :data:`MAX_IMU_SCALE_ERROR_PCT`, else an
    ``InputError`` naming it."""
    if not 0.0 <= pct <= MAX_IMU_SCALE_ERROR_PCT:
        raise InputError(f"--imu-scale-error-pct must be 0-{MAX_IMU_SCALE_ERROR_PCT:g} "
                         f"(got {pct:g})")


def check_imu_vibration(times: float) -> None:
    """``--imu-vibration`` within 0 .. :data:`MAX_IMU_VIBRATION`, else an ``InputError``."""
    if not 0.0 <= times <= MAX_IMU_VIBRATION:
        raise InputError(f"--imu-vibration must be 0-{MAX_IMU_VIBRATION:g} (got {times:g})")


def _check_args(scene: str, duration_s: float | None, lidar: str, fmt: str,
                noise_scale: float, imu_rate_hz: float = IMU_RATE_HZ) -> None:
    if scene not in SCENES:
        raise InputError(f"unknown scene '{scene}': choose one of {', '.join(SCENES)}")
    if lidar not in LIDAR_MODELS:
        raise InputError(f"unknown lidar '{lidar}': choose one of {', '.join(LIDAR_MODELS)}")
    if fmt not in FORMATS:
        raise InputError(f"unknown bag format '{fmt}': choose one of {', '.join(FORMATS)}")
    if duration_s is not None and not duration_s > 0.5:
        raise InputError(f"--duration must be > 0.5 s (got {duration_s})")
    if not noise_scale >= 0:
        raise InputError(f"--noise-scale must be >= 0 (got {noise_scale})")
    if not MIN_IMU_RATE_HZ <= imu_rate_hz <= MAX_IMU_RATE_HZ:
        raise InputError(f"--imu-rate must be {MIN_IMU_RATE_HZ:g}-{MAX_IMU_RATE_HZ:g} Hz "
                         f"(got {imu_rate_hz})")


def check_lidar_tilt(tilt_deg: float) -> None:
    """``--lidar-tilt-deg`` within +-:data:`MAX_LIDAR_TILT_DEG`, else an ``InputError``."""
    if not abs(tilt_deg) <= MAX_LIDAR_TILT_DEG:
        raise InputError(f"--lidar-tilt-deg must be within +-{MAX_LIDAR_TILT_DEG:g} "
                         f"(got {tilt_deg:g})")


def check_stray(flag: str, fraction: float) -> None:
    """A share of stray returns (``--ghosts``, ``--dust``; ``flag`` names it) within
    0 .. :data:`MAX_STRAY_FRACTION`, else an ``InputError``."""
    if not 0.0 <= fraction <= MAX_STRAY_FRACTION:
        raise InputError(f"{flag} must be a fraction 0-{MAX_STRAY_FRACTION:g} "
                         f"(got {fraction:g})")


def build_trajectory(scene_obj, T_imu_lidar: np.ndarray, seed: int,
                     handheld: HandheldMotion | None = None,
                     lidar_tilt_deg: float = 0.0, pace: float = 1.0) -> Trajectory:
    """The walking trajectory of a scene for a seed (with a recorded walk's handheld motion
    instead of the synthetic one when ``handheld`` is given), with the LiDAR level on the
    handle or pitched ``lidar_tilt_deg`` nose down (:func:`~adalio.sim.trajectory.
    tilt_rig_lidar`), the IMU fixed to it by ``T_imu_lidar``, the route walked ``pace`` times
    as fast as the scene's speeds (:class:`~adalio.sim.trajectory.Trajectory`)."""
    R_rig_imu = tilt_rig_lidar(lidar_tilt_deg) @ np.asarray(T_imu_lidar)[:3, :3].T
    return Trajectory(scene_obj.waypoints_m, scene_obj.speed_limit_m_s,
                      R_rig_imu, seed=seed, fillet_m=scene_obj.fillet_m,
                      handheld=handheld, pace=pace)


def mesh_distance_m(caster: RayCaster, points: np.ndarray, n_dirs: int = 256) -> np.ndarray:
    """Exact distance of each point to the mesh surface (metres).

    Embree rays in ``n_dirs`` directions give an upper bound; the exact point-triangle distance
    is then computed for the triangles whose bounding box lies within that bound.
    """
    k = np.arange(n_dirs) + 0.5
    phi = np.arccos(1 - 2 * k / n_dirs)
    th = np.pi * (1 + 5**0.5) * k
    dirs = np.column_stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)])
    P = np.asarray(points, dtype=np.float64)
    d, _ = caster.cast(np.repeat(P, n_dirs, axis=0), np.tile(dirs, (len(P), 1)))
    bound = d.reshape(len(P), n_dirs).min(axis=1)
    tris = caster.mesh.triangles
    lo, hi = tris.min(axis=1), tris.max(axis=1)
    out = np.empty(len(P))
    for i, (p, b) in enumerate(zip(P, bound, strict=True)):
        box_d = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=1)
        cand = np.flatnonzero(box_d <= min(b, 1e3) + 1e-9)
        if len(cand) == 0:
            out[i] = b
            continue
        q = trimesh.triangles.closest_point(tris[cand], np.repeat(p[None], len(cand), axis=0))
        out[i] = np.linalg.norm(q - p, axis=1).min()
    return out


def _config_dict(model, T_imu_lidar: np.ndarray, imu_rate_hz: float) -> dict:
    """The sequence's ``config.yaml``: the LiDAR's preset
    (:attr:`~adalio.sim.lidar.LidarModel.preset`) with the rig's topics, extrinsic and point time.
    Every model is simulated with the same IMU, the HILTI BMI085, so every config describes it as
    ``hilti2022`` does (its ``imu`` section): the generic presets' IMU values are Faster-LIO's, not
    this IMU's (README, Presets), and the LiDAR is then the only thing that changes between the
    models' sequences. The Livox models (``livox``: ``livox_mid360``, ``livox_avia``) give no point
    time fields (a ``CustomMsg`` carries its own point times, ``timebase + offset_time``);
    ``sensor.accel_unit`` stays ``auto``, which finds their IMU's g."""
    sensor = {"lidar_topic": model.lidar_topic, "imu_topic": model.imu_topic,
              "T_imu_lidar": np.asarray(T_imu_lidar).tolist(), "extrinsic_source": "config",
              "imu_rate_hz": float(imu_rate_hz), "lidar_rate_hz": model.rate_hz,
              **_POINT_TIME.get(model.driver, {})}
    config = {"preset": model.preset, "sensor": sensor}
    if model.preset != "hilti2022":  # hilti2022 itself describes the BMI085
        config["imu"] = preset_dict("hilti2022")["imu"]
    return config


def simulate(scene: str, out_dir: str | Path, *, seed: int = 0, duration_s: float | None = None,
             lidar: str = "xt32", fmt: str = "ros1", columns: int | None = None,
             noise_scale: float = 1.0, progress: bool = False,
             T_imu_lidar: list[list[float]] | np.ndarray | None = None,
             occluder: bool = True, scene_params: dict | None = None,
             imu_noise_scale: float = 1.0, imu_bias_scale: float = 1.0,
             motion_from: str | Path | None = None,
             make_room: Callable[[int], object] | None = None,
             imu_rate_hz: float = IMU_RATE_HZ,
             lidar_rate_hz: float | None = None,
             imu_time_offset_s: float = 0.0,
             imu_scale_error_pct: float = 0.0,
             people: int = 0, lidar_tilt_deg: float = 0.0, ghosts: float = 0.0,
             dust: float = 0.0, pace: float = 1.0, imu_vibration: float = 0.0) -> SimResult:
    """Generate one sequence of ``scene`` into ``out_dir`` (created; the bag must not exist).

    ``duration_s`` None walks the whole route; shorter values truncate it (static start kept).
    ``noise_scale`` multiplies all sensor noise, dropouts and initial IMU biases (0 = perfect).
    ``T_imu_lidar`` overrides the model's mounting (:func:`default_mounting`: the HILTI rig's,
    or a Livox model's built-in IMU), ``occluder`` toggles the operator's body,
    ``scene_params`` overrides the scene builder's sizes (see :mod:`adalio.sim.scenes`).
    ``imu_noise_scale`` further multiplies the IMU's white-noise densities only (x10: a 10x
    noisier IMU than the HILTI BMI085, whose bias walks and initial biases stay as they are).
    ``imu_bias_scale`` further multiplies the IMU's initial biases and bias random walks only
    (0: an IMU without bias, to separate what its bias costs from what the LiDAR costs).
    ``imu_rate_hz``: the IMU's sample rate (the HILTI BMI085's 400 Hz by default; an Ouster's
    internal IMU gives 100 Hz): the densities stay the same, so each sample's white noise is
    ``density * sqrt(rate)``, and the samples are the true motion's, at their stamps.
    ``lidar_rate_hz``: the sweeps per second (default the model's 10 Hz): each sweep lasts
    ``1 / lidar_rate_hz`` with ``columns`` columns, and ``config.yaml`` says the rate.
    ``imu_time_offset_s``: the IMU's stamps run this much late against the LiDAR's (each sample
    is the motion at its time, stamped later; negative: early), as an IMU stamped on arrival;
    ``config.yaml`` does not say it (``meta.json`` does), as a user would not know it.
    ``imu_scale_error_pct``: the gyro and the accelerometer read the truth through ``I + E``,
    each of ``E``'s nine entries drawn N(0, pct / 100) from the seed (scale factors on the
    diagonal, cross-axis sensitivity and misalignment off it; :func:`adalio.sim.imu.
    sensitivity_errors`); ``meta.json`` gives both ``E``, ``config.yaml`` neither (an
    uncalibrated IMU).
    ``people``: that many people walk along the route while the rig does (upright cylinders,
    :mod:`adalio.sim.people`; where and how fast each walks is drawn from the seed's own stream,
    so the scene, the motion and the noise stay as without them); ``meta.json`` says where.
    ``lidar_tilt_deg``: the LiDAR sits pitched this much nose down on the handle (negative: nose
    up; within +-90), about the walk's lateral axis, with the IMU fixed to it by ``T_imu_lidar``:
    the hand's motion stays the same, the LiDAR's spin axis leans forward, and its view takes in
    the floor ahead and the ceiling behind. ``config.yaml`` needs nothing for it (the extrinsic
    is the same); ``meta.json`` says it.
    ``ghosts``: each valid return, on its own, with this probability (0-0.5) lies a distance
    drawn uniformly from 0.3-2.0 m (:data:`~adalio.sim.lidar.STRAY_OFFSET_M`) further along its
    ray, behind its surface (multipath off glass or metal, cross-talk); beyond the model's
    maximum range it is dropped. ``dust``: likewise with this probability (0-0.5) that distance
    nearer, in front of its surface (dust); below the model's minimum range it is dropped. No
    return is both (one draw decides: dust with probability ``dust``, else a ghost with
    probability ``ghosts``; :func:`~adalio.sim.lidar.dirty_ranges`). Applied after the range
    noise and the dropouts, whatever ``noise_scale``; the intensity stays the surface's, the
    returns' times and rings their beams'. Drawn from a stream of their own (seed, 300, sweep),
    so the scene, the motion, the noise and the other returns stay as without them (with both 0
    the bag is the same, byte for byte); ``meta.json`` says both.
    ``pace``: the route walked this many times as fast as the scene's speeds (0.25-3, default
    1): its speed limits and yaw-rate bound times ``pace``, its acceleration bound times
    ``pace²``; the hand and the gait keep their times (:class:`~adalio.sim.trajectory.
    Trajectory`). The sequence is then shorter; ``meta.json`` says the pace.
    ``imu_vibration``: while the rig moves, the IMU shakes (a robot's motors or legs): white
    noise of this many times the IMU's white-noise densities (0-300) is added to its gyro and
    accelerometer samples, in full from :data:`VIBRATION_FULL_M_S` of speed on and in
    proportion below it, so that the still start is as quiet as without it. Drawn from a stream
    of its own (seed, 400): the rest of the sequence is the same (with 0, byte for byte).
    ``config.yaml`` does not say it; ``meta.json`` does.
    ``motion_from``: a TUM trajectory (>= 10 Hz) whose handheld motion replaces the synthetic
    one (:class:`adalio.sim.trajectory.HandheldMotion`; the seed picks where in it to start);
    ``"none"``: no hand motion at all, the route's own path and attitude (a robot's walk).
    Before writing, the disk must have room for the whole sequence (:func:`sequence_bytes`),
    else an ``OSError`` (ENOSPC) names ``out_dir``; ``make_room(bytes)`` is called first with
    that size (the sequence cache evicts to make room).
    """
    if not imu_noise_scale >= 0:
        raise InputError(f"--imu-noise-scale must be >= 0 (got {imu_noise_scale})")
    if not imu_bias_scale >= 0:
        raise InputError(f"--imu-bias-scale must be >= 0 (got {imu_bias_scale})")
    _check_args(scene, duration_s, lidar, fmt, noise_scale, imu_rate_hz)
    check_imu_scale_error(imu_scale_error_pct)
    check_people(people)
    check_lidar_tilt(lidar_tilt_deg)
    check_stray("--ghosts", ghosts)
    check_stray("--dust", dust)
    check_pace(pace)
    check_imu_vibration(imu_vibration)
    if not abs(imu_time_offset_s) <= MAX_IMU_TIME_OFFSET_S:
        raise InputError(f"--imu-time-offset-ms must be within +-{MAX_IMU_TIME_OFFSET_S * 1e3:g} "
                         f"ms (got {imu_time_offset_s * 1e3:g})")
    offset_ns = round(imu_time_offset_s * 1e9)
    model = lidar_model(lidar, columns, lidar_rate_hz)
    T_il = validate_transform(default_mounting(model) if T_imu_lidar is None else T_imu_lidar,
                              "T_imu_lidar")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bag_path = bag_path_for(out_dir, scene, fmt)
    if bag_path.exists():
        raise InputError(f"{bag_path} already exists: delete it or choose another --out")
    handheld = None if motion_from is None else HandheldMotion.load(motion_from)
    scn = build_scene(scene, seed, **(scene_params or {}))
    traj = build_trajectory(scn, T_il, seed, handheld, lidar_tilt_deg, pace)
    dur = math.floor(traj.duration_s * 10.0) / 10.0 if duration_s is None else float(duration_s)
    dur_ns = round(dur * 1e9)
    t0 = START_NS

    caster = RayCaster(scn.mesh, seed)
    t_check = np.arange(0.0, dur + 1e-9, 0.1)
    clearance = float(mesh_distance_m(caster, traj.sample(t_check).p_world_imu_m).min())
    if clearance < MIN_CLEARANCE_M:
        raise InputError(f"scene {scene} seed {seed}: route passes {clearance:.2f} m from the "
                         "geometry; try another --seed")

    imu_dt_ns = round(1e9 / imu_rate_hz)
    rate_hz = 1e9 / imu_dt_ns  # the rate the integer-ns stamps hold
    t_imu = t0 + np.arange(dur_ns // imu_dt_ns + 1, dtype=np.int64) * imu_dt_ns
    imu_noise = ImuNoise()
    sensitivity = (sensitivity_errors(seed, imu_scale_error_pct / 100.0)
                   if imu_scale_error_pct else None)
    imu = synthesize_imu(traj, t_imu, t0, np.random.default_rng([seed, 200]), imu_noise,
                         noise_scale, rate_hz, white_scale=imu_noise_scale,
                         bias_scale=imu_bias_scale, sensitivity=sensitivity)
    if imu_vibration:
        speed = np.linalg.norm(traj.sample((t_imu - t0) * 1e-9).v_world_m_s, axis=1)
        shake = imu_vibration * np.sqrt(rate_hz) * np.clip(speed / VIBRATION_FULL_M_S, 0.0,
                                                           1.0)[:, None]
        vib = np.random.default_rng([seed, 400])
        imu.gyro_rad_s = imu.gyro_rad_s + shake * imu_noise.gyro_noise_rad_s_sqrt_hz \
            * vib.standard_normal(imu.gyro_rad_s.shape)
        imu.accel_m_s2 = imu.accel_m_s2 + shake * imu_noise.accel_noise_m_s2_sqrt_hz \
            * vib.standard_normal(imu.accel_m_s2.shape)
    period = model.period_ns
    n_scans = dur_ns // period
    need = sequence_bytes(n_scans, model.columns, model.channels, len(t_imu))
    if make_room is not None:
        make_room(need)
    check_free_space(out_dir, need)
    walkers = People.along_route(scn.waypoints_m, int(people), seed)
    sim = SweepSimulator(caster, traj, model, T_il, t0, Occluder() if occluder else None,
                         walkers)
    n_points = 0
    bar = None
    if progress:
        from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

        bar = Progress(TextColumn(f"simulating {scene}"), BarColumn(),
                       TextColumn("{task.completed}/{task.total} sweeps"), TimeRemainingColumn())
        bar.start()
        task = bar.add_task("sweeps", total=int(n_scans))
    try:
        with SimBagWriter(bag_path, fmt, model) as writer:
            i_imu = 0
            for k in range(int(n_scans)):
                stamp = t0 + k * period
                record = stamp + period
                j = int(np.searchsorted(t_imu, record, side="right"))
                if j > i_imu:
                    writer.write_imu(t_imu[i_imu:j], imu.gyro_rad_s[i_imu:j],
                                     imu.accel_m_s2[i_imu:j], offset_ns)
                    i_imu = j
                stray = np.random.default_rng([seed, 300, k]) if ghosts or dust else None
                sweep = sim.sweep(stamp, np.random.default_rng([seed, 100, k]), noise_scale,
                                  ghosts, dust, stray)
                n_points += writer.write_sweep(sweep, stamp, record)
                if bar is not None:
                    bar.advance(task)
            if i_imu < len(t_imu):
                writer.write_imu(t_imu[i_imu:], imu.gyro_rad_s[i_imu:], imu.accel_m_s2[i_imu:],
                                 offset_ns)
    except BaseException:
        if bag_path.is_dir():
            shutil.rmtree(bag_path, ignore_errors=True)
        elif bag_path.exists():
            bag_path.unlink()
        raise
    finally:
        if bar is not None:
            bar.stop()

    gt_dt_ns = round(1e9 / GT_RATE_HZ)
    t_gt = t0 + np.arange(dur_ns // gt_dt_ns + 1, dtype=np.int64) * gt_dt_ns
    s = traj.sample((t_gt - t0) * 1e-9)
    R0, p0 = s.R_world_imu[0], s.p_world_imu_m[0]
    R_gt = np.einsum("ji,njk->nik", R0, s.R_world_imu)
    p_gt = (s.p_world_imu_m - p0) @ R0
    q_gt = Rotation.from_matrix(R_gt).as_quat()
    gt_path = out_dir / "gt.tum"
    with open(gt_path, "w") as f:
        f.write("# t_s x y z qx qy qz qw (IMU pose in world = IMU frame at t0)\n")
        f.writelines(_ns_to_s_str(t) + " " + " ".join(f"{v:.9f}" for v in (*p, *q)) + "\n" for t, p, q in zip(t_gt.tolist(), p_gt, q_gt, strict=True))

    T_scene_world = np.eye(4)
    T_scene_world[:3, :3] = R0
    T_scene_world[:3, 3] = p0
    scn.mesh.export(out_dir / "scene.ply")
    meta = {
        "scene": scene, "seed": int(seed), "scene_params": dict(scene_params or {}),
        "duration_s": dur, "lidar": model.name,
        "format": fmt, "columns": model.columns, "channels": model.channels,
        "noise_scale": float(noise_scale), "imu_noise_scale": float(imu_noise_scale),
        "imu_bias_scale": float(imu_bias_scale),
        "occluder": bool(occluder),
        "motion_from": None if handheld is None else handheld.source,
        "topics": {"lidar": model.lidar_topic, "imu": model.imu_topic},
        "frame_ids": {"lidar": model.lidar_frame, "imu": model.imu_frame},
        "T_imu_lidar": T_il.tolist(), "T_scene_world": T_scene_world.tolist(),
        "start_time_ns": t0, "start_time_s": _ns_to_s_str(t0), "static_s": traj.static_s,
        "imu_rate_hz": rate_hz, "lidar_rate_hz": model.rate_hz, "gt_rate_hz": GT_RATE_HZ,
        "imu_time_offset_s": offset_ns * 1e-9,
        "imu_scale_error_pct": float(imu_scale_error_pct),
        "imu_gyro_sensitivity_error": (np.zeros((3, 3)) if sensitivity is None
                                       else sensitivity[0]).tolist(),
        "imu_accel_sensitivity_error": (np.zeros((3, 3)) if sensitivity is None
                                        else sensitivity[1]).tolist(),
        "people": walkers.as_dict(), "lidar_tilt_deg": float(lidar_tilt_deg),
        "ghosts": float(ghosts), "dust": float(dust), "pace": float(pace),
        "imu_vibration": float(imu_vibration),
        "gravity_m_s2": GRAVITY_M_S2, "n_scans": int(n_scans), "n_imu": len(t_imu),
        "n_points": int(n_points), "route_length_m": traj.route_length_m,
        "min_clearance_m": round(clearance, 4),
        "range_noise_m": model.range_noise_m * noise_scale,
        "imu_noise": {k: v for k, v in vars(imu_noise).items()},
        "gyro_bias0_rad_s": imu.gyro_bias_rad_s[0].tolist(),
        "accel_bias0_m_s2": imu.accel_bias_m_s2[0].tolist(),
        "bag": bag_path.name,
    }
    if model.non_repetitive:  # only then: the other models' meta.json stay as they were
        meta["scan_pattern"] = "non_repetitive"
    if model.imu_accel_unit != "m_s2":
        meta["imu_accel_unit"] = model.imu_accel_unit
    meta_path = out_dir / "meta.json"
    meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    config_path = out_dir / "config.yaml"
    config = _config_dict(model, T_il, rate_hz)
    config_path.write_text(yaml.safe_dump(config, sort_keys=False, default_flow_style=None))
    return SimResult(bag_path=bag_path, gt_path=gt_path, meta_path=meta_path,
                     config_path=config_path)
