"""Stray returns: points whose range no neighbour along their ring continues.

A spinning LiDAR's ring samples a surface at successive azimuths, so along the ring the range
of a point on a surface is the straight continuation of the two returns before it or of the two
after it: ``|r_i - (2 r_{i-1} - r_{i-2})|`` is the range's second difference, a few centimetres
of noise and curvature on a wall, the floor or a surface seen at a grazing angle (where the
range grows fast but steadily), and on either side of an edge (a door frame, a stair's nosing)
the point still continues its own side. A return on nothing that the ring samples again, such
as dust or rain in front of a wall (a dual-return LiDAR's other return), a multipath or
cross-talk ghost behind it, or a mixed pixel between two surfaces, continues neither side: it is
a stray return, on no surface for a point-to-plane row, and kept it enters the map as well.

This is the range-image neighbour test of LiDAR drivers' noise filters and of LOAM's rejection of
points whose neighbours jump in range, in its simplest form. The ring order is the points'
time order within each ring (azimuth order for a spinning LiDAR); clouds without rings (a Livox
``CustomMsg``) are not tested, and a Livox driver's PointCloud2 ``line`` (one laser's scan) is
read as the ring.
"""

from __future__ import annotations

import numpy as np

from adalio.jit import kernel

MAX_RING_SPAN = 65536
"""Ring ids spread over more values than this are no rings (a LiDAR has at most a few hundred;
``Scan.ring`` is uint16)."""


@kernel()
def _ring_order(ring: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """Indices sorting the points by ring, then by time (stable: equal times keep the message
    order, as the two returns of one firing). The ring ids span at most ``MAX_RING_SPAN`` values
    (a counting sort)."""
    n = ring.shape[0]
    lo, hi = 0, 0
    if n:
        lo, hi = ring[0], ring[0]
    for i in range(n):
        lo = min(lo, ring[i])
        hi = max(hi, ring[i])
    counts = np.zeros(hi - lo + 2, np.int64)
    for i in range(n):
        counts[ring[i] - lo + 1] += 1
    for k in range(1, counts.shape[0]):
        counts[k] += counts[k - 1]
    starts = counts[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        k = ring[i] - lo
        order[counts[k]] = i
        counts[k] += 1
    for k in range(starts.shape[0]):  # within each ring, by time unless already in order
        a = starts[k]
        b = starts[k + 1] if k + 1 < starts.shape[0] else n
        ordered = True
        for j in range(a + 1, b):
            if t_ns[order[j]] < t_ns[order[j - 1]]:
                ordered = False
                break
        if not ordered:
            seg = order[a:b].copy()
            idx = np.argsort(t_ns[seg], kind="mergesort")
            for j in range(b - a):
                order[a + j] = seg[idx[j]]
    return order


@kernel()
def stray_returns(points: np.ndarray, t_ns: np.ndarray, ring: np.ndarray,
                  tolerance_m: float, tolerance_rel: float) -> np.ndarray:
    """(N,) bool: True for a stray return, a point whose range neither the two points before
    it along its ring nor the two after it continue within ``tolerance_m + tolerance_rel * r``
    (module docstring). A point with fewer than two ring neighbours on both sides is kept."""
    n = points.shape[0]
    order = _ring_order(ring, t_ns)
    r = np.empty(n)
    for i in range(n):
        x, y, z = points[order[i], 0], points[order[i], 1], points[order[i], 2]
        r[i] = np.sqrt(x * x + y * y + z * z)
    stray = np.zeros(n, np.bool_)
    for i in range(n):
        tol = tolerance_m + tolerance_rel * r[i]
        judged = False
        fits = False
        if i >= 2 and ring[order[i - 2]] == ring[order[i]]:
            judged = True
            fits = abs(r[i] - (2.0 * r[i - 1] - r[i - 2])) <= tol
        if not fits and i + 2 < n and ring[order[i + 2]] == ring[order[i]]:
            judged = True
            fits = abs(r[i] - (2.0 * r[i + 1] - r[i + 2])) <= tol
        stray[order[i]] = judged and not fits
    return stray
