"""Benchmark: does the default preset initialize and track on sensors it was not tuned on?

The sensor-variation matrix of issue #12, reusable by later work: for every scene, seed, IMU
noise level (x the HILTI BMI085 white-noise densities, ``simulate(imu_noise_scale=...)``; bias
walks and initial biases stay at the HILTI values) and
LiDAR (XT-32 at 512 / 2000 columns, Ouster OS1-64, VLP-16; ``--lidars`` also takes the OS0-128,
the XT-32 at 1000 columns, ``mid360``, a Livox Mid-360-like non-repetitive LiDAR, and ``avia``, a
Livox Avia-like forward-looking rosette, both written as Livox's ``CustomMsg``), the simulator's
sequence is run through ``adalio.pipeline.run_bag`` with the sequence's own ``config.yaml``
(preset ``hilti2022``, ``ouster``, ``velodyne``, ``livox_mid360`` or ``livox_avia`` with the
simulated extrinsic; nothing else set) twice:

* **still start**: the whole bag (the simulated walk rests for its first 2.5 s);
* **moving start**: the bag without its first ``--cut-s`` seconds (``run_bag(start_s=...)``),
  so the first message already moves; once per cut time given (default 8, 10 and 12 s: the
  corridor's moving start diverges at some cut times and not at others, so one start time alone
  says little).

Per cell: poses / scans in the part of the bag that was read, how the estimator initialized
(static / moving) and how long after the first scan read (``InitReport.wait_s``), SE(3)-aligned ATE RMSE against ground truth (evo), the median time per
scan, and the share of scans whose error (aligned on the filter's first scan) lies within 3
sigma of the ``scans.csv`` sigmas on x / y / z (``adalio.eval.metrics.sigma_consistency``).
The summary gives, per scene, start and noise level, the mean and worst ATE of the runs that
stayed within 1 m, the count of the others (over 1 m, or no result), the count of the runs
whose largest error after aligning the filter's first scan is over 1 m (issue #14's divergence
test; the README's *runs over 1 m*; each run's in ``cells.json``, ``max_error_first_m``), and
checks the issue's targets: poses >= 95 % of scans (still) / >= 90 % (moving); hall ATE <= 1 cm
(still) / <= 2 cm (moving); and no run over 1 m ATE in any scene.

With ``--mountings`` the sequences are also simulated with other IMU-LiDAR mountings
(:data:`MOUNTINGS`; the simulator keeps the LiDAR level and turns the IMU, so a mounting is how
the IMU sits under the LiDAR), each run with that sequence's own ``config.yaml``, whose
``sensor.T_imu_lidar`` is the mounting: nothing in the estimator may assume the HILTI rig's.
With ``--imu-rates`` the IMU samples at other rates than the BMI085's 400 Hz (an Ouster's
internal IMU: 100 Hz), with the same noise densities. With ``--lidar-rates`` the LiDAR sweeps
at other rates than 10 Hz (``simulate(lidar_rate_hz=...)``; the columns per sweep stay the
LiDAR's: ``xt32-1000`` at 20 Hz is the XT-32's 20 Hz setting, the firing rate of its 2000
columns at 10 Hz). With ``--motion-from`` every walk takes a
recording's hand motion instead of the synthetic one, or none at all (``none``: a robot's
walk, at the route's own height and attitude). With ``--imu-time-offsets-ms`` the IMU's stamps
run late (or early) against the LiDAR's, which the runs' configs do not say: the last column
gives the offset ``run_bag`` found and restarted with, and what the final run's check left.
With ``--extrinsic-errors-deg`` the runs' configs give the extrinsic's rotation turned by that
angle about an axis drawn from the seed: the column after gives the rotation ``run_bag`` found
(passes), what the final run's check left, and the final extrinsic's error. With
``--extrinsic-translation-errors-cm`` the configs' lever arm is that far off, along a direction
drawn from the seed: the last column gives what the translation check concluded (``found``:
significant, flagged in the run's summary; ``settled``: precise and not significant) and how far the configured lever
arm plus the correction it found is from the simulated one (the injected error where it found
none). With ``--imu-scale-errors-pct`` the simulated gyro and accelerometer read the truth
through ``I + E`` (scale factors and cross-axis sensitivity, each entry of ``E`` drawn from the
seed with that standard deviation, ``simulate(imu_scale_error_pct=...)``), which no config says:
an uncalibrated MEMS IMU. With ``--people`` that many people walk along the route while the
rig does (``simulate(people=...)``, upright cylinders; :mod:`adalio.sim.people`). With
``--lidar-tilts-deg`` the LiDAR sits pitched that much nose down on the handle, the IMU fixed to
it (``simulate(lidar_tilt_deg=...)``): the configs are the same, the view is not. With
``--ghosts`` and ``--dust`` that share of each sweep's returns lies 0.3-2.0 m behind its surface
(multipath, cross-talk) or in front of it (dust) along its ray (``simulate(ghosts=...,
dust=...)``), which no config says. With ``--paces`` the route is walked that many times as fast as
the scene's speeds (``simulate(pace=...)``): a brisk surveyor, a robot. With
``--imu-vibrations`` the IMU shakes while the rig moves, white noise of that many times its
densities (``simulate(imu_vibration=...)``), which the still start does not see.

    python benchmarks/bench_sensors.py                      # hall + corridor, 2 seeds, full routes
    python benchmarks/bench_sensors.py --scenes hall --seeds 1 --lidars xt32-512
    python benchmarks/bench_sensors.py --starts still --mountings upright skewed side
    python benchmarks/bench_sensors.py --starts still --imu-rates 400 200 100
    python benchmarks/bench_sensors.py --starts still --lidars xt32-1000 --lidar-rates 20
    python benchmarks/bench_sensors.py --scenes corridor --starts still --motion-from none
    python benchmarks/bench_sensors.py --starts still --imu-time-offsets-ms 0 20 -20 50
    python benchmarks/bench_sensors.py --starts still --extrinsic-errors-deg 0 1
    python benchmarks/bench_sensors.py --starts still --extrinsic-translation-errors-cm 0 3
    python benchmarks/bench_sensors.py --starts still --imu-scale-errors-pct 0 0.3 1
    python benchmarks/bench_sensors.py --starts still --people 0 4
    python benchmarks/bench_sensors.py --starts still --lidar-tilts-deg 0 30 90
    python benchmarks/bench_sensors.py --starts still --ghosts 0 0.1 --dust 0 0.2
    python benchmarks/bench_sensors.py --starts still --paces 1 1.5 2
    python benchmarks/bench_sensors.py --starts still --imu-vibrations 0 30 100
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import shlex
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from bench_modes import parse_overrides
from scipy.spatial.transform import Rotation

from adalio.config import load_config
from adalio.errors import InputError
from adalio.eval.files import read_map_points, read_scans_csv
from adalio.eval.metrics import ate, sigma_consistency
from adalio.eval.scene_map import map_off_scene
from adalio.pipeline import run_bag
from adalio.sim import cached_sequence
from adalio.sim.generate import (
    IMU_RATE_HZ,
    MAX_IMU_RATE_HZ,
    MAX_IMU_SCALE_ERROR_PCT,
    MAX_IMU_TIME_OFFSET_S,
    MAX_IMU_VIBRATION,
    MAX_LIDAR_TILT_DEG,
    MAX_STRAY_FRACTION,
    MIN_IMU_RATE_HZ,
    T_IMU_LIDAR_HILTI,
)
from adalio.sim.lidar import lidar_model
from adalio.sim.people import MAX_PEOPLE
from adalio.sim.trajectory import PACE_RANGE

LIDARS = {"xt32-512": ("xt32", 512), "xt32-2000": ("xt32", 2000), "os1-64": ("ouster64", None),
          "os0-128": ("ouster128", None),
          "vlp16": ("vlp16", None), "xt32-1000": ("xt32", 1000), "mid360": ("mid360", None),
          "avia": ("avia", None)}
"""Name -> (simulator model, columns per sweep; None the model's). ``xt32-1000`` is the XT-32 at
its 20 Hz setting (``--lidar-rates 20``: 1000 columns a sweep, the firing rate of its 2000 at
10 Hz); ``mid360`` the Livox Mid-360-like non-repetitive LiDAR (Livox ``CustomMsg``, its IMU's
accelerometer in g); ``avia`` the Livox Avia-like forward-looking rosette (70.4 x 77.2 deg along
the walk, ``CustomMsg``, IMU in g); none of these in the default matrix."""
DEFAULT_LIDARS = ["xt32-512", "xt32-2000", "os1-64", "vlp16"]
LIDAR_RATE_HZ = 10.0
"""Every simulated model sweeps at 10 Hz unless ``--lidar-rates`` says otherwise."""


def _mounting(euler_zyx_deg: tuple[float, float, float], t_m: tuple[float, float, float]) -> list:
    """``T_imu_lidar`` (4x4, ``p_imu = R p_lidar + t``) from z-y-x Euler angles and a lever arm."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", euler_zyx_deg, degrees=True).as_matrix()
    T[:3, 3] = t_m
    return T.tolist()


