"""Benchmark: adalio against the PyPI peers rko-lio, kiss-icp and genz-icp (issue #15).

Every system runs in this one process, back to back, on the same simulator sequence
(``adalio.sim.cached_sequence``, XT-32, ROS 2 MCAP with zstd). The bag is decoded once into memory
with ``adalio.io.bag.Bag`` + ``adalio.io.sequencer.Sequencer`` exactly as
``adalio.pipeline.run_bag`` does, so every system gets the same points (LiDAR frame, metres), the
same absolute per-point times (int64 ns) and the same IMU samples; the extrinsic ``T_imu_lidar``
is the sequence's own (``sensor.T_imu_lidar`` of its ``config.yaml``).

How each system is fed (only the per-scan call is timed, after a short untimed warm-up pass that
also takes numba compilation out of the timings):

* adalio: ``Odometry.add_imu`` per sequencer batch, ``Odometry.add_scan(points, t_ns, ring)`` timed
  (the rings, as ``adalio run`` passes them, for the stray-return test; before session 88 none).
* rko-lio: base frame = IMU (``extrinsic_imu2base = I``, ``extrinsic_lidar2base = T_imu_lidar``);
  every IMU sample older than the scan end goes in with ``add_imu_measurement`` first (as its own
  ``LidarIMUSequencer`` does), then ``register_scan(points, t_ns, start, end)`` is timed.
  ``initialization_phase`` is on (the sequences start at rest): it levels the world with the mean
  accelerometer between the first two scans; off, rko-lio takes the first base frame as level,
  and the simulated (HILTI) IMU is upside down. Poses (base = IMU in its world) with their stamps
  (scan ends) come from ``poses_with_timestamps()``, which also holds the levelled first pose
  that ``pose()`` never returned.
* kiss-icp / genz-icp: LiDAR only, ``register_frame(points, timestamps)`` timed, deskew on. kiss-icp
  normalizes the per-point times itself and deskews to the scan end; genz-icp uses them as given
  (``t - 0.5`` times the last motion), so it gets times normalized to [0, 1] and its pose is the
  mid-scan one. Their LiDAR poses become IMU poses by
  ``T_world_imu = T_imu_lidar @ T_lidar0_lidar @ inv(T_imu_lidar)``. genz-icp keeps its adaptive
  voxel size in a function-local static of its C++ core, so its first scans depend on what it ran
  on before in this process (the warm-up, the previous sequence).

Peers use ``--peer-max-range`` (m) and adalio's ``preprocess.blind_m`` as their range gate,
otherwise their package defaults (kiss-icp voxel = max range / 100, as its ``load_config``).

Per system: median / p90 / mean ms of the per-scan call over the same scan window for everyone
(from the 6th scan adalio estimated on, i.e. after its initialization), ATE RMSE after SE(3)
alignment against ``gt.tum`` (``adalio.eval.metrics.ate``, cm), poses / scans and a status (a crash
or a max error above ``--diverge-m`` is reported, the benchmark goes on). The figure of merit is
the ratio adalio / fastest working peer and adalio / rko-lio (absolute times are noisy on a shared
machine). It also reports adalio's whole ``run`` per scan (``run_bag(...).wall_s / n_scans_in``:
bag decoding, undistortion, sequencer, estimator and writers) on the same bag. ``--repeat k`` runs
every timed pass k times, interleaved across systems, and reports the median of the k medians.

``--floor`` adds one more adalio pass that splits each scan's time into the time spent inside
adalio's compiled (numba) kernels and the rest (the Python around them): every kernel a module of
``adalio.lio`` calls from Python is wrapped by a timer for that pass (calls from kernel to kernel
are compiled in and not seen). The kernels' sum is what the same kernels would cost with no Python
at all, i.e. a floor for this method at today's kernels; it is printed against 0.67x rko-lio's
median, with the map search alone. On every 10th timed scan the search's queries are also
searched again by adalio's kernel and by scipy's compiled k-d tree (``cKDTree.query``, k nearest,
all cores, tree built untimed on the same map points), a reference for what the kNN alone costs
in compiled code that is not ours.

``--busy-cores N`` keeps N cores busy with other processes while the systems run, as on a machine
doing other work; the header line says how numba's OpenMP threads wait (adalio makes them sleep,
``OMP_WAIT_POLICY=PASSIVE``, unless ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` is set: run with
``GOMP_SPINCOUNT=300000`` for GNU OpenMP's spinning default, as before session 88).

    python benchmarks/bench_peers.py --scenes hall spiral --columns 512 2000 --duration 20
    python benchmarks/bench_peers.py --scenes hall --columns 512 --busy-cores 1
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import ctypes
import gc
import importlib
import os
import shlex
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from adalio.config import MODES, Config, load_config
from adalio.eval.metrics import ate
from adalio.io.bag import Bag
from adalio.io.sequencer import Sequencer
from adalio.io.writers import TumWriter
from adalio.sim import SCENES, cached_sequence
from adalio.sim.lidar import LIDAR_MODELS
from adalio.types import ImuBatch, Scan

SYSTEMS = ("adalio", "rko-lio", "kiss-icp", "genz-icp")
PEER_MODULES = {"rko-lio": "rko_lio.lio", "kiss-icp": "kiss_icp.kiss_icp",
                "genz-icp": "genz_icp.genz_icp"}
SKIP_SCANS = 5
"""Scans left out of the timing statistics after adalio's first estimate."""


