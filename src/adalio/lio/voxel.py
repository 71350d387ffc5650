"""Voxel-grid downsampling of point clouds (lio-design.md §6.1 step 4).

Frame-agnostic: points and the leaf are in metres, in whatever frame the caller uses (the scan's
LiDAR frame after undistortion in the odometry). PCL VoxelGrid semantics: the grid is aligned at
integer multiples of the leaf, voxel key = floor(p / leaf_m) per axis, and each occupied voxel
yields the centroid of its points. Output rows are ordered by ascending (kx, ky, kz), so the result
does not depend on the input order. Non-finite points are ignored.
"""

from __future__ import annotations

import numpy as np

from adalio.errors import InputError
from adalio.jit import kernel

_MAX_ABS_KEY = 4.0e15


@kernel()
def _voxel_keys(points: np.ndarray, leaf_m: float):
    """Integer keys floor(p / leaf_m) of the finite points (§6.1 step 4) and their bounds.

    Returns (keys (V,3) int64, source row of each key (V,), lo (3,), hi (3,)).
    """
    n = points.shape[0]
    keys = np.empty((n, 3), np.int64)
    rows = np.empty(n, np.int64)
    lo = np.full(3, np.iinfo(np.int64).max)
    hi = np.full(3, np.iinfo(np.int64).min)
    nvalid = 0
    for i in range(n):
        fx = np.floor(points[i, 0] / leaf_m)
        fy = np.floor(points[i, 1] / leaf_m)
        fz = np.floor(points[i, 2] / leaf_m)
        if not (abs(fx) < _MAX_ABS_KEY and abs(fy) < _MAX_ABS_KEY and abs(fz) < _MAX_ABS_KEY):
            continue
        kx = np.int64(fx)
        ky = np.int64(fy)
        kz = np.int64(fz)
        keys[nvalid, 0] = kx
        keys[nvalid, 1] = ky
        keys[nvalid, 2] = kz
        rows[nvalid] = i
        nvalid += 1
        lo[0] = min(lo[0], kx)
        lo[1] = min(lo[1], ky)
        lo[2] = min(lo[2], kz)
        hi[0] = max(hi[0], kx)
        hi[1] = max(hi[1], ky)
        hi[2] = max(hi[2], kz)
    return keys[:nvalid], rows[:nvalid], lo, hi


@kernel()
def _bit_width(span: int) -> int:
    bits = 0
    while span > 0:
        span >>= 1
        bits += 1
    return bits


