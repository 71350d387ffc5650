"""The scan's own local surface, for checking each row's map plane (``filter.local_surface_check``).

A map plane is fitted to the k nearest map points of a scan point. Where those neighbours lie
on two faces (a ring line bent around a corner, a tread and the riser behind it), the fit is a
plane that exists nowhere, tilted up to 90° from the face the point lies on, and its residual
pulls the pose along that wrong normal. On the simulated stairwell 2 % of the rows had a fitted
normal more than 30° off the true face and held 46 % of the claimed height information; on the
spiral, an oracle that drops such rows halves the error (README, *Session 28*).

The scan itself says which face a point lies on: a spinning LiDAR samples a grid of rings
(elevation) by columns (azimuth), and the few samples around a point on its own ring and the
two adjacent rings, all fired within a millisecond, span a patch of the surface much smaller
than the map's neighbourhood. :class:`LocalSurface` fits a plane to that patch (principal
components of the undistorted points) for each downsampled scan point; the odometry drops a
row when the patch is one plane and its normal is more than ``filter.local_surface_max_angle_deg``
off the map plane's. A patch judges only when it is

* complete: three rings, no gap in azimuth;
* planar: its smallest principal variance below ``PLANAR_RATIO`` of the middle one;
* one plane: the planes of its four halves (left, right, upper two rings, lower two rings) all
  within ``HALVES_AGREE_DEG`` of its own. A patch folded over an edge, mostly on one face, passes
  the planarity test with the wrong normal; the halves catch it (on simulated sweeps the judged
  normals beyond 30° off the true face fell from 0.6 % to 0.1 %, ``tests/lio/test_local_surface``);
* near: within the range at which the patch, two ring spacings tall, is at most
  ``filter.local_surface_max_patch_m`` (0.1 m, the degenerate voxel leaf; 2.9 m for the XT-32).
  Without this limit the far rows it drops in a corridor are the door frames and ends that carry
  the along-axis information: corridor 8.1 and 7.5 cm on seeds 0 and 1 instead of 3.6 and 2.8.

Everything is derived from the sweep itself, so the check carries to any ring count, column
count and ring numbering:

* adjacent rings are adjacent in *measured* mean elevation (``ring`` ids are only labels; the
  drivers number them top-first, bottom-first or interleaved), and the ring spacing is the median
  elevation step between them;
* the column spacing is the median azimuth step within a ring;
* the patch spans the point's ring and the two adjacent ones, and ``window_ring_spacings`` ring
  spacings of azimuth either side, whatever the column count.

Topology (which samples are neighbours) comes from the raw sweep: its rings and azimuths as
measured. Geometry (the plane of the patch) comes from the same samples undistorted to the scan
end, the frame of the rows' points.
"""

from __future__ import annotations

import numpy as np

from adalio.jit import kernel

PLANAR_RATIO = 0.3
"""A patch is planar when its smallest principal variance is below this fraction of the middle
one; non-planar patches (edges, clutter) judge nothing."""

HALVES_AGREE_DEG = 10.0
"""A planar patch is one plane when the planes of its four halves are within this of its own."""


@kernel()
def _ring_layout(points: np.ndarray, ring: np.ndarray):
    """Rings ranked by mean elevation and each ring's samples sorted by azimuth.

    Returns (rank of each point (N,) int64, azimuth of each point (N,), order (N,) int64: the
    point indices sorted by (rank, azimuth), start (R+1,) int64: each rank's first position in
    ``order``, ring spacing (rad, NaN with fewer than 2 rings), column spacing (rad, NaN when no
    ring holds two distinct azimuths)).
    """
    n = points.shape[0]
    n_ids = 65536
    count = np.zeros(n_ids, np.int64)
    elev_sum = np.zeros(n_ids)
    az = np.empty(n)
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        az[i] = np.arctan2(y, x)
        r = np.sqrt(x * x + y * y + z * z)
        q = ring[i]
        count[q] += 1
        elev_sum[q] += np.arcsin(min(1.0, max(-1.0, z / r))) if r > 0.0 else 0.0
    ids = np.flatnonzero(count)
    n_rings = ids.shape[0]
    mean_elev = np.empty(n_rings)
    for k in range(n_rings):
        mean_elev[k] = elev_sum[ids[k]] / count[ids[k]]
    by_elev = np.argsort(mean_elev)
    rank_of_id = np.full(n_ids, -1, np.int64)
    start = np.zeros(n_rings + 1, np.int64)
    for k in range(n_rings):
        rank_of_id[ids[by_elev[k]]] = k
        start[k + 1] = start[k] + count[ids[by_elev[k]]]
    rank = np.empty(n, np.int64)
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        k = rank_of_id[ring[i]]
        rank[i] = k
        order[fill[k]] = i
        fill[k] += 1
    n_steps = 0
    steps = np.empty(max(n - n_rings, 1))
    for k in range(n_rings):
        s, e = start[k], start[k + 1]
        seg = order[s:e]
        seg_sorted = seg[np.argsort(az[seg], kind="mergesort")]
        order[s:e] = seg_sorted
        for j in range(1, e - s):
            d = az[seg_sorted[j]] - az[seg_sorted[j - 1]]
            if d > 1e-9:
                steps[n_steps] = d
                n_steps += 1
    if n_rings >= 2:
        ring_step = np.median(np.diff(mean_elev[by_elev]))
    else:
        ring_step = np.nan
    col_step = np.median(steps[:n_steps]) if n_steps else np.nan
    return rank, az, order, start, ring_step, col_step