@dataclass
class Sequence:
    """A simulator sequence decoded into memory."""

    scene: str
    columns: int
    lidar: str
    """The simulator's LiDAR model (``xt32``, ``ouster64``, ``ouster128``, ``vlp16``)."""
    gt_path: Path
    bag_path: Path
    config: Config
    T_imu_lidar: np.ndarray
    items: list[ImuBatch | Scan]
    scans: list[Scan]
    imu_t_ns: np.ndarray
    imu_gyro_rad_s: np.ndarray
    imu_accel_m_s2: np.ndarray
    decode_s: float


@dataclass
class Pass:
    """One pass of one system over a sequence: per-scan call times and its IMU trajectory."""

    ms: np.ndarray
    """(n_scans,) wall ms of the per-scan call, NaN for scans never handed over."""
    t_ns: list[int] = field(default_factory=list)
    T_world_imu: list[np.ndarray] = field(default_factory=list)
    first_pose_scan: int = -1
    """Index of the first scan that produced a pose (-1: none)."""


@dataclass
class Row:
    """What the tables print for one system on one sequence."""

    system: str
    status: str = "ok"
    median_ms: float = float("nan")
    p90_ms: float = float("nan")
    mean_ms: float = float("nan")
    ate_cm: float = float("nan")
    max_err_cm: float = float("nan")
    n_poses: int = 0
    n_scans: int = 0
    passes: list[Pass] = field(default_factory=list)

    @property
    def usable(self) -> bool:
        return self.status == "ok"

    @property
    def timed(self) -> bool:
        return self.status in ("ok", "diverged") and np.isfinite(self.median_ms)


@dataclass
class Result:
    scene: str
    columns: int
    lidar: str
    n_scans: int
    pts_per_scan: float
    window: tuple[int, int]
    decode_s: float
    rows: list[Row]
    run_ms_per_scan: float = float("nan")
    run_status: str = ""
    floor: Floor | None = None


# ---------------------------------------------------------------- data


def load_sequence(scene: str, seed: int, duration_s: float | None, columns: int,
                  mode: str | None, lidar: str = "xt32", lidar_tilt_deg: float = 0.0) -> Sequence:
    """Generate (or reuse) the sequence and decode its bag once, as ``run_bag`` does
    (``lidar_tilt_deg``: the LiDAR pitched nose down on the handle, ``simulate``'s)."""
    from adalio.pipeline import resolve_extrinsic

    sim = cached_sequence(scene, seed=seed, duration_s=duration_s, lidar=lidar, fmt="mcap",
                          columns=columns, lidar_tilt_deg=lidar_tilt_deg)
    overrides = {"adaptive.mode": mode} if mode else None
    cfg = load_config(config_file=sim.config_path, overrides=overrides)
    cfg.validate()
    t0 = time.perf_counter()
    items: list[ImuBatch | Scan] = []
    with Bag(sim.bag_path) as bag:
        lidar_topic, imu_topic = bag.select_topics(cfg.sensor)
        T_imu_lidar, _ = resolve_extrinsic(bag, lidar_topic, imu_topic, cfg)
        cfg.sensor.T_imu_lidar = T_imu_lidar.tolist()
        for item in Sequencer(bag, lidar_topic, imu_topic, cfg.sensor):
            if isinstance(item, Scan):  # adalio gets the rings, as in a run (its stray test)
                item.intensity = None
            items.append(item)
    decode_s = time.perf_counter() - t0
    scans = [it for it in items if isinstance(it, Scan)]
    imu = [it for it in items if isinstance(it, ImuBatch)]
    return Sequence(
        scene=scene, columns=columns, lidar=lidar, gt_path=sim.gt_path, bag_path=sim.bag_path,
        config=cfg,
        T_imu_lidar=np.asarray(T_imu_lidar, dtype=np.float64), items=items, scans=scans,
        imu_t_ns=np.concatenate([b.t_ns for b in imu]).astype(np.int64),
        imu_gyro_rad_s=np.concatenate([b.gyro_rad_s for b in imu]),
        imu_accel_m_s2=np.concatenate([b.accel_m_s2 for b in imu]), decode_s=decode_s)


# ---------------------------------------------------------------- systems