MOUNTINGS: dict[str, list | None] = {
    "default": None,
    "hilti": T_IMU_LIDAR_HILTI,
    "upright": _mounting((0.0, 0.0, 0.0), (0.0, 0.0, 0.06)),
    "skewed": _mounting((35.0, 8.0, -175.0), (0.10, -0.05, 0.10)),
    "side": _mounting((0.0, 0.0, 90.0), (0.0, -0.05, 0.03)),
}
"""IMU-LiDAR mountings ``T_imu_lidar``: ``default`` the simulator's for the LiDAR
(:func:`adalio.sim.generate.default_mounting`: the HILTI rig's for a spinning head, a Livox
model's built-in IMU); ``hilti`` the HILTI 2022 rig's (the LiDAR upside down over the IMU, 5.5 cm
apart), whatever the LiDAR; ``upright`` the IMU's axes along the
LiDAR's, 6 cm under it; ``skewed`` turned 35 / 8 / -175 degrees (z-y-x) with a 15 cm lever arm
(the README's OS1-64 stairwell walk); ``side`` the IMU rolled 90 degrees onto its side."""
TARGET_POSES = {"still": 0.95, "moving": 0.90}
TARGET_HALL_ATE_M = {"still": 0.01, "moving": 0.02}
MAX_ATE_M = 1.0
"""A run beyond this ATE has left the track (issue #14's divergence bound): never a pass."""


