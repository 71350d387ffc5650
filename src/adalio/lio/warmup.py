"""Compile the scan update's kernels in a second process while a cold run compiles the rest.

A fresh install has an empty numba cache, and its first ``adalio run`` spends most of its wall
time compiling (issue #15, ``benchmarks/bench_resources.py``). numba compiles one function at a
time per process (a global compiler lock), but its on-disk cache is shared: a kernel that another
process has compiled and saved is loaded, not compiled, on its first call here. So while the run
compiles the kernels of its first stages in the order it reaches them (decoding, IMU
propagation, undistortion, downsampling, the first map), :func:`start` lets a helper process
compile the kernels of the update and the map stages, which the run reaches only at its second
scan (:func:`compile_update_stage`, in the order the run reaches them: the kNN search and plane
fits first). Measured on the 2-core dev machine, the two halves take about as long (the run
compiled 16.5 s itself, the helper about 17 s; one process alone compiles 29-32 s). The helper is a plain subprocess whose output goes nowhere; the run never waits
for it and stops it when it ends (:class:`Warmup`), so whatever it has not finished the run
compiles itself, as without it.

It starts only where it can help: with at least two CPUs this process may run on
(:func:`adalio.cpus.usable_cpus`), numba's JIT on and the update's
kernels not in the cache yet for this adalio source (:func:`cache_is_cold`); and not at all with
``ADALIO_PARALLEL_COMPILE=0`` in the environment. Two processes saving kernels into one cache is
safe because the kernel decorator (``jit.kernel``) locks each save (the index and its data
files stay consistent).

The helper calls the same functions the run calls (``voxel_downsample``, ``associate``,
``_Association.measure`` under :func:`~adalio.lio.ieskf.iterated_update`, ``MapProvenance``, ...)
on a synthetic box room, so the signatures it compiles are the run's; ``tests/lio/test_warmup.py``
checks that a run after it compiles none of the helper's kernels again.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from adalio.cpus import usable_cpus

ENV_SWITCH = "ADALIO_PARALLEL_COMPILE"
"""Environment variable: ``0`` never starts the helper process."""


def _box_room(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points on the walls, floor and ceiling of a 12 x 8 x 3 m room, sensor frame at its
    centre (1.5 m above the floor), with 5 mm of Gaussian noise off the faces."""
    half = np.array([6.0, 4.0, 1.5])
    face = rng.integers(0, 6, n)
    axis, sign = face // 2, np.where(face % 2 == 0, -1.0, 1.0)
    pts = rng.uniform(-1.0, 1.0, (n, 3)) * half
    pts[np.arange(n), axis] = sign * half[axis]
    return pts + rng.normal(0.0, 0.005, pts.shape)


def compile_update_stage() -> None:
    """Compile the kernels of the update and map stages of :meth:`adalio.lio.Odometry.add_scan`
    (or load them from numba's cache) for the argument types a run passes, with the default
    configuration, on a box room, in the order the run reaches them after its first stages: the
    scan downsampling (the run's first scan needs it), the dense map (its first scan's points go
    in), the parallel search (the largest,
    compiled for its argument types without searching, so without building a map first), the
    filter update (on the room's exact planes), the map provenance, the gyro-unit check's
    preintegration, the moving things' tests and the map's upkeep, and the map written out at
    the end of the run (its return counts and plane test)."""
    from adalio.config import Config
    from adalio.lio.associate import associate
    from adalio.lio.degeneracy import localizability
    from adalio.lio.dense_map import DenseMap
    from adalio.lio.ieskf import iterated_update
    from adalio.lio.ivox import IVox
    from adalio.lio.map_uncertainty import MapProvenance
    from adalio.lio.measurement import (
        normal_noise_information,
        normal_noise_matrices,
        normal_noise_sums,
        pose_quadratic,
    )
    from adalio.lio.motion_init import preintegrate
    from adalio.lio.moving import MovingPoints
    from adalio.lio.odometry import _Association, _group_ids
    from adalio.lio.plane import fit_planes
    from adalio.lio.state import State, initial_covariance, pose_covariance_world
    from adalio.lio.voxel import voxel_downsample

    cfg = Config()
    f = cfg.filter
    rng = np.random.default_rng(0)
    general = cfg.adaptive.general
    cell_m = cfg.map.map_leaf_m
    ivox = IVox.from_config(cfg.map)
    pts = voxel_downsample(_box_room(20000, rng), general.voxel_size_m)
    # the dense map (output.dense_map_voxel_m): the run's first scan lays its points down
    DenseMap(cfg.output.dense_map_voxel_m or 0.05).add(pts)  # its blocks outgrow the first set
    associate(ivox, pts, f.knn_k, f.knn_max_range_m, f.min_neighbors, general.search_radius_m,
              general.plane_margin_m, f.plane_fit, f.plane_min_extent_fraction * cell_m,
              f.plane_within_support, keep_neighbours=True, compile_only=True)
    x = State(R_LI=np.eye(3), t_LI=np.zeros(3))
    P = initial_covariance(f.estimate_extrinsic)
    # the update, with the search's results set as the room's exact planes
    assoc = _Association(pts, ivox, cfg, general.search_radius_m, general.plane_margin_m, cell_m)
    axis = np.argmax(np.abs(pts) / [6.0, 4.0, 1.5], axis=1)
    assoc.normals = np.zeros((pts.shape[0], 3))
    assoc.normals[np.arange(pts.shape[0]), axis] = 1.0
    assoc.d = -np.round(pts[np.arange(pts.shape[0]), axis], 1)
    assoc.mu, assoc.lam_mid = pts.copy(), np.full(pts.shape[0], 0.01)
    assoc.counts = np.full(pts.shape[0], f.knn_k, np.int64)
    assoc.nearest = pts.copy()
    assoc.group_id, assoc.n_groups = _group_ids(assoc.nearest)
    assoc.selected = np.ones(pts.shape[0], np.bool_)
    result = iterated_update(x, P, lambda state, research: assoc.measure(state, False), f, None)
    localizability(assoc.H[:, :6], f.laser_point_cov, observability=False)
    k = f.knn_k  # the reported sigmas' discount (filter.sigmas_discount_normal_noise)
    neighbours = pts[:, None, :] + rng.normal(0.0, 0.1, (pts.shape[0], k, 3))
    normal_noise_information(pts, assoc.selected, x.R, x.R_LI, x.t_LI, assoc.normals,
                             neighbours, assoc.counts, np.ones(assoc.H.shape[0]))
    # the update's errors in variables (filter.errors_in_variables), as _Association.noise_terms
    N, plane = normal_noise_matrices(assoc.selected, assoc.normals, neighbours, assoc.counts,
                                     f.laser_point_cov, True)
    normal_noise_sums(pts, assoc.selected, x.R, x.p, x.R_LI, x.t_LI, assoc.mu, N, plane,
                      assoc.row_weights)
    pose_quadratic(assoc.H[:, :6], P[:6, :6])  # the robust kernel's spread of the rows
    provenance = MapProvenance(f.map_provenance_cell_m)
    provenance.add_scan(x.p, pose_covariance_world(x.R, P), pts)
    provenance.map_covariance(result.state.p, pts[::2].copy())
    provenance.add_scan(result.state.p, pose_covariance_world(result.state.R, result.P), pts)
    tau = np.linspace(0.0, 0.1, 41)
    preintegrate(tau, rng.normal(0.0, 0.1, (41, 3)), rng.normal(0.0, 0.1, (41, 3)),
                 np.zeros(3), np.array([0.0, 0.05]))
    if cfg.map.remove_moving:  # where the sweeps saw through (lio/moving.py)
        movers = MovingPoints.from_config(cfg.map)
        image = movers.image(pts)
        movers.add_sweep(image, np.eye(3), np.zeros(3), 0)
        movers.stored(pts, 0)
        movers.carve(ivox, image, np.eye(3), np.zeros(3), 1)
        movers.moving(pts, movers.lookback_ns, ivox, cell_m)
        ivox.add_points(pts, cell_m)
        ivox.knn(pts[:8].copy(), 1, max(cfg.map.moving_margin_m, cell_m))  # the body's map test
        ivox.would_store(pts, cell_m)
        ivox.remove_points(pts[:10])
    # the end of the run: the map written out (Odometry.map_cloud, its plane test)
    ivox.add_points(pts, cell_m)
    ivox.points_with_returns(cell_m)
    nbrs, counts, _ = ivox.knn(pts[:64].copy(), f.knn_k + 1, f.knn_max_range_m)
    fit_planes(nbrs[:, 1:], np.maximum(counts - 1, 0), f.min_neighbors, general.plane_margin_m,
               "pca", f.plane_min_extent_fraction * cell_m)