class System:
    """One odometry behind a common driver: ``reset`` builds a fresh instance; ``imu``,
    ``before_scan``, ``prepare`` and ``pose`` are untimed; ``step`` is the timed per-scan call,
    and ``pose`` turns its output into (t_ns, T_world_imu) or None."""

    name = ""
    uses_imu_batches = False

    def __init__(self, seq: Sequence, args: argparse.Namespace) -> None:
        self.seq = seq
        self.args = args

    def reset(self) -> None:
        raise NotImplementedError

    def imu(self, batch: ImuBatch) -> None:
        """A sequencer IMU batch (only for systems with ``uses_imu_batches``)."""

    def before_scan(self, scan: Scan) -> None:
        """Untimed work before the scan (e.g. IMU samples up to its end)."""

    def prepare(self, scan: Scan) -> tuple:
        return (scan.points_lidar, scan.t_ns)

    def step(self, *inputs: Any) -> Any:
        raise NotImplementedError

    def pose(self, scan: Scan, out: Any) -> tuple[int, np.ndarray] | None:
        raise NotImplementedError

    def trajectory(self, p: Pass) -> tuple[list[int], list[np.ndarray]]:
        return p.t_ns, p.T_world_imu


class Adalio(System):
    name = "adalio"
    uses_imu_batches = True

    def reset(self) -> None:
        from adalio.lio import Odometry

        self.odom = Odometry(self.seq.config)

    def imu(self, batch: ImuBatch) -> None:
        self.odom.add_imu(batch.t_ns, batch.gyro_rad_s, batch.accel_m_s2)

    def prepare(self, scan: Scan) -> tuple:
        return (scan.points_lidar, scan.t_ns, scan.ring)

    def step(self, points: np.ndarray, t_ns: np.ndarray, ring: np.ndarray | None) -> Any:
        return self.odom.add_scan(points, t_ns, ring)

    def pose(self, scan: Scan, out: Any) -> tuple[int, np.ndarray] | None:
        return None if out is None else (int(out.t_ns), np.asarray(out.T_world_imu))


class RkoLio(System):
    name = "rko-lio"

    def reset(self) -> None:
        from rko_lio.config import LIOConfig
        from rko_lio.lio import LIO
        from rko_lio.rko_lio_pybind import InputError

        self.input_error = InputError
        self.config = LIOConfig(min_range=self.seq.config.preprocess.blind_m,
                                max_range=self.args.peer_max_range, initialization_phase=True)
        self.lio = LIO(self.config)
        self.k = 0
        self.I4 = np.eye(4)

    def before_scan(self, scan: Scan) -> None:
        seq = self.seq
        hi = int(np.searchsorted(seq.imu_t_ns, scan.t_end_ns, side="left"))
        for i in range(self.k, hi):
            self.lio.add_imu_measurement(seq.imu_accel_m_s2[i], seq.imu_gyro_rad_s[i],
                                         int(seq.imu_t_ns[i]), extrinsic_imu2base=self.I4)
        self.k = max(self.k, hi)

    def prepare(self, scan: Scan) -> tuple:
        return (scan.points_lidar, scan.t_ns, scan.t_start_ns, scan.t_end_ns)

    def step(self, points: np.ndarray, t_ns: np.ndarray, start_ns: int, end_ns: int) -> Any:
        try:
            return self.lio.register_scan(points, t_ns, extrinsic_lidar2base=self.seq.T_imu_lidar,
                                          start_time_ns=start_ns, end_time_ns=end_ns)
        except self.input_error:  # its own pipeline drops such a scan
            return None

    def pose(self, scan: Scan, out: Any) -> tuple[int, np.ndarray] | None:
        return None if out is None else (scan.t_end_ns, self.lio.pose())

    def trajectory(self, p: Pass) -> tuple[list[int], list[np.ndarray]]:
        """rko-lio's own stamped poses (base = IMU), x y z qx qy qz qw."""
        from scipy.spatial.transform import Rotation

        stamps, poses = self.lio.poses_with_timestamps()
        out = []
        for q in poses:
            q = np.asarray(q, dtype=np.float64)
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(q[3:7]).as_matrix()
            T[:3, 3] = q[:3]
            out.append(T)
        return [int(t) for t in np.asarray(stamps).ravel()], out


class _LidarOnly(System):
    """kiss-icp / genz-icp: ``register_frame(points, timestamps)``, ``last_pose`` =
    T_lidar0_lidar, turned into the IMU pose."""

    def lidar_to_imu(self, T_lidar0_lidar: np.ndarray) -> np.ndarray:
        T = self.seq.T_imu_lidar
        return T @ np.asarray(T_lidar0_lidar) @ np.linalg.inv(T)

    def step(self, points: np.ndarray, times: np.ndarray) -> Any:
        return self.odom.register_frame(points, times)

    def pose(self, scan: Scan, out: Any) -> tuple[int, np.ndarray] | None:
        return self.stamp(scan), self.lidar_to_imu(self.odom.last_pose)

    def stamp(self, scan: Scan) -> int:
        raise NotImplementedError