@dataclass
class Cell:
    scene: str
    seed: int
    imu_noise: float
    lidar: str
    start: str
    cut_s: float = 0.0
    """Moving start: seconds cut from the bag's start (0 for a still start)."""
    mounting: str = "default"
    """Key of :data:`MOUNTINGS`."""
    imu_rate_hz: float = IMU_RATE_HZ
    """The simulated IMU's sample rate (``simulate(imu_rate_hz=...)``)."""
    lidar_rate_hz: float = LIDAR_RATE_HZ
    """The simulated LiDAR's sweep rate (``simulate(lidar_rate_hz=...)``)."""
    motion_from: str | None = None
    """The walk's hand motion (``simulate(motion_from=...)``): None the synthetic hand, a TUM
    recording's, or ``none`` (a robot's walk)."""
    imu_time_offset_ms: float = 0.0
    """The simulated IMU's stamps run this late against the LiDAR's
    (``simulate(imu_time_offset_s=...)``); the run's config does not say it."""
    extrinsic_error_deg: float = 0.0
    """The run's config gives the extrinsic's rotation this many degrees off the simulated one
    (about an axis drawn from the seed, :func:`turned_extrinsic`)."""
    extrinsic_translation_error_cm: float = 0.0
    """... and its lever arm this many centimetres off (:func:`shifted_extrinsic`)."""
    imu_scale_error_pct: float = 0.0
    """The simulated IMU's sensitivity errors, standard deviation per entry in %
    (``simulate(imu_scale_error_pct=...)``); the run's config does not say them."""
    people: int = 0
    """People walking along the route (``simulate(people=...)``)."""
    lidar_tilt_deg: float = 0.0
    """The LiDAR pitched this much nose down on the handle (``simulate(lidar_tilt_deg=...)``)."""
    imu_bias_scale: float = 1.0
    """The simulated IMU's initial biases and bias walks x this (``simulate(imu_bias_scale=...)``);
    the run's config does not say it."""
    ghosts: float = 0.0
    """Share of the returns pushed 0.3-2.0 m behind their surface (``simulate(ghosts=...)``)."""
    dust: float = 0.0
    """Share of the returns pulled 0.3-2.0 m in front of their surface (``simulate(dust=...)``)."""
    pace: float = 1.0
    """The route walked this many times as fast as the scene's speeds (``simulate(pace=...)``)."""
    imu_vibration: float = 0.0
    """White noise of this many times the IMU's densities while the rig moves
    (``simulate(imu_vibration=...)``)."""
    stray_share: float = float("nan")
    """Stray returns found over the run, a share of the points read (scans.csv ``n_stray`` /
    ``n_raw``; :mod:`adalio.lio.stray`)."""
    stray_scan_max: float = float("nan")
    """The largest share of stray returns in one scan."""
    stray_dropped_scans: float = float("nan")
    """Share of the scans that dropped their stray returns (scans.csv ``n_stray_dropped`` above 0)."""
    map_off_scene: float = float("nan")
    """Share of the written map's points off the scene's surfaces, the map placed by the
    trajectory's SE(3) alignment to the GT: ghosts of people walking by, and a map that drifted
    (:func:`adalio.eval.scene_map.map_off_scene`)."""
    map_left_out: float = float("nan")
    """Share of the map's points left out of the written map (``output.map_min_returns``:
    cells only one of the scans' points reached, on no plane of the map)."""
    map_points: int = 0
    """Points of the written map (``map.ply``)."""
    dense_points: int = 0
    """Points of the dense map (``map_dense.ply``, output.dense_map_voxel_m; 0: none)."""
    dense_off_scene: float = float("nan")
    """:attr:`map_off_scene` of the dense map."""
    scale_found_pct: float = float("nan")
    """The gyro scale correction ``run_bag`` restarted with, its largest entry in % (NaN: none)."""
    scale_passes: int = 0
    scale_left_pct: float = float("nan")
    """The final run's gyro scale check: its estimate's largest entry in % (NaN: no
    estimate)."""
    scale_left_sigma_pct: float = float("nan")
    scale_error_pct: float = float("nan")
    """The symmetric part of the gyro's sensitivity error left after the final run's
    ``sensor.gyro_sensitivity`` (the simulated one from ``meta.json``), largest entry in %."""
    scans: int = 0
    poses: int = 0
    init: str = ""
    ate_m: float = float("nan")
    ms_per_scan: float = float("nan")
    error: str = ""
    within_3sigma: list[float] = field(default_factory=lambda: [float("nan")] * 3)
    """Share of scans whose error (aligned on the filter's first scan) is within 3 sigma on x, y,
    z."""
    max_error_first_m: float = float("nan")
    """The largest position error over the scans, aligned on the filter's first scan (issue
    #14's divergence test: a run whose largest error is over 1 m has left the track)."""
    mean_nees: float = float("nan")
    median_abs_z: list[float] = field(default_factory=lambda: [float("nan")] * 3)
    """Median over the scans of |error| / sigma on x, y, z: 0.67 for honest sigmas, far below
    for sigmas much larger than the errors (``SigmaConsistency.median_abs_z``)."""
    init_wait_s: float = float("nan")
    """From the first scan read to the end of the initialization (InitReport.wait_s)."""
    refused_fits: int = 0
    """Moving start: fits refused before one passed."""
    backfilled: int = 0
    """Scans read before the initialization that the backfill gave a pose."""
    backfill_err_m: float = float("nan")
    """The largest error of those poses, the ground truth aligned on the filter's first scan
    (``SigmaConsistency.backfill_max_error_m``): the seam between the backfill and the forward
    run."""
    filter_noise: str = ""
    offset_found_ms: float = float("nan")
    """The IMU time offset ``run_bag`` found and restarted with (NaN: no restart)."""
    offset_left_ms: float = float("nan")
    """The offset the final run's check concluded was left (NaN: it did not conclude)."""
    offset_passes: int = 0
    rotation_found_deg: float = float("nan")
    """The correction of the extrinsic's rotation ``run_bag`` restarted with (NaN: none)."""
    rotation_passes: int = 0
    rotation_left_deg: float = float("nan")
    """The rotation the final run's check concluded was left (NaN: it did not conclude)."""
    rotation_error_deg: float = float("nan")
    """The final extrinsic's rotation (the run's config.yaml) against the simulated one."""
    gross_found_deg: float = float("nan")
    """The gross rotation error ``run_bag`` restarted with first (NaN: none)."""
    gross_refused_deg: float = float("nan")
    """A gross rotation the run refused (``RunResult.extrinsic_rotation_gross_refuted``)."""
    gross_checked_deg: float = float("nan")
    """Where the gross rotation check closed finding none: its last estimate's angle and
    largest standard deviation (NaN: no estimate, or it found one)."""
    gross_checked_sigma_deg: float = float("nan")
    offset_unsettled_s: float = float("nan")
    """The final run's time offset check closed unsettled after this many seconds of updates
    (``RunResult.time_offset_unsettled``; NaN: it concluded)."""
    rotation_unsettled_s: float = float("nan")
    """The same for the rotation check."""
    rotation_unsettled_deg: float = float("nan")
    """... and its last estimate's angle and standard deviation (NaN: no estimate)."""
    rotation_unsettled_sigma_deg: float = float("nan")
    translation_text: str = "–"
    """What the translation check concluded ('found (+1.4, -2.1, +0.7) cm (+-0.3)', 'settled
    ...', 'unsettled 60 s ...', '–' off)."""
    translation_found: bool = False
    """The check flagged a significant correction (cells.json; the text says 'found')."""
    translation_left_cm: float = float("nan")
    """How far the configured lever arm, plus the correction where the check found (flagged)
    one, is from the simulated one."""
    """Which IMU white-noise densities the filter used (``InitReport.noise_used``)."""

    @property
    def pose_ratio(self) -> float:
        return self.poses / self.scans if self.scans else 0.0

    def passes(self) -> bool:
        ok = (not self.error and self.pose_ratio >= TARGET_POSES[self.start]
              and self.ate_m <= MAX_ATE_M)
        if self.scene == "hall":
            ok = ok and self.ate_m <= TARGET_HALL_ATE_M[self.start]
        return bool(ok)