@kernel()
def _nearest_member(points: np.ndarray, voxel_of_point: np.ndarray,
                    centroids: np.ndarray) -> np.ndarray:
    """Index of the point of each voxel closest to its centroid (-1 for an empty voxel)."""
    m = centroids.shape[0]
    best = np.full(m, np.inf)
    rep = np.full(m, -1, np.int64)
    for i in range(points.shape[0]):
        v = voxel_of_point[i]
        if v < 0:
            continue
        d = 0.0
        for a in range(3):
            t = points[i, a] - centroids[v, a]
            d += t * t
        if d < best[v]:
            best[v] = d
            rep[v] = i
    return rep


@kernel()
def _plane_normal(q: np.ndarray, rows: np.ndarray, cols: np.ndarray):
    """Unit normal and the two smallest principal variances of the samples ``q[rows][:, cols]``
    (q: (rings, columns, 3))."""
    s1 = np.zeros(3)
    s2 = np.zeros((3, 3))
    cnt = 0.0
    for a in rows:
        for b in cols:
            for u in range(3):
                s1[u] += q[a, b, u]
                for v in range(3):
                    s2[u, v] += q[a, b, u] * q[a, b, v]
            cnt += 1.0
    mu = s1 / cnt
    lam, vec = np.linalg.eigh(s2 / cnt - np.outer(mu, mu))
    return vec[:, 0].copy(), lam[0], lam[1]


@kernel()
def _patch_normals(points_end: np.ndarray, rank: np.ndarray, az: np.ndarray, order: np.ndarray,
                   start: np.ndarray, query: np.ndarray, half_width: int, max_gap_rad: float,
                   max_range_m: float, planar_ratio: float, min_agree_cos: float):
    """Plane of the patch around each queried point: its ring and the two adjacent ones,
    ``half_width`` samples either side in azimuth (raw topology), fitted to ``points_end``.

    A query is judged (``planar`` True) only if it is not -1, lies within ``max_range_m``, the
    patch is complete (three rings, no sample farther than ``max_gap_rad`` in azimuth), planar
    (smallest principal variance below ``planar_ratio`` times the middle one), and one plane:
    the planes of its four halves (left, right, upper two rings, lower two rings) all within
    ``acos(min_agree_cos)`` of the patch's, so a patch folded over an edge is not judged.
    Returns (unit normals (Q,3), planar (Q,) bool).
    """
    nq = query.shape[0]
    n_rings = start.shape[0] - 1
    normals = np.zeros((nq, 3))
    planar = np.zeros(nq, np.bool_)
    w = 2 * half_width + 1
    patch = np.empty((3, w, 3))
    all_rows = np.arange(3)
    all_cols = np.arange(w)
    halves_rows = (np.arange(3), np.arange(3), np.arange(0, 2), np.arange(1, 3))
    halves_cols = (np.arange(0, half_width + 1), np.arange(half_width, w), np.arange(w),
                   np.arange(w))
    for q in range(nq):
        i = query[q]
        if i < 0:
            continue
        x0, y0, z0 = points_end[i, 0], points_end[i, 1], points_end[i, 2]
        if x0 * x0 + y0 * y0 + z0 * z0 > max_range_m * max_range_m:
            continue
        k0 = rank[i]
        if k0 < 1 or k0 > n_rings - 2:
            continue
        a0 = az[i]
        complete = True
        for dk in range(3):
            s, e = start[k0 - 1 + dk], start[k0 + dk]
            n_k = e - s
            if n_k < w:
                complete = False
                break
            lo, hi = s, e  # first position with azimuth >= a0
            while lo < hi:
                mid = (lo + hi) // 2
                if az[order[mid]] < a0:
                    lo = mid + 1
                else:
                    hi = mid
            pos = lo - s
            for m in range(w):
                j = order[s + (pos + m - half_width) % n_k]
                d = abs(az[j] - a0)
                d = min(d, 2.0 * np.pi - d)
                if d > max_gap_rad:
                    complete = False
                    break
                for a in range(3):
                    patch[dk, m, a] = points_end[j, a]
            if not complete:
                break
        if not complete:
            continue
        n, lam0, lam1 = _plane_normal(patch, all_rows, all_cols)
        if not lam0 < planar_ratio * lam1:
            continue
        one_plane = True
        for h in range(4):
            nh, _, _ = _plane_normal(patch, halves_rows[h], halves_cols[h])
            if abs(nh[0] * n[0] + nh[1] * n[1] + nh[2] * n[2]) < min_agree_cos:
                one_plane = False
                break
        if one_plane:
            planar[q] = True
            normals[q, 0], normals[q, 1], normals[q, 2] = n[0], n[1], n[2]
    return normals, planar