class KissIcp(_LidarOnly):
    name = "kiss-icp"

    def reset(self) -> None:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP

        max_r = self.args.peer_max_range
        self.config = KISSConfig(
            data={"max_range": max_r, "min_range": self.seq.config.preprocess.blind_m,
                  "deskew": True},
            mapping={"voxel_size": max_r / 100.0})
        self.odom = KissICP(self.config)

    def prepare(self, scan: Scan) -> tuple:
        """Seconds since the scan start (kiss-icp normalizes them to [0, 1] itself; absolute
        ns in float64 would lose the sub-microsecond digits)."""
        return (scan.points_lidar, (scan.t_ns - scan.t_start_ns).astype(np.float64) * 1e-9)

    def stamp(self, scan: Scan) -> int:
        return scan.t_end_ns


class GenzIcp(_LidarOnly):
    name = "genz-icp"

    def reset(self) -> None:
        from genz_icp.config import GenZConfig
        from genz_icp.genz_icp import GenZICP

        self.config = GenZConfig(
            data={"max_range": self.args.peer_max_range,
                  "min_range": self.seq.config.preprocess.blind_m, "deskew": True})
        self.odom = GenZICP(self.config)

    def prepare(self, scan: Scan) -> tuple:
        """Per-point times normalized to [0, 1] over the scan: genz-icp deskews with
        ``(t - 0.5) * log(last motion)`` and does not normalize."""
        t = (scan.t_ns - scan.t_start_ns).astype(np.float64)
        span = float(scan.t_end_ns - scan.t_start_ns)
        return (scan.points_lidar, t / span if span > 0 else np.full_like(t, 0.5))

    def stamp(self, scan: Scan) -> int:
        return (scan.t_start_ns + scan.t_end_ns) // 2


SYSTEM_CLASSES: dict[str, type[System]] = {
    "adalio": Adalio, "rko-lio": RkoLio, "kiss-icp": KissIcp, "genz-icp": GenzIcp}


@contextlib.contextmanager
def native_stdout_to_stderr() -> Iterator[None]:
    """Send what native code writes to file descriptor 1 (rko-lio's log lines) to stderr, so that
    stdout holds only the tables."""
    sys.stdout.flush()
    libc = ctypes.CDLL(None)
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        libc.fflush(None)
        os.dup2(saved, 1)
        os.close(saved)


def available_systems(wanted: list[str]) -> list[str]:
    """The wanted systems whose package imports; prints a note for each that does not."""
    out = []
    for name in wanted:
        module = PEER_MODULES.get(name)
        if module is not None:
            try:
                importlib.import_module(module)
            except ImportError as exc:
                print(f"note: {name} skipped ({exc}); install the peers with "
                      "`pip install -e .[peers]`", file=sys.stderr)
                continue
        out.append(name)
    return out


# ---------------------------------------------------------------- driving


def run_pass(system: System, seq: Sequence, max_poses: int | None = None) -> Pass:
    """Feed the whole sequence (or until ``max_poses`` poses) and time every per-scan call."""
    system.reset()
    ms = np.full(len(seq.scans), np.nan)
    p = Pass(ms=ms)
    k = 0
    gc.collect()
    for item in seq.items:
        if isinstance(item, ImuBatch):
            if system.uses_imu_batches:
                system.imu(item)
            continue
        system.before_scan(item)
        inputs = system.prepare(item)
        t0 = time.perf_counter()
        out = system.step(*inputs)
        ms[k] = (time.perf_counter() - t0) * 1e3
        pose = system.pose(item, out)
        if pose is not None:
            if p.first_pose_scan < 0:
                p.first_pose_scan = k
            p.t_ns.append(pose[0])
            p.T_world_imu.append(pose[1])
            if max_poses is not None and len(p.t_ns) >= max_poses:
                break
        k += 1
    return p


def write_tum(path: Path, t_ns: list[int], poses: list[np.ndarray]) -> None:
    with TumWriter(path) as w:
        for t, T in zip(t_ns, poses, strict=True):
            w.write(t, T)


def evaluate(row: Row, system: System, seq: Sequence, out_dir: Path, diverge_m: float) -> None:
    """ATE of the first pass, status (ok / diverged / eval failed) and poses / scans."""
    p = row.passes[0]
    t_ns, poses = system.trajectory(p)
    row.n_poses = len(t_ns)
    row.n_scans = int(np.count_nonzero(np.isfinite(p.ms)))
    if not t_ns:
        row.status = "no pose"
        return
    if not all(np.all(np.isfinite(T)) for T in poses):
        row.status = "diverged (non-finite pose)"
        return
    path = out_dir / f"{seq.scene}_c{seq.columns}_{system.name}.tum"
    write_tum(path, t_ns, poses)
    try:
        res = ate(path, seq.gt_path)
    except Exception as exc:  # noqa: BLE001 - reported in the table
        row.status = f"eval failed: {exc}".splitlines()[0][:80]
        return
    row.ate_cm = 100.0 * res["rmse_m"]
    row.max_err_cm = 100.0 * res["max_m"]
    if not res["max_m"] <= diverge_m:
        row.status = "diverged"


