"""Live 3D view of a run with rerun (``adalio run --view`` / ``--rrd FILE``).

:class:`RerunView` receives each :class:`~adalio.types.Estimate` as it is written and logs, on
the timeline ``scan_time`` (the scan end, absolute ns) and the sequence ``scan`` (0, 1, ...):

* ``world/scan``: the downsampled scan in the world frame, blue on general scans and orange on
  degenerate ones;
* ``world/map/NNNN``: the map, decimated to one point per ``map_voxel_m`` cell; every
  ``map_every_scans`` scans the cells seen for the first time are logged as one new child, so
  each point is sent once and the map grows without re-logging it;
* ``world/trajectory``: the IMU positions so far (line strip), ``world/imu``: the IMU pose;
* ``world/weakest_direction``: the translation part of the weakest eigenvector of the scan's
  6x6 point-to-plane information (world frame, see :mod:`adalio.lio.degeneracy`), as an arrow
  at the IMU scaled by the degeneracy score (1 m for a pure translation at score 1), labelled
  with the score;
* ``plots/...``: the degeneracy score and flag, the point counts (raw, downsampled, matched)
  and the position and yaw standard deviations of ``scans.csv`` (the filter's covariance plus
  the map's, see :mod:`adalio.lio.map_uncertainty`; cm and degrees).

The recording carries a default layout (:func:`blueprint`): the 3D view of ``world`` on the left,
three stacked time series (degeneracy, points, sigma) on the right. A layout the user arranged
in the viewer is kept across runs of the same application id, as rerun does.

World frame and metres as in ``trajectory.tum``. ``rerun`` is imported lazily: it is the optional
extra ``adalio[view]``.
"""

from __future__ import annotations

import bisect
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import uuid
import warnings
from pathlib import Path
from typing import Any, Self

import numpy as np

from adalio.errors import AdalioError
from adalio.types import Estimate

MISSING_RERUN = "--view/--rrd need rerun-sdk: pip install 'adalio[view]'"
TIMELINE = "scan_time"
SEQUENCE = "scan"
GENERAL_RGB = (70, 140, 230)
DEGENERATE_RGB = (240, 130, 30)
MAP_RGB = (160, 160, 160)
TRAJECTORY_RGB = (40, 200, 90)
FLUSH_TIMEOUT_S = 10.0
"""How long :meth:`RerunView.close` waits for the viewer / file to take the last messages."""
VIEWER_PORT = 9876
"""gRPC port of the spawned viewer (rerun's default) when ``RerunView`` is given none."""
MAX_SCAN_POINTS = 20_000
"""Scans with more points are logged with a regular stride (bounds the .rrd size)."""
VIEWER_START_S = 20.0
"""How long the spawned viewer may take to listen on its port."""
VIEWER_SETTLE_S = 1.5
"""... and how long it must then stay up: the viewer listens before it opens its window, and
exits right after when it cannot (a display that does not answer: ``Failed to open connection to
X server`` within tens of milliseconds of the port, measured with ``DISPLAY=:99`` and no server
there; a software renderer's panic in ``--headless``, 0.6 s)."""


def _import_rerun() -> Any:
    try:
        import rerun as rr
    except ImportError:
        raise AdalioError(MISSING_RERUN) from None
    return rr


def has_display() -> bool:
    """Whether a native window can open: always on macOS / Windows, X11 or Wayland on Linux."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def blueprint() -> tuple[Any, dict[str, Any]]:
    """The default layout and its views by name (``world``, ``degeneracy``, ``points``,
    ``sigma``). Each view's ``id`` is fixed (a UUID5 of its name), so a script can address a
    view of a running viewer, e.g. ``ViewerClient.save_screenshot(path, view_id=...)``."""
    import rerun.blueprint as rrb

    views = {
        "world": rrb.Spatial3DView(origin="/world", name="world (map, scan, trajectory)"),
        "degeneracy": rrb.TimeSeriesView(origin="/plots/degeneracy", name="degeneracy"),
        "points": rrb.TimeSeriesView(origin="/plots/points", name="points per scan"),
        "sigma": rrb.TimeSeriesView(origin="/plots/sigma", name="sigma (cm, deg)"),
    }
    for name, view in views.items():
        view.id = uuid.uuid5(uuid.NAMESPACE_URL, f"https://adalio/view/{name}")
    layout = rrb.Horizontal(
        views["world"],
        rrb.Vertical(views["degeneracy"], views["points"], views["sigma"]),
        column_shares=[3, 2])
    return rrb.Blueprint(layout, collapse_panels=True), views


def _listening(port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def _exit_reason(log: Any) -> str:
    """The viewer's own account of its exit: the last ``Error:`` or panic line of its output,
    else the last line (ANSI colours removed)."""
    log.seek(0)
    lines = [re.sub(r"\x1b\[[0-9;]*m", "", ln).strip()
             for ln in log.read().decode(errors="replace").splitlines()]
    lines = [ln for ln in lines if ln]
    errors = [ln for ln in lines if ln.startswith("Error:") or "panicked at" in ln]
    reason = (errors or lines or ["no output"])[-1]
    return re.sub(r"\s*(os error )?at \S+\.rs:\d+:", "", reason)[:300]  # the source line


def start_viewer(exe: str, port: int) -> subprocess.Popen | None:
    """Start the rerun viewer listening on ``port`` (its own session: it stays open after the
    run, as ``rerun.spawn`` leaves it) and wait until it is up. None: a viewer already listens
    there (``rerun.spawn`` reuses it too). A viewer that exits at start raises
    :class:`AdalioError` with its reason: ``rerun.spawn`` let the run go on, its messages lost,
    after a 6 s wait and a screen of the viewer's log."""
    if _listening(port):
        return None
    with tempfile.TemporaryFile() as log:  # the viewer keeps its own handle
        proc = subprocess.Popen([exe, f"--port={port}", "--memory-limit=75%",
                                 "--server-memory-limit=1GiB", "--expect-data-soon"],
                                stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                                start_new_session=True)
        return _wait_for_viewer(proc, port, log)