def run_cell(cell: Cell, duration_s: float | None, out_root: Path,
             overrides: dict[str, str]) -> Cell:
    lidar, columns = LIDARS[cell.lidar]
    sim = cached_sequence(cell.scene, seed=cell.seed, duration_s=duration_s, lidar=lidar,
                          columns=columns, imu_noise_scale=cell.imu_noise,
                          T_imu_lidar=MOUNTINGS[cell.mounting], imu_rate_hz=cell.imu_rate_hz,
                          motion_from=cell.motion_from, lidar_rate_hz=cell.lidar_rate_hz,
                          imu_time_offset_s=cell.imu_time_offset_ms * 1e-3,
                          imu_scale_error_pct=cell.imu_scale_error_pct, people=cell.people,
                          lidar_tilt_deg=cell.lidar_tilt_deg, imu_bias_scale=cell.imu_bias_scale,
                          ghosts=cell.ghosts, dust=cell.dust, pace=cell.pace,
                          imu_vibration=cell.imu_vibration)
    meta = json.loads(sim.meta_path.read_text())
    cfg = load_config(config_file=sim.config_path, overrides=overrides)
    T_true = cfg.T_imu_lidar()
    if cell.extrinsic_error_deg:
        cfg.sensor.T_imu_lidar = turned_extrinsic(T_true, cell.extrinsic_error_deg,
                                                  cell.seed).tolist()
    if cell.extrinsic_translation_error_cm:
        cfg.sensor.T_imu_lidar = shifted_extrinsic(cfg.T_imu_lidar(),
                                                   cell.extrinsic_translation_error_cm,
                                                   cell.seed).tolist()
    start_s = cell.cut_s
    cell.scans = int(meta["n_scans"] - round(start_s * meta["lidar_rate_hz"]))
    cut = f"{cell.cut_s:g}" if cell.start == "moving" else ""
    other = "" if cell.mounting == "default" else f"_{cell.mounting}"
    other += "" if cell.imu_rate_hz == IMU_RATE_HZ else f"_{cell.imu_rate_hz:g}hz"
    other += "" if cell.lidar_rate_hz == LIDAR_RATE_HZ else f"_lidar{cell.lidar_rate_hz:g}hz"
    other += "" if cell.motion_from is None else f"_hand-{Path(cell.motion_from).stem}"
    other += "" if not cell.imu_time_offset_ms else f"_imu{cell.imu_time_offset_ms:+g}ms"
    other += "" if not cell.extrinsic_error_deg else f"_rot{cell.extrinsic_error_deg:g}deg"
    other += "" if not cell.extrinsic_translation_error_cm else \
        f"_lever{cell.extrinsic_translation_error_cm:g}cm"
    other += "" if not cell.imu_scale_error_pct else f"_scale{cell.imu_scale_error_pct:g}pct"
    other += "" if not cell.people else f"_people{cell.people}"
    other += "" if not cell.lidar_tilt_deg else f"_tilt{cell.lidar_tilt_deg:g}deg"
    other += "" if cell.imu_bias_scale == 1.0 else f"_bias{cell.imu_bias_scale:g}x"
    other += "" if not cell.ghosts else f"_ghosts{cell.ghosts:g}"
    other += "" if not cell.dust else f"_dust{cell.dust:g}"
    other += "" if cell.pace == 1.0 else f"_pace{cell.pace:g}"
    other += "" if not cell.imu_vibration else f"_vib{cell.imu_vibration:g}"
    out = out_root / (f"{cell.scene}_s{cell.seed}_imu{cell.imu_noise:g}_{cell.lidar}_"
                      f"{cell.start}{cut}{other}")
    try:
        res = run_bag(sim.bag_path, cfg, out, progress=False, start_s=start_s)
    except Exception as exc:  # noqa: BLE001 - a failed cell is reported, the matrix goes on
        cell.error = f"{type(exc).__name__}: {exc}".splitlines()[0][:160]
        return cell
    cell.poses = res.n_scans
    cell.init = res.init_report.method if res.init_report is not None else "none"
    if res.init_report is not None:
        cell.init_wait_s = float(res.init_report.wait_s)
        cell.refused_fits = int(res.init_report.refused_fits)
        cell.backfilled = int(res.init_report.backfilled)
        cell.filter_noise = res.init_report.noise_used
    cell.ms_per_scan = res.ms_per_scan_median
    if res.time_offset_found is not None:
        cell.offset_found_ms = res.time_offset_found.offset_s * 1e3
        cell.offset_passes = len(res.time_offset_found.passes)
    if res.time_offset is not None:
        cell.offset_left_ms = res.time_offset.offset_s * 1e3
    gross = res.extrinsic_rotation_gross_found
    if gross is not None:
        cell.gross_found_deg = float(np.degrees(gross.angle_rad))
    refused = getattr(res, "extrinsic_rotation_gross_refuted", None)
    if refused is not None:
        cell.gross_refused_deg = float(np.degrees(refused[0].angle_rad))
    checked = res.extrinsic_rotation_gross_checked
    if checked is not None:
        cell.gross_checked_deg = float(np.degrees(checked.angle_rad))
        cell.gross_checked_sigma_deg = float(np.degrees(checked.sigma_rad))
    if res.extrinsic_rotation_found is not None:
        cell.rotation_found_deg = res.extrinsic_rotation_found.angle_deg
        cell.rotation_passes = len(res.extrinsic_rotation_found.passes)
    if res.extrinsic_rotation is not None:
        cell.rotation_left_deg = float(np.degrees(res.extrinsic_rotation.angle_rad))
    if res.time_offset_unsettled is not None:
        cell.offset_unsettled_s = res.time_offset_unsettled.span_s
    if res.extrinsic_rotation_unsettled is not None:
        cell.rotation_unsettled_s = res.extrinsic_rotation_unsettled.span_s
        est = res.extrinsic_rotation_unsettled.estimate
        if est is not None:
            cell.rotation_unsettled_deg = float(np.degrees(est.angle_rad))
            cell.rotation_unsettled_sigma_deg = float(np.degrees(est.sigma_rad))
    t_cfg = np.asarray(cfg.sensor.T_imu_lidar)[:3, 3]
    tr = res.extrinsic_translation
    if tr is not None:
        cell.translation_found = bool(tr.significant)
        cell.translation_text = f"{'found' if tr.significant else 'settled'} {tr.text()}"
        if tr.significant:  # the correction the summary's line gives
            t_cfg = t_cfg + tr.horizontal_m
    elif res.extrinsic_translation_unsettled is not None:
        est = res.extrinsic_translation_unsettled.estimate
        cell.translation_text = (f"unsettled {res.extrinsic_translation_unsettled.span_s:.0f} s"
                                 + ("" if est is None else f" {est.text()}"))
    cell.translation_left_cm = float(100 * np.linalg.norm(t_cfg - T_true[:3, 3]))
    R_used = np.asarray(load_config(config_file=res.config_path).sensor.T_imu_lidar)[:3, :3]
    cell.rotation_error_deg = float(np.degrees(
        Rotation.from_matrix(R_used @ T_true[:3, :3].T).magnitude()))
    if res.gyro_scale_found is not None:
        cell.scale_found_pct = res.gyro_scale_found.largest_pct
        cell.scale_passes = len(res.gyro_scale_found.passes)
    sc = res.gyro_scale if res.gyro_scale is not None else (
        None if res.gyro_scale_unsettled is None else res.gyro_scale_unsettled.estimate)
    if sc is not None:
        cell.scale_left_pct, cell.scale_left_sigma_pct = 100 * sc.largest, 100 * sc.sigma
    S_used = np.asarray(load_config(config_file=res.config_path).sensor.gyro_sensitivity)
    S_true = np.eye(3) + np.asarray(meta.get("imu_gyro_sensitivity_error", np.zeros((3, 3))))
    left = np.linalg.solve(S_used, S_true) - np.eye(3)
    cell.scale_error_pct = float(100 * np.abs(0.5 * (left + left.T)).max())
    cell.ate_m = float(ate(res.trajectory_path, sim.gt_path, align="se3")["rmse_m"])
    left_out, n_map = getattr(res, "map_left_out", (0, 0))  # (0, 0): code before session 91
    cell.map_left_out = left_out / n_map if n_map else float("nan")
    with contextlib.suppress(InputError):
        cell.map_off_scene = map_off_scene(res.map_path, res.trajectory_path, sim.gt_path,
                                           sim.meta_path)
        cell.map_points = len(read_map_points(res.map_path))
    dense_path = getattr(res, "dense_map_path", None)  # None: the code before session 93
    if dense_path is not None:
        with contextlib.suppress(InputError):
            cell.dense_off_scene = map_off_scene(dense_path, res.trajectory_path, sim.gt_path,
                                                 sim.meta_path)
            cell.dense_points = len(read_map_points(dense_path))
    with contextlib.suppress(InputError):
        scans = read_scans_csv(out / "scans.csv")
        n_raw = np.maximum(scans["n_raw"], 1)
        cell.stray_share = float(scans["n_stray"].sum() / n_raw.sum())
        cell.stray_scan_max = float((scans["n_stray"] / n_raw).max())
        cell.stray_dropped_scans = float((scans["n_stray_dropped"] > 0).mean())
        cons = sigma_consistency(res.trajectory_path, sim.gt_path, scans)
        cell.within_3sigma = [float(v) for v in cons.within_3sigma]
        if len(cons.errors_world_m):
            cell.max_error_first_m = float(np.linalg.norm(cons.errors_world_m, axis=1).max())
        cell.mean_nees = cons.mean_nees
        cell.median_abs_z = [float(v) for v in cons.median_abs_z]
        cell.backfill_err_m = cons.backfill_max_error_m
    return cell