def timing_window(adalio_pass: Pass | None, n_scans: int) -> tuple[int, int]:
    """Scans [start, end) every system is timed on: from adalio's 6th estimate on (after its
    initialization), or from scan 6 without adalio."""
    start = SKIP_SCANS
    if adalio_pass is not None and adalio_pass.first_pose_scan >= 0:
        start = adalio_pass.first_pose_scan + SKIP_SCANS
    return min(start, n_scans), n_scans


def fill_timing(row: Row, window: tuple[int, int]) -> None:
    medians, p90s, means = [], [], []
    for p in row.passes:
        ms = p.ms[window[0]:window[1]]
        ms = ms[np.isfinite(ms)]
        if ms.size:
            medians.append(np.median(ms))
            p90s.append(np.percentile(ms, 90))
            means.append(np.mean(ms))
    if medians:
        row.median_ms = float(np.median(medians))
        row.p90_ms = float(np.median(p90s))
        row.mean_ms = float(np.median(means))


def whole_run_ms(seq: Sequence, out_dir: Path) -> tuple[float, str]:
    """adalio's ``run`` on the same bag: wall ms per scan handed to the estimator."""
    from adalio.pipeline import run_bag

    try:
        res = run_bag(seq.bag_path, seq.config, out_dir, progress=False)
    except Exception as exc:  # noqa: BLE001
        return float("nan"), f"run failed: {exc}".splitlines()[0][:80]
    return 1e3 * res.wall_s / max(res.n_scans_in, 1), ""


def bench_sequence(seq: Sequence, names: list[str], args: argparse.Namespace,
                   out_dir: Path, log: Callable[[str], None]) -> Result:
    rows = {n: Row(n) for n in names}
    systems = {n: SYSTEM_CLASSES[n](seq, args) for n in names}
    for name, system in systems.items():
        try:
            run_pass(system, seq, max_poses=args.warmup)
        except Exception as exc:  # noqa: BLE001 - one system never stops the benchmark
            rows[name].status = f"crashed: {type(exc).__name__}: {exc}".splitlines()[0][:80]
            log(f"{seq.scene} c{seq.columns} {name}: warm-up {rows[name].status}")
    run_ms: list[float] = []
    run_status = ""
    for r in range(args.repeat):
        for name, system in systems.items():
            row = rows[name]
            if row.status.startswith("crashed"):
                continue
            t0 = time.perf_counter()
            try:
                row.passes.append(run_pass(system, seq))
            except Exception as exc:  # noqa: BLE001
                row.status = f"crashed: {type(exc).__name__}: {exc}".splitlines()[0][:80]
                log(f"{seq.scene} c{seq.columns} {name}: {row.status}")
                continue
            if r == 0:
                evaluate(row, system, seq, out_dir, args.diverge_m)
            log(f"{seq.scene} c{seq.columns} {name} pass {r + 1}/{args.repeat}: "
                f"{time.perf_counter() - t0:.1f} s, ATE {row.ate_cm:.2f} cm, {row.status}")
        if "adalio" in names and not args.no_run:
            ms, run_status = whole_run_ms(seq, out_dir / f"{seq.scene}_c{seq.columns}_run")
            run_ms.append(ms)
            log(f"{seq.scene} c{seq.columns} adalio run pass {r + 1}/{args.repeat}: "
                f"{ms:.1f} ms/scan {run_status}")
    ada = rows.get("adalio")
    window = timing_window(ada.passes[0] if ada and ada.passes else None, len(seq.scans))
    for row in rows.values():
        fill_timing(row, window)
    floor = None
    if args.floor and ada is not None and ada.passes:
        floor = floor_pass(seq, args, window)
        log(f"{seq.scene} c{seq.columns} adalio floor pass: kernels {floor.kernels_ms:.2f} of "
            f"{floor.wall_ms:.2f} ms/scan")
    return Result(scene=seq.scene, columns=seq.columns, lidar=seq.lidar, n_scans=len(seq.scans),
                  pts_per_scan=float(np.median([len(s) for s in seq.scans])), window=window,
                  decode_s=seq.decode_s, rows=list(rows.values()),
                  run_ms_per_scan=float(np.median(run_ms)) if run_ms else float("nan"),
                  run_status=run_status, floor=floor)


@dataclass
class Floor:
    """adalio's per-scan time inside its compiled kernels (``--floor``), medians over the
    timed scans, ms."""

    wall_ms: float
    kernels_ms: float
    search_ms: float
    top: list[tuple[str, float]]
    """The largest kernels: (name, median ms per scan)."""
    resample_adalio_ms: float = float("nan")
    resample_kdtree_ms: float = float("nan")
    n_resampled: int = 0