def _wait_for_viewer(proc: subprocess.Popen, port: int, log: Any) -> subprocess.Popen:
    up_at = None
    deadline = time.monotonic() + VIEWER_START_S
    while True:
        now = time.monotonic()
        if proc.poll() is not None:
            where = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
            raise AdalioError("--view: the rerun viewer exited as it started"
                              + (f" on display {where}" if where else "")
                              + f" ({_exit_reason(log)})")
        if up_at is None and _listening(port):
            up_at = now
        if up_at is not None and now - up_at >= VIEWER_SETTLE_S:
            return proc
        if up_at is None and now > deadline:
            proc.kill()
            raise AdalioError(f"--view: the rerun viewer did not listen on port {port} within "
                              f"{VIEWER_START_S:g} s ({_exit_reason(log)})")
        time.sleep(0.05)


def _without_viewer(reason: str, *, recording: bool) -> None:
    """``--view`` whose viewer cannot show the run: an error, or a warning where an ``.rrd`` is
    written anyway (the run goes on and records only)."""
    if not recording:
        raise AdalioError(f"{reason}; record with --rrd FILE and open it elsewhere with "
                          "`rerun FILE`")
    warnings.warn(f"{reason}; writing only the .rrd", stacklevel=3)


def viewer_executable() -> str | None:
    """The ``rerun`` viewer binary of the rerun-sdk wheel (this environment first, then PATH)."""
    here = shutil.which("rerun", path=str(Path(sys.executable).parent))
    return here or shutil.which("rerun")


