"""Voxel-grid downsampling of point clouds (lio-design.md §6.1 step 4).

Frame-agnostic: points and the leaf are in metres, in whatever frame the caller uses (the scan's
LiDAR frame after undistortion in the odometry). PCL VoxelGrid semantics: the grid is aligned at
integer multiples of the leaf, voxel key = floor(p / leaf_m) per axis, and each occupied voxel
yields the centroid of its points. Output rows are ordered by ascending (kx, ky, kz), so the result
does not depend on the input order. Non-finite points are ignored.

Also holds the integer-key hash shared with the iVox map (lio-design.md §7).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from adalio.errors import InputError


def _as_int64(value: int) -> np.int64:
    return np.int64(value - (1 << 64) if value >= (1 << 63) else value)


_HASH_X = _as_int64(0x9E3779B97F4A7C15)
_HASH_Y = _as_int64(0xC2B2AE3D27D4EB4F)
_HASH_Z = _as_int64(0x165667B19E3779F9)
_MAX_ABS_KEY = 4.0e15


@njit(cache=True, inline="always")
def hash_key3(kx: int, ky: int, kz: int, mask: int) -> int:
    """Slot of an integer voxel key in a power-of-two open-addressing table (§7 "Hash")."""
    h = kx * _HASH_X + ky * _HASH_Y + kz * _HASH_Z
    h ^= h >> 29
    h *= _HASH_Z
    h ^= h >> 32
    return h & mask


@njit(cache=True)
def table_size_for(n: int) -> int:
    """Smallest power of two >= 2 n (load factor <= 0.5), at least 16."""
    size = 16
    while size < 2 * n:
        size <<= 1
    return size


@njit(cache=True)
def _voxel_centroids(points: np.ndarray, leaf_m: float):
    """Hash every point to floor(p / leaf) and accumulate per-voxel sums (§6.1 step 4).

    Returns (voxel keys (V,3) in first-appearance order, centroids (V,3), voxel id per point with
    -1 for non-finite points).
    """
    n = points.shape[0]
    size = table_size_for(n)
    mask = size - 1
    table = np.full(size, -1, np.int64)
    vkeys = np.empty((n, 3), np.int64)
    sums = np.zeros((n, 3), np.float64)
    counts = np.zeros(n, np.int64)
    voxel_of_point = np.empty(n, np.int64)
    nv = 0
    for i in range(n):
        fx = np.floor(points[i, 0] / leaf_m)
        fy = np.floor(points[i, 1] / leaf_m)
        fz = np.floor(points[i, 2] / leaf_m)
        if not (abs(fx) < _MAX_ABS_KEY and abs(fy) < _MAX_ABS_KEY and abs(fz) < _MAX_ABS_KEY):
            voxel_of_point[i] = -1
            continue
        kx = np.int64(fx)
        ky = np.int64(fy)
        kz = np.int64(fz)
        h = hash_key3(kx, ky, kz, mask)
        while True:
            v = table[h]
            if v < 0:
                v = nv
                table[h] = v
                vkeys[v, 0] = kx
                vkeys[v, 1] = ky
                vkeys[v, 2] = kz
                nv += 1
                break
            if vkeys[v, 0] == kx and vkeys[v, 1] == ky and vkeys[v, 2] == kz:
                break
            h = (h + 1) & mask
        sums[v, 0] += points[i, 0]
        sums[v, 1] += points[i, 1]
        sums[v, 2] += points[i, 2]
        counts[v] += 1
        voxel_of_point[i] = v
    centroids = np.empty((nv, 3), np.float64)
    for v in range(nv):
        inv = 1.0 / counts[v]
        centroids[v, 0] = sums[v, 0] * inv
        centroids[v, 1] = sums[v, 1] * inv
        centroids[v, 2] = sums[v, 2] * inv
    return vkeys[:nv], centroids, voxel_of_point


@njit(cache=True)
def _bit_width(span: int) -> int:
    bits = 0
    while span > 0:
        span >>= 1
        bits += 1
    return bits


@njit(cache=True)
def radix_argsort(keys: np.ndarray, n_bits: int) -> np.ndarray:
    """Stable LSD radix argsort of non-negative int64 keys below 2**n_bits (11-bit digits)."""
    n = keys.shape[0]
    order = np.arange(n)
    tmp = np.empty(n, np.int64)
    counts = np.empty(2048, np.int64)
    shift = 0
    while shift < n_bits:
        counts[:] = 0
        for i in range(n):
            counts[(keys[i] >> shift) & 2047] += 1
        total = 0
        for d in range(2048):
            c = counts[d]
            counts[d] = total
            total += c
        for i in range(n):
            j = order[i]
            d = (keys[j] >> shift) & 2047
            tmp[counts[d]] = j
            counts[d] += 1
        order, tmp = tmp, order
        shift += 11
    return order


@njit(cache=True)
def _packed_order(vkeys: np.ndarray) -> np.ndarray:
    """Permutation sorting voxel keys lexicographically via one tightly packed int64 per key.

    Returns an empty array when the three key spans need more than 62 bits (caller falls back).
    """
    nv = vkeys.shape[0]
    if nv == 0:
        return np.empty(0, np.int64)
    lo = vkeys[0].copy()
    hi = vkeys[0].copy()
    for v in range(1, nv):
        for a in range(3):
            lo[a] = min(lo[a], vkeys[v, a])
            hi[a] = max(hi[a], vkeys[v, a])
    by = _bit_width(hi[1] - lo[1])
    bz = _bit_width(hi[2] - lo[2])
    n_bits = _bit_width(hi[0] - lo[0]) + by + bz
    if n_bits > 62:
        return np.empty(0, np.int64)
    packed = np.empty(nv, np.int64)
    for v in range(nv):
        packed[v] = (
            ((vkeys[v, 0] - lo[0]) << (by + bz))
            | ((vkeys[v, 1] - lo[1]) << bz)
            | (vkeys[v, 2] - lo[2])
        )
    return radix_argsort(packed, n_bits)


@njit(cache=True)
def _apply_order(centroids: np.ndarray, voxel_of_point: np.ndarray, order: np.ndarray):
    nv = order.shape[0]
    rank = np.empty(nv, np.int64)
    out = np.empty((nv, 3), np.float64)
    for r in range(nv):
        rank[order[r]] = r
        out[r] = centroids[order[r]]
    idx = np.empty_like(voxel_of_point)
    for i in range(voxel_of_point.shape[0]):
        v = voxel_of_point[i]
        idx[i] = rank[v] if v >= 0 else -1
    return out, idx


def _check_points(points: np.ndarray, name: str) -> np.ndarray:
    arr = np.ascontiguousarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {np.shape(points)}")
    return arr


def voxel_downsample_with_index(points: np.ndarray, leaf_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel-grid downsampling that also returns the output row of every input point.

    Implements lio-design.md §6.1 step 4 (PCL VoxelGrid: key = floor(p / leaf_m), centroid per
    occupied voxel). Returns ``(centroids (M,3) float64, voxel_of_point (N,) int64)`` with rows
    sorted by ascending (kx, ky, kz) and ``-1`` for non-finite input points.
    """
    if not (np.isfinite(leaf_m) and leaf_m > 0.0):
        raise InputError(f"voxel leaf must be a positive number of metres, got {leaf_m!r}")
    arr = _check_points(points, "points")
    vkeys, centroids, voxel_of_point = _voxel_centroids(arr, float(leaf_m))
    order = _packed_order(vkeys)
    if order.shape[0] != vkeys.shape[0]:
        order = np.lexsort((vkeys[:, 2], vkeys[:, 1], vkeys[:, 0])).astype(np.int64)
    return _apply_order(centroids, voxel_of_point, order)


def voxel_downsample(points: np.ndarray, leaf_m: float) -> np.ndarray:
    """Centroid of the points of each occupied leaf_m voxel, (M,3) float64 (lio-design.md §6.1).

    Grid aligned at multiples of ``leaf_m`` (key = floor(p / leaf_m)); rows in ascending key order.
    """
    return voxel_downsample_with_index(points, leaf_m)[0]