SEARCH_KERNELS = ("_associate_parallel", "_associate_serial")
KERNEL_MODULES = ("associate", "degeneracy", "ieskf", "imu", "ivox", "map_uncertainty",
                  "measurement", "motion_init", "odometry", "plane", "so3", "state", "voxel")


@contextlib.contextmanager
def kernel_timers(spent: dict[str, float]) -> Iterator[None]:
    """Wrap every numba kernel that the ``adalio.lio`` modules call from Python by a timer that
    adds its wall seconds to ``spent[name]`` (outermost calls only); restored on exit."""
    from numba.core.registry import CPUDispatcher

    depth = [0]

    def wrap(name: str, f: Callable) -> Callable:
        def timed(*a: Any, **kw: Any) -> Any:
            if depth[0]:
                return f(*a, **kw)
            depth[0] += 1
            t0 = time.perf_counter()
            try:
                return f(*a, **kw)
            finally:
                spent[name] = spent.get(name, 0.0) + time.perf_counter() - t0
                depth[0] -= 1
        return timed

    patched = []
    for m in KERNEL_MODULES:
        mod = importlib.import_module(f"adalio.lio.{m}")
        for name, obj in list(vars(mod).items()):
            if isinstance(obj, CPUDispatcher):
                patched.append((mod, name, obj))
                setattr(mod, name, wrap(name, obj))
    try:
        yield
    finally:
        for mod, name, obj in patched:
            setattr(mod, name, obj)


class FloorAdalio(Adalio):
    """adalio for the ``--floor`` pass, driven by :func:`run_pass` under :func:`kernel_timers`:
    each scan's kernel seconds are kept for the scans of ``window``, and on every 10th of them
    the scan's first search is captured (on a copy of the map as it saw it) and run again, after
    the timed call, by adalio's kernel and by scipy's k-d tree on the same map points."""

    def __init__(self, seq: Sequence, args: argparse.Namespace, window: tuple[int, int],
                 spent: dict[str, float]) -> None:
        super().__init__(seq, args)
        self.window = window
        self.spent = spent
        self.k = -1
        self.captured: list[tuple] = []
        self.per_scan: list[dict[str, float]] = []
        self.ada_ms: list[float] = []
        self.tree_ms: list[float] = []

    def timed(self) -> bool:
        return self.window[0] <= self.k < self.window[1]

    def capture(self, real_associate: Callable) -> Callable:
        """A stand-in for ``odometry.associate`` that keeps the first search of a sampled scan."""
        def associate(ivox: Any, points_world: np.ndarray, *a: Any, **kw: Any) -> Any:
            if self.timed() and (self.k - self.window[0]) % 10 == 0 and not self.captured:
                self.captured.append((copy.deepcopy(ivox), np.array(points_world), a, kw))
            return real_associate(ivox, points_world, *a, **kw)
        return associate

    def before_scan(self, scan: Scan) -> None:
        self.k += 1
        self.spent.clear()
        self.captured.clear()

    def pose(self, scan: Scan, out: Any) -> tuple[int, np.ndarray] | None:
        if self.timed():
            self.per_scan.append(dict(self.spent))
        if self.captured:
            self.search_again(*self.captured[0])
        return super().pose(scan, out)

    def search_again(self, ivox: Any, queries: np.ndarray, a: tuple, kw: dict) -> None:
        from scipy.spatial import cKDTree

        from adalio.lio.associate import associate

        t0 = time.perf_counter()
        associate(ivox, queries, *a, **kw)
        self.ada_ms.append(time.perf_counter() - t0)
        tree = cKDTree(ivox.points())
        cfg = self.seq.config.filter
        t0 = time.perf_counter()
        tree.query(queries, k=cfg.knn_k, distance_upper_bound=cfg.knn_max_range_m, workers=-1)
        self.tree_ms.append(time.perf_counter() - t0)


def floor_pass(seq: Sequence, args: argparse.Namespace, window: tuple[int, int]) -> Floor:
    """One :class:`FloorAdalio` pass, summarised."""
    import adalio.lio.odometry as odo_mod

    spent: dict[str, float] = {}
    system = FloorAdalio(seq, args, window, spent)
    real_associate = odo_mod.associate
    odo_mod.associate = system.capture(real_associate)
    try:
        with kernel_timers(spent):
            p = run_pass(system, seq)
    finally:
        odo_mod.associate = real_associate
    wall = p.ms[window[0]:window[1]]
    wall = wall[np.isfinite(wall)]
    per_scan = system.per_scan

    def median_ms(values: list[float]) -> float:
        return 1e3 * float(np.median(values)) if values else float("nan")

    names = sorted({n for d in per_scan for n in d})
    med = {n: median_ms([d.get(n, 0.0) for d in per_scan]) for n in names}
    return Floor(
        wall_ms=float(np.median(wall)) if wall.size else float("nan"),
        kernels_ms=median_ms([sum(d.values()) for d in per_scan]),
        search_ms=median_ms([sum(d.get(n, 0.0) for n in SEARCH_KERNELS) for d in per_scan]),
        top=sorted(med.items(), key=lambda kv: -kv[1])[:6],
        resample_adalio_ms=median_ms(system.ada_ms),
        resample_kdtree_ms=median_ms(system.tree_ms),
        n_resampled=len(system.ada_ms))