class RerunView:
    """Stream a run to a spawned rerun viewer and/or record it to an ``.rrd`` file.

    ``spawn`` without a display is an :class:`AdalioError` unless ``rrd_path`` is given too (then
    a warning, and only the file is written). Use as ``run_bag(..., on_estimate=view.log_estimate)``
    and call :meth:`close` at the end (or use it as a context manager).
    """

    def __init__(self, *, spawn: bool = False, rrd_path: str | Path | None = None,
                 map_voxel_m: float = 0.2, map_every_scans: int = 10, port: int | None = None,
                 application_id: str = "adalio") -> None:
        if not spawn and rrd_path is None:
            raise AdalioError("RerunView needs spawn=True or an rrd_path")
        if not map_voxel_m > 0 or map_every_scans < 1:
            raise AdalioError("RerunView: map_voxel_m must be > 0 and map_every_scans >= 1")
        rr = _import_rerun()
        self._rr = rr
        if spawn and not has_display():
            _without_viewer("--view needs a display (neither DISPLAY nor WAYLAND_DISPLAY is set)",
                            recording=rrd_path is not None)
            spawn = False
        self.rrd_path = None if rrd_path is None else Path(rrd_path)
        self.spawned = spawn
        self._viewer: subprocess.Popen | None = None
        self._rec = rr.RecordingStream(application_id)
        sinks: list[Any] = []
        if spawn:
            exe = viewer_executable()
            if exe is None:
                raise AdalioError("--view: the rerun viewer binary is not on PATH; reinstall "
                                  "with pip install 'adalio[view]'")
            port = VIEWER_PORT if port is None else int(port)
            try:
                # kept while the run streams to it (it outlives the run, as rerun.spawn's does)
                self._viewer = start_viewer(exe, port)
            except AdalioError as exc:
                _without_viewer(str(exc), recording=self.rrd_path is not None)
                spawn = self.spawned = False
        if spawn:
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"))
        try:
            if self.rrd_path is not None:
                self.rrd_path.parent.mkdir(parents=True, exist_ok=True)
                sinks.append(rr.FileSink(str(self.rrd_path)))
            self._rec.set_sinks(*sinks, default_blueprint=blueprint()[0])
        except (OSError, RuntimeError) as exc:  # rerun raises RuntimeError for a file it cannot open
            raise AdalioError(f"--rrd {self.rrd_path}: cannot write the recording there "
                              f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); "
                              "give a writable file") from None
        self._rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.map_voxel_m = float(map_voxel_m)
        self.map_every_scans = int(map_every_scans)
        self._map_keys: set[int] = set()
        self._map_new: list[np.ndarray] = []
        self._map_chunks = 0
        self._positions: list[np.ndarray] = []
        self._times_ns: list[int] = []
        """Stamps of ``_positions``, ascending (backfilled poses arrive after later ones)."""
        self.n_scans = 0

    # -------------------------------------------------------------------------------- logging
    def log_estimate(self, est: Estimate) -> None:
        """Log one scan's estimate (call after it was written)."""
        rr, rec = self._rr, self._rec
        rec.set_time(TIMELINE, timestamp=np.datetime64(int(est.t_ns), "ns"))
        rec.set_time(SEQUENCE, sequence=self.n_scans)
        stats = est.stats
        T = np.asarray(est.T_world_imu, dtype=np.float64)
        p = T[:3, 3]
        k = bisect.bisect_right(self._times_ns, int(est.t_ns))
        self._times_ns.insert(k, int(est.t_ns))
        self._positions.insert(k, p.copy())
        color = DEGENERATE_RGB if stats.degenerate else GENERAL_RGB
        pts = est.points_world
        if pts is None:
            pts = np.zeros((0, 3))
        pts = np.asarray(pts, dtype=np.float32)
        if len(pts) > MAX_SCAN_POINTS:
            pts = pts[:: -(-len(pts) // MAX_SCAN_POINTS)]
        rec.log("world/scan", rr.Points3D(pts, colors=color, radii=0.03))
        self._collect_map(pts)
        if (self.n_scans + 1) % self.map_every_scans == 0:
            self._flush_map()
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        rec.log("world/imu", rr.Transform3D(translation=p, quaternion=q))
        rec.log("world/trajectory", rr.LineStrips3D([np.asarray(self._positions)],
                                                    colors=TRAJECTORY_RGB, radii=0.02))
        weak = np.asarray(stats.weakest_direction, dtype=np.float64).reshape(-1)
        score = float(stats.degeneracy_score)
        if weak.shape == (6,) and np.all(np.isfinite(weak)):
            rec.log("world/weakest_direction", rr.Arrows3D(
                origins=[p], vectors=[weak[3:6] * max(score, 0.05)], colors=color, radii=0.02,
                labels=[f"score {score:.2f}"]))
        rec.log("plots/degeneracy/score", rr.Scalars(score))
        rec.log("plots/degeneracy/degenerate", rr.Scalars(float(bool(stats.degenerate))))
        for name in ("n_raw", "n_down", "n_matched"):
            rec.log(f"plots/points/{name}", rr.Scalars(float(getattr(stats, name))))
        sig_p = np.asarray(stats.sigma_p_world_m, dtype=np.float64).reshape(-1)
        if sig_p.shape[0] == 3 and np.all(np.isfinite(sig_p)):
            for axis, s in zip("xyz", sig_p, strict=True):
                rec.log(f"plots/sigma/position_{axis}_cm", rr.Scalars(100.0 * s))
            rec.log("plots/sigma/yaw_deg", rr.Scalars(float(stats.sigma_rot_world_deg[2])))
        self.n_scans += 1

    def __call__(self, est: Estimate) -> None:
        self.log_estimate(est)

    def _collect_map(self, pts: np.ndarray) -> None:
        if not len(pts):
            return
        finite = pts[np.all(np.isfinite(pts), axis=1)]
        cells = np.floor(finite / self.map_voxel_m).astype(np.int64)
        cells = np.clip(cells, -(2**20), 2**20 - 1) + 2**20
        keys = (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]
        keys, first = np.unique(keys, return_index=True)
        new = np.fromiter((k not in self._map_keys for k in keys.tolist()), bool, len(keys))
        if new.any():
            self._map_keys.update(keys[new].tolist())
            self._map_new.append(finite[first[new]])

    def _flush_map(self) -> None:
        if not self._map_new:
            return
        pts = np.concatenate(self._map_new)
        self._map_new = []
        self._rec.log(f"world/map/{self._map_chunks:04d}",
                      self._rr.Points3D(pts, colors=MAP_RGB, radii=0.02))
        self._map_chunks += 1

    # -------------------------------------------------------------------------------- closing
    def close(self) -> None:
        """Log the last map cells and flush the sinks (bounded wait for a viewer)."""
        if self._rec is None:
            return
        try:
            self._flush_map()
            self._rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
        except RuntimeError as exc:  # a viewer closed early or never reachable: the run is done
            warnings.warn(f"the rerun viewer did not receive everything ({exc})", stacklevel=2)
        finally:
            self._rec.disconnect()
            self._rec = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