def _update_kernel():
    """The dispatcher whose cache entry tells a warm cache from a cold one: the search a run
    with this process's numba threads uses (the largest compilation of the update stage)."""
    import numba

    from adalio.lio.associate import _associate_parallel, _associate_serial

    return _associate_parallel if numba.get_num_threads() > 1 else _associate_serial


def cache_is_cold() -> bool:
    """True while numba's cache holds no search kernel compiled for this adalio source and
    this machine (a fresh install; adalio's kernel sources changed since; a cache folder shared
    with another kind of CPU)."""
    try:
        dispatcher = _update_kernel()
        magic = dispatcher.targetctx.codegen().magic_tuple()
        index = dispatcher._cache._cache_file._load_index()  # {} when absent or stale
        return not any(key[1] == magic for key in index)
    except Exception:  # noqa: BLE001  (numba internals moved: no helper, nothing lost)
        return False


def wanted() -> bool:
    """Whether :func:`start` would start the helper in this process: not where this process
    may run on one CPU only, where the two would share it (a cold run held to one CPU took
    44.8 s with the helper, 36.4 s without; session 92)."""
    import numba

    return (os.environ.get(ENV_SWITCH, "1") != "0" and usable_cpus() >= 2
            and not numba.config.DISABLE_JIT and cache_is_cold())


class Warmup:
    """The helper process, if one was started; :meth:`stop` ends it (idempotent)."""

    def __init__(self, proc: subprocess.Popen | None) -> None:
        self.proc = proc

    @property
    def started(self) -> bool:
        return self.proc is not None

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()  # numba writes each cache file to a temporary name, then renames it
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=5.0)
            return
        proc.kill()
        proc.wait()


def helper_env() -> dict[str, str]:
    """The helper's environment: this one, with this process's numba thread count (the search
    kernel a run compiles depends on it) and this adalio first on ``PYTHONPATH`` (so that a run
    from a source tree, or with another adalio installed, has its own kernels compiled)."""
    import numba

    import adalio

    root = str(Path(adalio.__file__).resolve().parents[1])
    path = os.environ.get("PYTHONPATH", "")
    return {**os.environ, "NUMBA_NUM_THREADS": str(numba.get_num_threads()),
            "PYTHONPATH": root + (os.pathsep + path if path else "")}


def start() -> Warmup:
    """Start the helper process if :func:`wanted`; never raises (without it the run compiles
    everything itself, as it always could)."""
    try:
        if not wanted():
            return Warmup(None)
        env = helper_env()
        proc = subprocess.Popen(
            [sys.executable, "-c", "from adalio.lio.warmup import compile_update_stage as f; f()"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env=env, start_new_session=True)
        return Warmup(proc)
    except Exception:  # noqa: BLE001
        return Warmup(None)