# ---------------------------------------------------------------- tables


def ratios(res: Result) -> tuple[float, str, float]:
    """(adalio / fastest working peer, that peer, adalio / rko-lio) of the median ms."""
    by = {r.system: r for r in res.rows}
    ada = by.get("adalio")
    if ada is None or not ada.timed:
        return float("nan"), "", float("nan")
    peers = [r for r in res.rows if r.system != "adalio" and r.usable and r.timed]
    fastest = min(peers, key=lambda r: r.median_ms) if peers else None
    rko = by.get("rko-lio")
    to_rko = ada.median_ms / rko.median_ms if rko is not None and rko.timed else float("nan")
    if fastest is None:
        return float("nan"), "", to_rko
    return ada.median_ms / fastest.median_ms, fastest.system, to_rko


def fmt(v: float, spec: str = ".1f", unit: str = "") -> str:
    return "–" if not np.isfinite(v) else format(v, spec) + unit


def _sensor(res: Result) -> str:
    """``512 columns``, or with another LiDAR than the XT-32 ``ouster128, 1024 columns``."""
    return (f"{res.columns} columns" if res.lidar == "xt32"
            else f"{res.lidar}, {res.columns} columns")


def sequence_table(res: Result) -> str:
    title = (f"### {res.scene}, {_sensor(res)}: {res.n_scans} scans, "
             f"{res.pts_per_scan:.0f} points/scan, timed scans {res.window[0]}.."
             f"{res.window[1] - 1}")
    head = ("| system | median ms | p90 ms | mean ms | ATE cm | max err cm | poses/scans | "
            "status |")
    lines = [title, "", head, "|" + "---|" * 8]
    for r in res.rows:
        lines.append(f"| {r.system} | {fmt(r.median_ms)} | {fmt(r.p90_ms)} | {fmt(r.mean_ms)} | "
                     f"{fmt(r.ate_cm, '.2f')} | {fmt(r.max_err_cm, '.1f')} | "
                     f"{r.n_poses}/{r.n_scans} | {r.status} |")
    to_fast, fastest, to_rko = ratios(res)
    lines.append("")
    lines.append(f"adalio / fastest peer ({fastest or '–'}): {fmt(to_fast, '.2f', 'x')}; "
                 f"adalio / rko-lio: {fmt(to_rko, '.2f', 'x')}")
    if np.isfinite(res.run_ms_per_scan) or res.run_status:
        dec = 1e3 * res.decode_s / max(res.n_scans, 1)
        lines.append(f"adalio whole run (run_bag wall / scans in): {fmt(res.run_ms_per_scan)} "
                     f"ms/scan {res.run_status}(bag decoding + sequencer alone, as here: "
                     f"{dec:.1f} ms/scan)")
    if res.floor is not None:
        lines.append(floor_line(res))
    return "\n".join(lines)


def floor_line(res: Result) -> str:
    """``--floor``: adalio's kernels against 0.67x rko-lio's median."""
    f = res.floor
    rko = {r.system: r for r in res.rows}.get("rko-lio")
    target = 0.67 * rko.median_ms if rko is not None and rko.timed else float("nan")
    top = ", ".join(f"{n} {v:.2f}" for n, v in f.top)
    return (f"adalio floor pass (medians per scan): {fmt(f.wall_ms, '.2f')} ms, of which "
            f"{fmt(f.kernels_ms, '.2f')} ms in compiled kernels (map search "
            f"{fmt(f.search_ms, '.2f')} ms) against 0.67 x rko-lio = {fmt(target, '.2f')} ms; "
            f"largest kernels: {top}. Search re-run on {f.n_resampled} scans' maps: adalio "
            f"(kNN + plane fits) {fmt(f.resample_adalio_ms, '.2f')} ms, scipy cKDTree kNN "
            f"alone {fmt(f.resample_kdtree_ms, '.2f')} ms")


def summary_table(results: list[Result], names: list[str]) -> str:
    head = (["scene", "columns"] + [f"{n} ms" for n in names]
            + ["adalio/fastest", "adalio/rko-lio", "adalio run ms/scan"]
            + [f"ATE {n} cm" for n in names])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for res in results:
        by = {r.system: r for r in res.rows}
        to_fast, fastest, to_rko = ratios(res)
        ms = [fmt(by[n].median_ms) if by[n].timed else by[n].status.split(":")[0]
              for n in names]
        ates = [fmt(by[n].ate_cm, ".2f") + ("" if by[n].usable else f" ({by[n].status})")
                for n in names]
        cells = ([res.scene, _sensor(res).removesuffix(" columns")] + ms
                 + [f"{fmt(to_fast, '.2f', 'x')} ({fastest or '–'})", fmt(to_rko, ".2f", "x"),
                    fmt(res.run_ms_per_scan)] + ates)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------- main