@kernel()
def pack_keys(keys: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """One int64 per key, (kx, ky, kz) - lo bit-packed so that integer order = lexicographic order.

    Returns (packed (V,), n_bits); n_bits > 62 means the spans do not fit (packed is empty).
    """
    by = _bit_width(hi[1] - lo[1])
    bz = _bit_width(hi[2] - lo[2])
    n_bits = _bit_width(hi[0] - lo[0]) + by + bz
    if n_bits > 62:
        return np.empty(0, np.int64), n_bits
    packed = np.empty(keys.shape[0], np.int64)
    for v in range(keys.shape[0]):
        packed[v] = (
            ((keys[v, 0] - lo[0]) << (by + bz))
            | ((keys[v, 1] - lo[1]) << bz)
            | (keys[v, 2] - lo[2])
        )
    return packed, n_bits


@kernel()
def radix_argsort(keys: np.ndarray, n_bits: int) -> np.ndarray:
    """Stable LSD radix argsort of non-negative int64 keys below 2**n_bits (<= 11-bit digits)."""
    n = keys.shape[0]
    order = np.arange(n)
    if n_bits <= 0:
        return order
    n_pass = (n_bits + 10) // 11
    digit_bits = (n_bits + n_pass - 1) // n_pass
    digit_mask = (1 << digit_bits) - 1
    tmp = np.empty(n, np.int64)
    counts = np.empty(digit_mask + 1, np.int64)
    for p in range(n_pass):
        shift = p * digit_bits
        counts[:] = 0
        for i in range(n):
            counts[(keys[i] >> shift) & digit_mask] += 1
        total = 0
        for d in range(digit_mask + 1):
            c = counts[d]
            counts[d] = total
            total += c
        for i in range(n):
            j = order[i]
            d = (keys[j] >> shift) & digit_mask
            tmp[counts[d]] = j
            counts[d] += 1
        order, tmp = tmp, order
    return order


@kernel()
def _centroids_of_runs(
    points: np.ndarray, rows: np.ndarray, packed: np.ndarray, order: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Centroid of each run of equal packed keys in sorted order (§6.1 step 4, PCL centroid)."""
    nvalid = order.shape[0]
    centroids = np.empty((nvalid, 3), np.float64)
    voxel_of_point = np.full(points.shape[0], -1, np.int64)
    nv = -1
    prev = -1
    cnt = 0
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for r in range(nvalid):
        j = order[r]
        if packed[j] != prev:
            if nv >= 0:
                centroids[nv, 0] = sx / cnt
                centroids[nv, 1] = sy / cnt
                centroids[nv, 2] = sz / cnt
            nv += 1
            prev = packed[j]
            cnt = 0
            sx = 0.0
            sy = 0.0
            sz = 0.0
        i = rows[j]
        sx += points[i, 0]
        sy += points[i, 1]
        sz += points[i, 2]
        cnt += 1
        voxel_of_point[i] = nv
    if nv >= 0:
        centroids[nv, 0] = sx / cnt
        centroids[nv, 1] = sy / cnt
        centroids[nv, 2] = sz / cnt
    return centroids[: nv + 1], voxel_of_point


def _lexicographic_fallback(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense rank per key (as the packed key) and the lexicographic order, for huge key spans."""
    order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
    sorted_keys = keys[order]
    new_run = np.ones(len(order), np.int64)
    new_run[1:] = np.any(sorted_keys[1:] != sorted_keys[:-1], axis=1)
    rank = np.empty(len(order), np.int64)
    rank[order] = np.cumsum(new_run) - 1
    return rank, order.astype(np.int64)


def _check_points(points: np.ndarray, name: str) -> np.ndarray:
    arr = np.ascontiguousarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {np.shape(points)}")
    return arr


def voxel_downsample_with_index(points: np.ndarray, leaf_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel-grid downsampling that also returns the output row of every input point.

    Implements lio-design.md §6.1 step 4 (PCL VoxelGrid: key = floor(p / leaf_m), centroid per
    occupied voxel) by a radix sort of bit-packed keys. Returns ``(centroids (M,3) float64,
    voxel_of_point (N,) int64)`` with rows sorted by ascending (kx, ky, kz) and ``-1`` for
    non-finite input points.
    """
    if not (np.isfinite(leaf_m) and leaf_m > 0.0):
        raise InputError(f"voxel leaf must be a positive number of metres, got {leaf_m!r}")
    arr = _check_points(points, "points")
    keys, rows, lo, hi = _voxel_keys(arr, float(leaf_m))
    if keys.shape[0] == 0:
        return np.empty((0, 3), np.float64), np.full(arr.shape[0], -1, np.int64)
    packed, n_bits = pack_keys(keys, lo, hi)
    if n_bits <= 62:
        order = radix_argsort(packed, n_bits)
    else:
        packed, order = _lexicographic_fallback(keys)
    return _centroids_of_runs(arr, rows, packed, order)


def voxel_downsample(points: np.ndarray, leaf_m: float) -> np.ndarray:
    """Centroid of the points of each occupied leaf_m voxel, (M,3) float64 (lio-design.md §6.1).

    Grid aligned at multiples of ``leaf_m`` (key = floor(p / leaf_m)); rows in ascending key order.
    """
    return voxel_downsample_with_index(points, leaf_m)[0]
