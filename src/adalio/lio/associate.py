"""Point-to-plane correspondences in one pass: kNN, plane fit and neighbour moments per query.

The same computation as :meth:`adalio.lio.ivox.IVox.knn` followed by
:func:`adalio.lio.plane.fit_planes` and :func:`adalio.lio.plane.neighbour_moments` (lio-design.md
§6.2, §7), fused into one numba loop over the queries: each row's k neighbours live in a small
scratch buffer instead of an (M, k, 3) array that three kernels read in turn, so the search
touches memory once and allocates nothing per row. Without the support test, results are
bit-identical to the three-step path (``tests/lio/test_associate.py`` checks that; the support
test has no three-step twin and is checked against brute force there).

Output per query row (world frame, metres): the plane ``n . x + d = 0`` and its §6.2 validity
combined with the §9.4 search-radius gate (enough neighbours and the farthest of them within
``radius_m``) and, optionally, the support test (the query not beyond all its neighbours), the
neighbours' centroid and middle covariance eigenvalue (for the plane-fit
variance), the neighbour count and the nearest neighbour (for the shared-neighbour weighting).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numba import prange

from adalio.errors import ConfigError
from adalio.jit import kernel
from adalio.lio.ivox import IVox, _key_of, _knn_row
from adalio.lio.plane import (
    PLANE_METHODS,
    _middle_eigenvalue,
    _scatter,
    elevation_spread,
    fit_plane,
    within_margin,
    within_support,
)

PARALLEL_MIN_QUERIES = 256
"""Batches of at least this many queries run on all numba threads (``NUMBA_NUM_THREADS``). On the
quiet 2-core dev machine (OpenMP layer) two threads beat one from 128 queries on: 0.23 vs 0.36 ms
at 512, 1.6 vs 2.7 ms at 2842 (a 512-column XT-32 scan). On a machine whose cores are all busy,
OpenMP's spin-waiting made them slower (8 vs 3.8 ms measured, before adalio made its OpenMP
threads sleep while they wait in session 88: ``adalio/__init__.py``), hence one numba thread per
``adalio batch`` worker when the workers fill the cores."""


@dataclass
class Correspondences:
    """Per query row: plane, validity and the neighbour statistics the residual model uses."""

    normals: np.ndarray
    """(M,3) unit plane normals (NaN where no fit)."""
    d: np.ndarray
    """(M,) plane offsets, m (NaN where no fit)."""
    valid: np.ndarray
    """(M,) bool: a valid plane (§6.2) from enough neighbours, the farthest within the radius."""
    counts: np.ndarray
    """(M,) int64 neighbours found."""
    mu: np.ndarray
    """(M,3) neighbour centroid (NaN for fewer than 3 neighbours)."""
    lam_mid: np.ndarray
    """(M,) middle eigenvalue of the neighbour covariance, m² (0 for fewer than 3)."""
    nearest: np.ndarray
    """(M,3) nearest neighbour (NaN when none)."""
    queries: np.ndarray | None = None
    """(M,3) the searched world points (with ``keep_neighbours``)."""
    neighbours: np.ndarray | None = None
    """(M,k,3) the k nearest, ascending (NaN-padded; with ``keep_neighbours``)."""


@kernel(inline="always")
def _warm_bound(queries, prev_queries, prev_nbrs, i, k, max_d2, resolution_m):
    """A squared distance that the k nearest of query ``i`` all lie below: just above the
    farthest of the k neighbours its previous position had, when both positions search the same
    voxels (same query voxel) and the map has not changed since; else ``max_d2``. The search
    started with it returns the same neighbours, in the same order, as one started with
    ``max_d2`` (every point it passes over is farther than k points it keeps), and prunes more."""
    ok, kx, ky, kz = _key_of(queries[i, 0], queries[i, 1], queries[i, 2], resolution_m)
    ok0, kx0, ky0, kz0 = _key_of(prev_queries[i, 0], prev_queries[i, 1], prev_queries[i, 2],
                                 resolution_m)
    if not (ok and ok0 and kx == kx0 and ky == ky0 and kz == kz0):
        return max_d2
    far = 0.0
    for j in range(k):
        d = ((prev_nbrs[i, j, 0] - queries[i, 0]) ** 2 + (prev_nbrs[i, j, 1] - queries[i, 1]) ** 2
             + (prev_nbrs[i, j, 2] - queries[i, 2]) ** 2)
        far = max(far, d)
    bound = np.nextafter(far, np.inf)
    return min(max_d2, bound)


@kernel(inline="always")
def _associate_row(i, queries, k, max_d2, resolution_m, offsets, cap, store, min_count,
                   radius2, margin_m, min_extent_m, use_ls, support_test, nb, d2, scratch,
                   normals, dist, valid, counts, mu, lam_mid, nearest, warm, prev_queries,
                   prev_nbrs, prev_counts, out_nbrs, ring):
    # ring (7,): the one-ring test's LiDAR position (0:3), spin axis (3:6) and least elevation
    # spread in rad (6; 0 = off), in one array: passed as three arguments, numba 0.68 refused to
    # inline the call ("Calling a closure with *args is unsupported")
    for j in range(k):
        d2[0, j] = np.inf
        nb[0, j, 0] = np.nan
        nb[0, j, 1] = np.nan
        nb[0, j, 2] = np.nan
    bound = max_d2
    if warm and prev_counts[i] == k:
        bound = _warm_bound(queries, prev_queries, prev_nbrs, i, k, max_d2, resolution_m)
    c = _knn_row(np.int64(0), queries[i:i + 1], k, bound, resolution_m, offsets, cap, store, nb, d2)
    if out_nbrs.shape[0]:
        for j in range(k):
            out_nbrs[i, j, 0] = nb[0, j, 0]
            out_nbrs[i, j, 1] = nb[0, j, 1]
            out_nbrs[i, j, 2] = nb[0, j, 2]
    counts[i] = c
    nearest[i, 0] = nb[0, 0, 0]
    nearest[i, 1] = nb[0, 0, 1]
    nearest[i, 2] = nb[0, 0, 2]
    if c >= 3:
        mu[i, 0], mu[i, 1], mu[i, 2] = _scatter(nb[0], c, scratch[0])
        lam_mid[i] = _middle_eigenvalue(scratch[0]) / c
    if c < min_count:
        return
    d = fit_plane(nb[0], c, use_ls, scratch, normals[i])  # kept for gated rows, as fit_planes
    dist[i] = d
    if not (np.isfinite(d) and d2[0, c - 1] <= radius2
            and within_margin(nb[0], c, normals[i], d, margin_m)):
        return
    if min_extent_m > 0.0 and not lam_mid[i] >= min_extent_m * min_extent_m:
        return
    if support_test and not within_support(nb[0], c, normals[i], mu[i, 0], mu[i, 1], mu[i, 2],
                                           queries[i, 0], queries[i, 1], queries[i, 2]):
        return
    if ring[6] > 0.0 and elevation_spread(nb[0], c, ring[0:3], ring[3:6]) < ring[6]:
        return
    valid[i] = True


@kernel()
def _associate_serial(queries, k, max_d2, resolution_m, offsets, cap, store, min_count, radius2,
                      margin_m, min_extent_m, use_ls, support_test, normals, dist, valid, counts,
                      mu, lam_mid, nearest, warm, prev_queries, prev_nbrs, prev_counts, out_nbrs,
                      ring):
    """All rows, one thread, one scratch buffer."""
    nb = np.empty((1, k, 3))
    d2 = np.empty((1, k))
    scratch = np.empty((2, 3, 3))
    for i in range(queries.shape[0]):
        _associate_row(i, queries, k, max_d2, resolution_m, offsets, cap, store, min_count,
                       radius2, margin_m, min_extent_m, use_ls, support_test, nb, d2, scratch,
                       normals, dist, valid, counts, mu, lam_mid, nearest, warm, prev_queries,
                       prev_nbrs, prev_counts, out_nbrs, ring)


@kernel(parallel=True)
def _associate_parallel(queries, k, max_d2, resolution_m, offsets, cap, store, min_count,
                        radius2, margin_m, min_extent_m, use_ls, support_test, normals, dist,
                        valid, counts, mu, lam_mid, nearest, warm, prev_queries, prev_nbrs,
                        prev_counts, out_nbrs, ring):
    """All rows on all numba threads; rows are independent (own scratch), so deterministic."""
    for i in prange(queries.shape[0]):
        nb = np.empty((1, k, 3))
        d2 = np.empty((1, k))
        scratch = np.empty((2, 3, 3))
        _associate_row(i, queries, k, max_d2, resolution_m, offsets, cap, store, min_count,
                       radius2, margin_m, min_extent_m, use_ls, support_test, nb, d2, scratch,
                       normals, dist, valid, counts, mu, lam_mid, nearest, warm, prev_queries,
                       prev_nbrs, prev_counts, out_nbrs, ring)


def associate(ivox: IVox, points_world: np.ndarray, k: int, max_range_m: float,
              min_neighbors: int, radius_m: float, margin_m: float, method: str = "ls",
              min_extent_m: float = 0.0, support_test: bool = False,
              keep_neighbours: bool = False,
              warm_from: Correspondences | None = None,
              compile_only: bool = False,
              ring_origin: np.ndarray | None = None, ring_axis: np.ndarray | None = None,
              ring_max_deg: float = 0.0) -> Correspondences:
    """Planes from the k nearest map points of each world point (§6.2, §7, §9.4).

    Same arguments and result as ``ivox.knn(points_world, k, max_range_m)``, then
    ``fit_planes(nbrs, counts, min_neighbors, margin_m, method, min_extent_m)`` with the search
    radius gate ``counts >= min_neighbors and dist2[count - 1] <= radius_m²`` folded into
    ``valid``, and ``neighbour_moments``. With ``support_test`` a plane is also valid only where
    the query lies within its neighbours' span (:func:`adalio.lio.plane.within_support`).

    ``keep_neighbours`` also returns the queries and their neighbours. ``warm_from``, such a
    result for the same rows (e.g. the same scan points at an earlier pose) on the *unchanged*
    map, starts each row's search from its previous neighbours' farthest distance: the same
    result, bit for bit, with fewer points and voxels visited (:func:`_warm_bound`).

    ``compile_only`` compiles the search kernel these arguments would run (for their types, on
    any map, even an empty one) and searches nothing (:mod:`adalio.lio.warmup`).

    ``ring_max_deg > 0`` (the one-ring test, ``filter.one_ring_max_deg``): a plane is also valid
    only where its neighbours' elevations seen from ``ring_origin`` (the LiDAR's world position)
    about ``ring_axis`` (its spin axis in the world) spread over at least that many degrees
    (:func:`adalio.lio.plane.elevation_spread`): not one ring's cone from (near) here.
    """
    if method not in PLANE_METHODS:
        raise ConfigError(f"filter.plane_fit must be 'ls' or 'pca', got {method!r}")
    if not (np.isfinite(min_extent_m) and min_extent_m >= 0.0):
        raise ConfigError(f"plane min_extent_m must be >= 0 metres, got {min_extent_m!r}")
    if not (np.isfinite(ring_max_deg) and ring_max_deg >= 0.0):
        raise ConfigError(f"one-ring test: max spread must be >= 0 degrees, got {ring_max_deg!r}")
    ring_o = np.zeros(3) if ring_origin is None else np.asarray(ring_origin, dtype=np.float64)
    ring_a = (np.array([0.0, 0.0, 1.0]) if ring_axis is None
              else np.asarray(ring_axis, dtype=np.float64))
    if ring_max_deg > 0.0 and not (ring_o.shape == (3,) and ring_a.shape == (3,)
                                   and np.all(np.isfinite(ring_o))
                                   and abs(np.linalg.norm(ring_a) - 1.0) < 1e-6):
        raise ConfigError("one-ring test: ring_origin must be a finite (3,) point and "
                          "ring_axis a (3,) unit vector")
    q = np.ascontiguousarray(points_world, dtype=np.float64)
    m = q.shape[0]
    k = int(k)
    out = Correspondences(normals=np.full((m, 3), np.nan), d=np.full(m, np.nan),
                          valid=np.zeros(m, np.bool_), counts=np.zeros(m, np.int64),
                          mu=np.full((m, 3), np.nan), lam_mid=np.zeros(m),
                          nearest=np.full((m, 3), np.nan))
    if keep_neighbours:
        out.queries = q
        out.neighbours = np.full((m, k, 3), np.nan)
    if (m == 0 or ivox.num_voxels == 0) and not compile_only:
        return out
    warm = (warm_from is not None and warm_from.neighbours is not None
            and warm_from.neighbours.shape == (m, k, 3))
    if warm:
        prev_q, prev_nb, prev_c = warm_from.queries, warm_from.neighbours, warm_from.counts
    else:
        prev_q, prev_nb, prev_c = np.empty((0, 3)), np.empty((0, k, 3)), np.empty(0, np.int64)
    out_nb = out.neighbours if keep_neighbours else np.empty((0, k, 3))
    parallel = m >= PARALLEL_MIN_QUERIES and numba.get_num_threads() > 1
    kernel = _associate_parallel if parallel else _associate_serial
    args = (q, k, float(max_range_m) ** 2, ivox.resolution_m, ivox._offsets,
            ivox.max_points_per_voxel,
            (ivox._table, ivox._vkeys, ivox._vtotal, ivox._vblocks, ivox._pool),
            max(int(min_neighbors), 3), float(radius_m) ** 2, float(margin_m),
            float(min_extent_m), method == "ls", bool(support_test), out.normals, out.d,
            out.valid, out.counts, out.mu, out.lam_mid, out.nearest, warm, prev_q, prev_nb,
            prev_c, out_nb, np.r_[ring_o, ring_a, np.radians(ring_max_deg)])
    if compile_only:
        kernel.compile(tuple(numba.typeof(a) for a in args))
    else:
        kernel(*args)
    return out