class LocalSurface:
    """One sweep's rings, for the local planes of its downsampled points (module docstring).

    ``points_raw`` are the sweep's points as measured and ``points_end`` the same points
    undistorted to the scan end (both (N,3), LiDAR frame), ``ring`` their ring ids (N,) and
    ``rows`` the positions in these arrays of the points the odometry downsamples (the decimated
    ones, ``preprocess.point_filter_num``).
    """

    def __init__(self, points_raw: np.ndarray, points_end: np.ndarray, ring: np.ndarray,
                 rows: np.ndarray, window_ring_spacings: float) -> None:
        self.points_end = np.ascontiguousarray(points_end, dtype=np.float64)
        self.rows = np.asarray(rows, dtype=np.int64)
        (self.rank, self.az, self.order, self.start, self.ring_step_rad,
         self.col_step_rad) = _ring_layout(np.ascontiguousarray(points_raw, dtype=np.float64),
                                           np.ascontiguousarray(ring, dtype=np.uint16))
        self.usable = bool(np.isfinite(self.ring_step_rad) and self.ring_step_rad > 0
                           and np.isfinite(self.col_step_rad) and self.col_step_rad > 0)
        self.half_width = 1
        if self.usable:
            self.half_width = max(1, round(window_ring_spacings * self.ring_step_rad
                                           / self.col_step_rad))

    def max_range_m(self, max_patch_m: float) -> float:
        """Range within which the patch (two ring spacings tall) is at most ``max_patch_m``."""
        return max_patch_m / (2.0 * self.ring_step_rad) if self.usable else 0.0

    def members(self, points_down: np.ndarray, voxel_of_point: np.ndarray) -> np.ndarray:
        """(M,) the row (in the sweep's arrays) of the decimated point closest to each
        downsampled point's centroid, whose patch stands for it; -1 for none."""
        rep = _nearest_member(self.points_end[self.rows], voxel_of_point, points_down)
        return np.where(rep >= 0, self.rows[np.maximum(rep, 0)], -1)

    def normals(self, points_down: np.ndarray, voxel_of_point: np.ndarray,
                max_patch_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Local plane of each downsampled point: the patch around the decimated point closest
        to its centroid. ``voxel_of_point`` is ``voxel_downsample_with_index``'s second output
        for the decimated points. Returns (unit normals (M,3) in the LiDAR frame at the scan end,
        judged (M,) bool: False where the check abstains)."""
        m = points_down.shape[0]
        if not self.usable or m == 0:
            return np.zeros((m, 3)), np.zeros(m, np.bool_)
        query = self.members(points_down, voxel_of_point)
        max_gap = (self.half_width + 1.5) * self.col_step_rad
        return _patch_normals(self.points_end, self.rank, self.az, self.order, self.start,
                              query, self.half_width, max_gap,
                              self.max_range_m(max_patch_m), PLANAR_RATIO,
                              np.cos(np.radians(HALVES_AGREE_DEG)))


def disagrees(normals_map_world: np.ndarray, normals_local_lidar: np.ndarray,
              judged: np.ndarray, R_world_lidar: np.ndarray, max_angle_deg: float) -> np.ndarray:
    """(M,) bool: rows whose map plane's normal is more than ``max_angle_deg`` off the judged
    local plane's (both unsigned)."""
    n_loc = normals_local_lidar @ R_world_lidar.T
    c = np.abs(np.sum(np.nan_to_num(normals_map_world) * n_loc, axis=1))
    return judged & (c < np.cos(np.radians(max_angle_deg)))