def _dense_cell(c: Cell) -> str:
    """'418303 (13.7x), 0.00 %': the dense map's points, their multiple of the written map's,
    and its share off the scene ('–': none written)."""
    if not c.dense_points:
        return "–"
    times = f" ({c.dense_points / c.map_points:.1f}x)" if c.map_points else ""
    return f"{c.dense_points}{times}, {share_cell(c.dense_off_scene)}"


def share_cell(share: float) -> str:
    """'1.23 %' ('–' for NaN)."""
    return "–" if not np.isfinite(share) else f"{100 * share:.2f} %"


def sigma_cells(w: np.ndarray) -> str:
    """'x / y / z %' of within-3-sigma shares (rows: cells; mean with the worst in brackets)."""
    if not np.isfinite(w).any():
        return "–"
    return " / ".join(f"{100 * np.nanmean(w[:, k]):.0f} ({100 * np.nanmin(w[:, k]):.0f})"
                      for k in range(3)) + " %"


def wait_cells(wait_s: np.ndarray) -> str:
    """'median (max) s' of the initialization waits (NaN: no initialization)."""
    if not np.isfinite(wait_s).any():
        return "–"
    return f"{np.nanmedian(wait_s):.1f} ({np.nanmax(wait_s):.1f}) s"


def cm(x: float) -> str:
    return "–" if not np.isfinite(x) else f"{x * 100:.2f} cm"


def _lidar_label(c: Cell) -> str:
    """The LiDAR, and the mounting, the IMU's rate and the LiDAR's when they are not the
    simulator's defaults."""
    other = [] if c.mounting == "default" else [c.mounting]
    other += [] if c.imu_rate_hz == IMU_RATE_HZ else [f"{c.imu_rate_hz:g} Hz IMU"]
    other += [] if c.lidar_rate_hz == LIDAR_RATE_HZ else [f"{c.lidar_rate_hz:g} Hz"]
    other += [] if not c.imu_time_offset_ms else [f"IMU {c.imu_time_offset_ms:+g} ms"]
    other += [] if not c.extrinsic_error_deg else [f"rotation {c.extrinsic_error_deg:g}° off"]
    other += [] if not c.extrinsic_translation_error_cm else [
        f"lever arm {c.extrinsic_translation_error_cm:g} cm off"]
    other += [] if not c.imu_scale_error_pct else [f"IMU scales {c.imu_scale_error_pct:g} %"]
    other += [] if not c.people else [f"{c.people} people"]
    other += [] if not c.lidar_tilt_deg else [f"tilted {c.lidar_tilt_deg:g}°"]
    other += [] if c.imu_bias_scale == 1.0 else [f"IMU bias x{c.imu_bias_scale:g}"]
    other += [] if not c.ghosts else [f"{100 * c.ghosts:g} % ghosts"]
    other += [] if not c.dust else [f"{100 * c.dust:g} % dust"]
    other += [] if c.pace == 1.0 else [f"pace x{c.pace:g}"]
    other += [] if not c.imu_vibration else [f"IMU shaking x{c.imu_vibration:g}"]
    return f"{c.lidar} ({', '.join(other)})" if other else c.lidar


