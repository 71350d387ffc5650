"""Wall-clock timings of the map kernels (lio-design.md §6.1, §6.2, §7) on synthetic room scans.

Run: ``python benchmarks/bench_map_kernels.py``. Prints the median and the minimum over repeats
(ms) after a warm-up call (numba compile / cache load excluded). kNN and plane fits are timed on
the single-threaded path and on the numba-parallel path (``NUMBA_NUM_THREADS`` threads); on a
loaded machine the minimum is the more telling figure.
"""

from __future__ import annotations

import time

import numba
import numpy as np

from adalio.lio import ivox as ivox_module
from adalio.lio import plane as plane_module
from adalio.lio.ivox import IVox
from adalio.lio.plane import fit_planes
from adalio.lio.voxel import voxel_downsample

ROOM_HALF_M = np.array([15.0, 8.0, 2.0])


def room_scan(rng: np.random.Generator, n: int, origin: np.ndarray) -> np.ndarray:
    """n ray hits on the inside of an axis-aligned box room, seen from ``origin`` (world frame)."""
    dirs = rng.normal(size=(n, 3))
    dirs[:, 2] *= 0.4
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    with np.errstate(divide="ignore"):
        t = np.min((np.sign(dirs) * ROOM_HALF_M - origin) / dirs, axis=1)
    return origin + t[:, None] * dirs + rng.normal(scale=0.01, size=(n, 3))


def median_ms(fn, repeats: int) -> tuple[float, float]:
    fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(samples)), 1e3 * float(np.min(samples))


def forced(threshold: int, fn):
    """Run fn with both modules' parallel thresholds set to ``threshold`` rows."""

    def run():
        saved = ivox_module.PARALLEL_MIN_ROWS, plane_module.PARALLEL_MIN_ROWS
        ivox_module.PARALLEL_MIN_ROWS = plane_module.PARALLEL_MIN_ROWS = threshold
        try:
            return fn()
        finally:
            ivox_module.PARALLEL_MIN_ROWS, plane_module.PARALLEL_MIN_ROWS = saved

    return run


def main() -> None:
    rng = np.random.default_rng(0)
    scan = room_scan(rng, 64_000, np.array([1.0, 0.5, 0.0]))
    rows = []
    for leaf in (0.1, 0.2, 0.5):
        n_out = len(voxel_downsample(scan, leaf))
        rows.append(
            (
                f"voxel_downsample 64k pts, leaf {leaf} m -> {n_out}",
                median_ms(lambda leaf=leaf: voxel_downsample(scan, leaf), 30),
            )
        )

    map_points = np.vstack(
        [room_scan(rng, 50_000, rng.uniform(-5, 5, 3) * [1, 1, 0.2]) for _ in range(4)]
    )

    def build() -> IVox:
        ivox = IVox(0.5, 18, 1_000_000, 64)
        ivox.add_points(map_points)
        return ivox

    ivox = build()
    rows.append(
        (f"IVox.add_points 200k pts (fresh map, {ivox.num_voxels} voxels)", median_ms(build, 5))
    )
    queries = voxel_downsample(room_scan(rng, 64_000, np.array([0.0, 0.0, 0.3])), 0.5)
    queries = queries[rng.permutation(len(queries))[:2000]]
    serial, parallel = 1 << 62, 1
    threads = numba.get_num_threads()
    for nearby in (6, 18, 26):
        ivox_n = IVox(0.5, nearby, 1_000_000, 64)
        ivox_n.add_points(map_points)
        for label, threshold in (("1 thread", serial), (f"{threads} threads", parallel)):
            rows.append(
                (
                    f"IVox.knn 2000 queries, k=5, NEARBY{nearby}, 200k-pt map, {label}",
                    median_ms(forced(threshold, lambda m=ivox_n: m.knn(queries, 5, 5.0)), 20),
                )
            )
    nbrs, counts, _ = ivox.knn(queries, 5, 5.0)

    def insert_scan() -> None:
        ivox.add_points(queries)

    rows.append(
        ("IVox.add_points of a 2000-pt scan (existing map)", median_ms(insert_scan, 20))
    )
    for method in ("ls", "pca"):
        for label, threshold in (("1 thread", serial), (f"{threads} threads", parallel)):
            rows.append(
                (
                    f"fit_planes 2000 x 5 nbrs, {method}, {label}",
                    median_ms(
                        forced(threshold, lambda m=method: fit_planes(nbrs, counts, 3, 0.1, m)), 50
                    ),
                )
            )
    width = max(len(name) for name, _ in rows)
    print(f"{'kernel':<{width}}  {'median':>9}  {'min':>9}")
    for name, (med, low) in rows:
        print(f"{name:<{width}}  {med:6.3f} ms  {low:6.3f} ms")


if __name__ == "__main__":
    main()