def thread_note() -> str:
    import numba

    wait = (f"GOMP_SPINCOUNT={os.environ['GOMP_SPINCOUNT']}" if "GOMP_SPINCOUNT" in os.environ
            else f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}")
    return (f"{os.cpu_count()} cores; numba threads {numba.get_num_threads()} ({wait}), peers' "
            "max_num_threads 0 (= all cores, TBB)")


@contextlib.contextmanager
def busy_cores(n: int):
    """``n`` other processes that keep a core each busy while the systems run (a machine doing
    other work), stopped on the way out."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["hall", "spiral"], choices=list(SCENES))
    ap.add_argument("--columns", nargs="+", type=int, default=[512, 2000],
                    help="azimuth columns per sweep (the XT-32's 2000 = the real sensor; the "
                         "Ouster models' 1024)")
    ap.add_argument("--lidar", default="xt32", choices=list(LIDAR_MODELS),
                    help="the simulator's LiDAR model (default the XT-32)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lidar-tilt-deg", type=float, default=0.0,
                    help="the LiDAR pitched this many degrees nose down on the handle "
                         "(simulate --lidar-tilt-deg; default 0: level)")
    ap.add_argument("--duration", type=float, default=None,
                    help="sequence length in seconds (default: the full route)")
    ap.add_argument("--systems", nargs="+", default=list(SYSTEMS), choices=list(SYSTEMS))
    ap.add_argument("--mode", default=None, choices=list(MODES),
                    help="adalio adaptive.mode (default: the sequence config's)")
    ap.add_argument("--out", type=Path, default=None,
                    help="folder for the TUM trajectories and adalio's run (default: a temp dir)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="timed passes per system, interleaved; the median of medians is shown")
    ap.add_argument("--warmup", type=int, default=10,
                    help="untimed warm-up pass until this many poses per system")
    ap.add_argument("--peer-max-range", type=float, default=30.0,
                    help="max range of the peers (m); kiss-icp's voxel is 1 %% of it")
    ap.add_argument("--diverge-m", type=float, default=1.0,
                    help="a system diverged if its max SE(3)-aligned error exceeds this (m)")
    ap.add_argument("--floor", action="store_true",
                    help="one more adalio pass: time inside its compiled kernels, the search "
                         "against scipy's k-d tree")
    ap.add_argument("--no-run", action="store_true",
                    help="skip adalio's whole run (run_bag) per sequence")
    ap.add_argument("--busy-cores", type=int, default=0,
                    help="keep this many cores busy with other processes while the systems run "
                         "(a machine doing other work; default 0)")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        raise SystemExit(f"error: --repeat must be >= 1 (got {args.repeat})")
    if not 0 <= args.busy_cores <= (os.cpu_count() or 1):
        raise SystemExit(f"error: --busy-cores must be 0-{os.cpu_count() or 1} (got {args.busy_cores})")

    out_dir = (args.out.expanduser().resolve() if args.out is not None
               else Path(tempfile.mkdtemp(prefix="bench_peers_")))
    out_dir.mkdir(parents=True, exist_ok=True)
    names = available_systems(args.systems)
    t_start = time.perf_counter()

    def log(text: str) -> None:
        print(f"[{time.perf_counter() - t_start:6.0f} s] {text}", file=sys.stderr, flush=True)

    results: list[Result] = []
    for scene in args.scenes:
        for columns in args.columns:
            try:
                seq = load_sequence(scene, args.seed, args.duration, columns, args.mode,
                                    args.lidar, args.lidar_tilt_deg)
            except Exception as exc:  # noqa: BLE001
                log(f"{scene} c{columns}: sequence failed: {exc}")
                continue
            log(f"{scene} c{columns}: {len(seq.scans)} scans decoded in {seq.decode_s:.1f} s")
            with native_stdout_to_stderr(), busy_cores(args.busy_cores):
                res = bench_sequence(seq, names, args, out_dir, log)
            results.append(res)
            del seq
            print(sequence_table(res), flush=True)
            print(flush=True)
    wall = time.perf_counter() - t_start
    cmd = "python benchmarks/bench_peers.py " + " ".join(
        shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    print(f"Command: `{cmd.strip()}`  (seed {args.seed}, duration "
          f"{args.duration or 'full'} s, repeat {args.repeat}, {thread_note()}, "
          f"other processes busy on {args.busy_cores} of the cores; "
          f"took {wall:.0f} s; trajectories in {out_dir})\n")
    print(summary_table(results, names), flush=True)
    os.dup2(2, 1)  # rko-lio prints its profile to fd 1 at exit
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