def _refuse_outside(flag: str, values: list[float], lo: float, hi: float) -> None:
    """One ``error:`` line and exit 2 (SystemExit) for the first value outside ``lo``-``hi``."""
    for v in values:
        if not lo <= v <= hi:
            raise SystemExit(f"error: {flag} must be {lo:g}-{hi:g} (got {v:g})")


def shifted_extrinsic(T: np.ndarray, cm: float, seed: int) -> np.ndarray:
    """``T`` with its translation moved by ``cm`` centimetres along a unit direction drawn from
    ``seed`` (the same for every scene and IMU of that seed)."""
    direction = np.random.default_rng(2000 + seed).normal(size=3)
    out = np.array(T, dtype=np.float64)
    out[:3, 3] += 1e-2 * cm * direction / np.linalg.norm(direction)
    return out


def _translation_cell(c: Cell) -> str:
    """'found (+1.4, -2.1, +0.7) cm (+-0.3), 1.2 cm': what the translation check concluded, and
    how far the lever arm (corrected where it concluded) is from the simulated one."""
    return f"{c.translation_text}, {c.translation_left_cm:.1f} cm"


MAX_EXTRINSIC_ERROR_DEG = 180.0
"""``--extrinsic-errors-deg``: larger turns are not a calibration error but a wrong mounting."""


def turned_extrinsic(T: np.ndarray, deg: float, seed: int) -> np.ndarray:
    """``T`` with its rotation turned by ``deg`` degrees about a unit axis drawn from ``seed``
    (the same axis for every scene and IMU of that seed)."""
    axis = np.random.default_rng(1000 + seed).normal(size=3)
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = Rotation.from_rotvec(np.deg2rad(deg) * axis / np.linalg.norm(axis)).as_matrix() \
        @ out[:3, :3]
    return out


def _rotation_cell(c: Cell) -> str:
    """'1.02° (2), 0.03°, 0.08°': the rotation run_bag restarted with (passes), what the final
    run's check left ('unsettled 60 s (0.63° ±0.16)': it closed without a conclusion after 60 s
    of updates, at that estimate), and the final extrinsic's error ('–' where none); after a
    gross error, 'gross 89.8° + ' before the rotation the fine check found then ('gross 13.5°
    refused + ' where the run refused it and the fine check went on from the configured one)."""
    found = "–" if not np.isfinite(c.rotation_found_deg) else \
        f"{c.rotation_found_deg:.2f}° ({c.rotation_passes})"
    if np.isfinite(c.gross_found_deg):
        found = f"gross {c.gross_found_deg:.1f}° + {found}"
    if np.isfinite(c.gross_refused_deg):
        found = f"gross {c.gross_refused_deg:.1f}° refused + {found}"
    left = "–" if not np.isfinite(c.rotation_left_deg) else f"{c.rotation_left_deg:.2f}°"
    if np.isfinite(c.rotation_unsettled_s):
        left = f"unsettled {c.rotation_unsettled_s:.0f} s"
        if np.isfinite(c.rotation_unsettled_deg):
            left += f" ({c.rotation_unsettled_deg:.2f}° ±{c.rotation_unsettled_sigma_deg:.2f})"
    return f"{found}, {left}, {c.rotation_error_deg:.2f}°"


def _scale_cell(c: Cell) -> str:
    """'1.85 % (3), 0.12 % (+-0.05), 0.21 %': the gyro scale correction run_bag restarted with
    (passes), the final run's estimate, and the gyro's scale error left ('–' where none)."""
    found = "–" if not np.isfinite(c.scale_found_pct) else \
        f"{c.scale_found_pct:.2f} % ({c.scale_passes})"
    left = "–" if not np.isfinite(c.scale_left_pct) else \
        f"{c.scale_left_pct:.2f} % (+-{c.scale_left_sigma_pct:.2f})"
    return f"{found}, {left}, {c.scale_error_pct:.2f} %"


def _offset_cell(c: Cell) -> str:
    """'+21.0 ms (2), +0.3 ms': the offset run_bag restarted with (passes), and what the final
    run's check left ('–' where none)."""
    found = "–" if not np.isfinite(c.offset_found_ms) else \
        f"{c.offset_found_ms:+.1f} ms ({c.offset_passes})"
    left = "–" if not np.isfinite(c.offset_left_ms) else f"{c.offset_left_ms:+.1f} ms"
    if np.isfinite(c.offset_unsettled_s):
        left = f"unsettled {c.offset_unsettled_s:.0f} s"
    return f"{found}, {left}"


def _summary_key(c: Cell) -> tuple:
    """What a summary row groups its cells by: everything but the seed, the LiDAR and the
    moving start's cut."""
    return (c.scene, c.start, c.imu_noise, c.mounting, c.imu_rate_hz, c.lidar_rate_hz,
            c.imu_time_offset_ms, c.extrinsic_error_deg, c.extrinsic_translation_error_cm,
            c.imu_scale_error_pct, c.people, c.lidar_tilt_deg, c.imu_bias_scale, c.ghosts,
            c.dust, c.pace, c.imu_vibration)


def summary_table(cells: list[Cell]) -> str:
    lines = [("| scene | start | IMU noise | LiDARs | runs | poses/scans min | ATE mean | "
              "ATE worst | runs > 1 m or failed | largest error > 1 m (first pose) or failed | "
              "init | init after, median (max) | target | "
              "within 3σ x / y / z | map off the scene, mean (worst) |"),
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    keys = sorted({_summary_key(c) for c in cells},
                  key=lambda k: (k[0], k[1] != "still", k[2], k[3] != "default", k[3], -k[4],
                                 k[5], k[6], k[7], k[8], k[9], k[10], k[11], k[12], k[13],
                                 k[14]))
    for key in keys:
        scene, start, noise = key[:3]
        cs = [c for c in cells if _summary_key(c) == key]
        ates = np.array([c.ate_m for c in cs])
        off = np.array([c.map_off_scene for c in cs])
        off = off if np.isfinite(off).any() else np.array([0.0]) * np.nan
        on_track = ates[ates <= MAX_ATE_M]  # mean and worst of these
        inits = sorted({c.init or "error" for c in cs})
        ok = all(c.passes() for c in cs)
        lines.append(
            f"| {scene} | {start} | x{noise:g} | {', '.join(sorted({_lidar_label(c) for c in cs}))} | "
            f"{len(cs)} | {100 * min(c.pose_ratio for c in cs):.1f} % | "
            f"{cm(float(on_track.mean())) if on_track.size else '–'} | "
            f"{cm(float(on_track.max())) if on_track.size else '–'} | "
            f"{ates.size - on_track.size} | "
            f"{sum(not c.max_error_first_m <= MAX_ATE_M for c in cs)} | "
            f"{'/'.join(inits)} | {wait_cells(np.array([c.init_wait_s for c in cs]))} | "
            f"{'pass' if ok else 'FAIL'} | "
            f"{sigma_cells(np.array([c.within_3sigma for c in cs]))} | "
            f"{share_cell(float(np.nanmean(off)))} ({share_cell(float(np.nanmax(off)))}) |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["hall", "corridor"])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--first-seed", type=int, default=0,
                    help="seeds first-seed .. first-seed + seeds - 1")
    ap.add_argument("--imu-noise", nargs="+", type=float, default=[1.0, 10.0])
    ap.add_argument("--lidars", nargs="+", default=DEFAULT_LIDARS, choices=list(LIDARS),
                    help="simulated LiDARs (LIDARS; default: " + " ".join(DEFAULT_LIDARS)
                    + "; mid360: a Livox Mid-360-like non-repetitive LiDAR, CustomMsg; avia: a "
                    "Livox Avia-like forward-looking rosette, CustomMsg)")
    ap.add_argument("--mountings", nargs="+", default=["default"], choices=list(MOUNTINGS),
                    help="IMU-LiDAR mountings to simulate (MOUNTINGS)")
    ap.add_argument("--imu-bias-scales", nargs="+", type=float, default=[1.0],
                    help="the simulated IMU's initial biases and bias walks x this (default 1: "
                    "the BMI085's); the runs' configs do not say it")
    ap.add_argument("--imu-rates", nargs="+", type=float, default=[IMU_RATE_HZ],
                    help="IMU sample rates to simulate, Hz (default: the BMI085's 400)")
    ap.add_argument("--lidar-rates", nargs="+", type=float, default=[LIDAR_RATE_HZ],
                    help="LiDAR sweep rates to simulate, Hz (default 10; the columns per "
                    "sweep stay the LiDAR's)")
    ap.add_argument("--imu-time-offsets-ms", nargs="+", type=float, default=[0.0],
                    help="the simulated IMU's stamps run this many ms late against the "
                    "LiDAR's (default 0); the runs' configs do not say it")
    ap.add_argument("--extrinsic-errors-deg", nargs="+", type=float, default=[0.0],
                    help="the runs' configs give the extrinsic's rotation this many degrees off "
                    "the simulated one, about an axis drawn from the seed (default 0)")
    ap.add_argument("--extrinsic-translation-errors-cm", nargs="+", type=float, default=[0.0],
                    help="the runs' configs give the lever arm this many cm off the simulated "
                    "one, along a direction drawn from the seed (default 0)")
    ap.add_argument("--imu-scale-errors-pct", nargs="+", type=float, default=[0.0],
                    help="the simulated gyro's and accelerometer's sensitivity errors (scale "
                    "factors and cross-axis), standard deviation per entry in %% (default 0); "
                    "the runs' configs do not say them")
    ap.add_argument("--people", nargs="+", type=int, default=[0],
                    help=f"people walking along the route while the rig does (0-{MAX_PEOPLE}, "
                    "default 0)")
    ap.add_argument("--lidar-tilts-deg", nargs="+", type=float, default=[0.0],
                    help="the LiDAR pitched this many degrees nose down on the handle, the IMU "
                    f"fixed to it (within +-{MAX_LIDAR_TILT_DEG:g}, default 0: level)")
    ap.add_argument("--ghosts", nargs="+", type=float, default=[0.0],
                    help="share of the returns simulated 0.3-2.0 m behind their surface along "
                    f"their ray: multipath, cross-talk (0-{MAX_STRAY_FRACTION:g}, default 0)")
    ap.add_argument("--dust", nargs="+", type=float, default=[0.0],
                    help="share of the returns simulated 0.3-2.0 m in front of their surface "
                    f"along their ray: dust (0-{MAX_STRAY_FRACTION:g}, default 0)")
    ap.add_argument("--paces", nargs="+", type=float, default=[1.0],
                    help="walk the route this many times as fast as the scene's speeds "
                    f"({PACE_RANGE[0]:g}-{PACE_RANGE[1]:g}, default 1)")
    ap.add_argument("--imu-vibrations", nargs="+", type=float, default=[0.0],
                    help="white noise of this many times the IMU's densities while the rig "
                    f"moves (0-{MAX_IMU_VIBRATION:g}, default 0)")
    ap.add_argument("--starts", nargs="+", default=["still", "moving"],
                    choices=["still", "moving"])
    ap.add_argument("--duration", type=float, default=0.0,
                    help="seconds of each simulated walk (0 = the whole route)")
    ap.add_argument("--cut-s", nargs="+", type=float, default=[8.0, 10.0, 12.0],
                    help="moving start: seconds cut from the bag (one run per value)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every run (e.g. imu.noise_source=measured)")
    ap.add_argument("--motion-from", default=None, metavar="TUM",
                    help="walk with this recording's hand motion instead of the synthetic one "
                    "(as bench_modes.py); 'none': no hand motion (a robot's walk)")
    ap.add_argument("--out", type=Path, default=Path("runs/bench_sensors"))
    args = ap.parse_args(argv)
    overrides = parse_overrides(args.set)
    try:  # before any run: a rate the simulator refuses is one error line
        for rate in args.lidar_rates:
            lidar_model("xt32", None, rate)
    except InputError as exc:
        raise SystemExit(f"error: {exc}") from None
    for rate in args.imu_rates:
        if not MIN_IMU_RATE_HZ <= rate <= MAX_IMU_RATE_HZ:
            raise SystemExit(f"error: --imu-rates: the simulator's --imu-rate must be "
                             f"{MIN_IMU_RATE_HZ:g}-{MAX_IMU_RATE_HZ:g} Hz (got {rate:g})")
    for offset in args.imu_time_offsets_ms:
        if not abs(offset) <= MAX_IMU_TIME_OFFSET_S * 1e3:
            raise SystemExit(f"error: --imu-time-offsets-ms must be within "
                             f"+-{MAX_IMU_TIME_OFFSET_S * 1e3:g} (got {offset:g})")
    for turn in args.extrinsic_errors_deg:
        if not abs(turn) <= MAX_EXTRINSIC_ERROR_DEG:
            raise SystemExit(f"error: --extrinsic-errors-deg must be within "
                             f"+-{MAX_EXTRINSIC_ERROR_DEG:g} (got {turn:g})")
    _refuse_outside("--imu-scale-errors-pct", args.imu_scale_errors_pct, 0.0,
                    MAX_IMU_SCALE_ERROR_PCT)
    for bias in args.imu_bias_scales:
        if not bias >= 0:
            raise SystemExit(f"error: --imu-bias-scales must be >= 0 (got {bias:g})")
    _refuse_outside("--people", args.people, 0, MAX_PEOPLE)
    for tilt in args.lidar_tilts_deg:
        if not abs(tilt) <= MAX_LIDAR_TILT_DEG:
            raise SystemExit(f"error: --lidar-tilts-deg must be within "
                             f"+-{MAX_LIDAR_TILT_DEG:g} (got {tilt:g})")
    for flag, fractions in (("--ghosts", args.ghosts), ("--dust", args.dust)):
        for frac in fractions:
            if not 0.0 <= frac <= MAX_STRAY_FRACTION:
                raise SystemExit(f"error: {flag} must be a fraction 0-{MAX_STRAY_FRACTION:g} "
                                 f"(got {frac:g})")
    _refuse_outside("--imu-vibrations", args.imu_vibrations, 0.0, MAX_IMU_VIBRATION)
    _refuse_outside("--paces", args.paces, *PACE_RANGE)
    duration = args.duration or None
    cells = []
    t0 = time.perf_counter()
    print("| scene | seed | IMU noise | LiDAR | start | poses/scans | init | ATE SE(3) | "
          "ms/scan | within 3σ x / y / z | median abs(error) / σ | backfilled, worst error | "
          "IMU time offset found (passes), left | LiDAR-IMU rotation found (passes), left, "
          "final error | LiDAR-IMU translation, lever arm's error | gyro scale found (passes), "
          "left, final error | map off the scene (left out of it); dense map's points (x the "
          "map's), off the scene | stray returns, largest in "
          "a scan, scans "
          "dropping them | error |\n"
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
          flush=True)
    starts = [("still", 0.0)] if "still" in args.starts else []
    starts += [("moving", c) for c in args.cut_s] if "moving" in args.starts else []
    for scene in args.scenes:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            for noise in args.imu_noise:
                for (lidar, mounting, rate, lidar_rate, offset, turn, lever,
                     scale, people, tilt, bias, ghosts, dust, pace, vib) in itertools.product(
                        args.lidars, args.mountings, args.imu_rates, args.lidar_rates,
                        args.imu_time_offsets_ms, args.extrinsic_errors_deg,
                        args.extrinsic_translation_errors_cm, args.imu_scale_errors_pct,
                        args.people, args.lidar_tilts_deg, args.imu_bias_scales,
                        args.ghosts, args.dust, args.paces, args.imu_vibrations):
                    for start, cut_s in starts:
                        c = run_cell(Cell(scene, seed, noise, lidar, start, cut_s, mounting,
                                          rate, lidar_rate, args.motion_from, offset, turn,
                                          lever, scale, people=people,
                                          lidar_tilt_deg=tilt, imu_bias_scale=bias,
                                          ghosts=ghosts, dust=dust, pace=pace,
                                          imu_vibration=vib),
                                     duration, args.out,
                                     overrides)
                        cells.append(c)
                        label = f"moving {cut_s:g} s" if start == "moving" else start
                        print(f"| {scene} | {seed} | x{noise:g} | {_lidar_label(c)} | {label} | "
                              f"{c.poses}/{c.scans} ({100 * c.pose_ratio:.0f} %) | "
                              f"{c.init} after {c.init_wait_s:.1f} s | "
                              f"{cm(c.ate_m)} | {c.ms_per_scan:.1f} | "
                              f"{sigma_cells(np.array([c.within_3sigma]))} | "
                              f"{' / '.join(f'{v:.2f}' for v in c.median_abs_z)} | "
                              f"{c.backfilled} ({cm(c.backfill_err_m)}) | "
                              f"{_offset_cell(c)} | {_rotation_cell(c)} | "
                              f"{_translation_cell(c)} | {_scale_cell(c)} | "
                              f"{share_cell(c.map_off_scene)} "
                              f"({share_cell(c.map_left_out)}); {_dense_cell(c)} | "
                              f"{share_cell(c.stray_share)}, {share_cell(c.stray_scan_max)}, "
                              f"{share_cell(c.stray_dropped_scans)} | {c.error} |",
                              flush=True)
    print()
    print(summary_table(cells))
    print(f"\n{len(cells)} runs in {time.perf_counter() - t0:.0f} s; command: python "
          f"benchmarks/bench_sensors.py {shlex.join(argv if argv is not None else sys.argv[1:])}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "cells.json").write_text(json.dumps([asdict(c) for c in cells], indent=1))
    return 0 if all(c.passes() for c in cells) else 1


if __name__ == "__main__":
    raise SystemExit(main())
