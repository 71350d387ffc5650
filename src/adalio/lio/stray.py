"""Stray returns: points whose range no neighbour along their ring continues, and that no
adjacent ring sees.

A spinning LiDAR's ring samples a surface at successive azimuths, so along the ring the range
of a point on a surface is the straight continuation of the two returns before it or of the two
after it: ``|r_i - (2 r_{i-1} - r_{i-2})|`` is the range's second difference, a few centimetres
of noise and curvature on a wall, the floor or a surface seen at a grazing angle (where the
range grows fast but steadily), and on either side of an edge (a door frame, a stair's nosing)
the point still continues its own side. A return on nothing that the ring samples again, such
as dust or rain in front of a wall (a dual-return LiDAR's other return), a multipath or
cross-talk ghost behind it, or a mixed pixel between two surfaces, continues neither side. So
does a thin thing one column wide (a post, a baluster, a cable), but the adjacent rings see that
at the same range and at the same time, and a speck of dust or a ghost they do not: a return
that neither side of its ring continues and that no adjacent ring's return near its time lies
at is a stray return, on no surface for a point-to-plane row, and kept it enters the map too.

This is the range-image neighbour test of LiDAR drivers' noise filters and of LOAM's rejection of
points whose neighbours jump in range, in its simplest form. The ring order is the points'
time order within each ring (azimuth order for a spinning LiDAR), and adjacent ring ids are
adjacent beams, as the Hesai, Ouster and Velodyne drivers number them. Clouds without rings are
not tested.

A Livox cloud's lasers (``CustomMsg``'s ``line``, or a Livox driver's PointCloud2's) are read as
its rings, each laser's points in firing order (``lines``). A laser's trace is no ring: it
changes elevation at every firing (about 1 deg a firing on the simulator's Mid-360), by steps
that a dropped return doubles, and turns at the edges of its band. Along it the range of a
surface seen at a grazing angle grows by up to metres a firing, and not in a straight line
(``h / sin(e)`` on a floor ``h`` below, over equal steps of elevation ``e``), and a pillar or a
car 10-20 m away is crossed in two or three firings: the range's second difference flagged
2.4 % of a clean Mid-360 sweep in the simulator's garage on average, up to 7.4 %, half its
sweeps above the 2 % that drop them. So along a laser a side continues a point where its ray
meets the straight line through the side's two returns within the tolerance of its range
(exact for a surface flat there, whatever the steps). A point no side continues is still no
stray return where the line through its two neighbours meets its ray, or where a neighbour lies
at its range that nothing continues either (a surface crossed in two or three firings; a ghost
or a speck of dust next to a surface's continued return is still stray): such a point is
``SUPPORTED``, as a thin thing that an adjacent ring sees, so a sweep's share counts only the
returns nothing sees, and a dirty sweep drops these with them (at edges the line between two
surfaces passes through where ghosts lie).
"""

from __future__ import annotations

import numpy as np

from adalio.jit import kernel
from adalio.lio.voxel import _bit_width, radix_argsort

MAX_RING_SPAN = 65536
"""Ring ids spread over more values than this are no rings (a LiDAR has at most a few hundred;
``Scan.ring`` is uint16)."""


def ring_id_span(ring: np.ndarray | None) -> int:
    """How many values a cloud's ring ids spread over (max - min + 1; 0 without rings or
    points)."""
    if ring is None or len(ring) == 0:
        return 0
    return int(np.max(ring)) - int(np.min(ring)) + 1


def rings_testable(span: int) -> bool:
    """Ring ids spread over ``span`` values (:func:`ring_id_span`) are rings the test reads:
    more than one id (a driver that fills the field with one value gives none), spread over at
    most :data:`MAX_RING_SPAN` (more: a field with another meaning)."""
    return 1 < span <= MAX_RING_SPAN


SUPPORT_SIDE = 2
"""An adjacent ring's points nearest in time that may support a point: this many fired before
its time and as many after (its column and the next on either side, for a spinning LiDAR)."""


@kernel()
def _ring_order(ring: np.ndarray, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices sorting the points by ring, then by time (stable: equal times keep the message
    order, as the two returns of one firing), and where each ring id from the smallest on
    starts in that order (``starts[k]``: ring ``min + k``; an id without points starts where
    the next one does). The ring ids span at most ``MAX_RING_SPAN`` values (a counting sort);
    within a ring the times sort by the map's stable radix sort (``voxel.radix_argsort``,
    which a run compiles anyway: numba's merge sort took 1 s of a cold start)."""
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
            t0 = t1 = t_ns[seg[0]]
            for j in range(b - a):
                t0 = min(t0, t_ns[seg[j]])
                t1 = max(t1, t_ns[seg[j]])
            keys = np.empty(b - a, np.int64)
            for j in range(b - a):
                keys[j] = t_ns[seg[j]] - t0
            idx = radix_argsort(keys, _bit_width(t1 - t0))
            for j in range(b - a):
                order[a + j] = seg[idx[j]]
    return order, starts


@kernel()
def _first_at_or_after(t_sorted: np.ndarray, a: int, b: int, t: int) -> int:
    """The first index in ``[a, b)`` whose time is at or after ``t`` (``b`` if none): a binary
    search of ``t_sorted``, sorted there (``np.searchsorted``'s left side)."""
    while a < b:
        mid = (a + b) // 2
        if t_sorted[mid] < t:
            a = mid + 1
        else:
            b = mid
    return a


CONTINUED = 0
"""``stray_codes``: a side of its ring continues the point's range (or it has no side to judge)."""
SUPPORTED = 1
"""``stray_codes``: no side of its ring continues it, but an adjacent ring sees a return at its
range there (a thin thing; or a point whose ring neighbour is a stray return); along a Livox
laser also a point on its neighbours' line, or next to one at its range (module docstring)."""
STRAY = 2
"""``stray_codes``: a stray return."""


@kernel()
def _meets_the_line(q: np.ndarray, r: np.ndarray, i: int, near: int, far: int,
                    tol: float, on_one_ray: float) -> bool:
    """Along a Livox laser: whether the ray of sorted point ``i`` meets the straight line
    through points ``far`` and ``near`` (two of its neighbours) within ``tol`` of its range
    ``r[i]``. In the plane of the two returns and the origin, the line's points
    ``p`` satisfy ``(a x b) . (p x d) = |a x b|^2`` (``a``, ``b`` the far and near return,
    ``d = b - a``), so along the ray ``u`` it lies at ``s`` with ``1 / s = (a x b) . (u x d) /
    |a x b|^2``: no division by a grazing angle, and nothing assumed of the steps. Where the two
    returns lie on one ray (``a x b`` vanishing against their ranges), the range
    ``on_one_ray`` (their straight continuation) instead."""
    ax, ay, az = q[far, 0], q[far, 1], q[far, 2]
    bx, by, bz = q[near, 0], q[near, 1], q[near, 2]
    wx, wy, wz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    ww = wx * wx + wy * wy + wz * wz
    if not ww > 1e-12 * (r[far] * r[near]) ** 2:
        return abs(r[i] - on_one_ray) <= tol
    ri = r[i]
    if not ri > 0.0:
        return False
    ux, uy, uz = q[i, 0] / ri, q[i, 1] / ri, q[i, 2] / ri
    dx, dy, dz = bx - ax, by - ay, bz - az
    inv_s = (wx * (uy * dz - uz * dy) + wy * (uz * dx - ux * dz)
             + wz * (ux * dy - uy * dx)) / ww
    return inv_s > 0.0 and abs(1.0 - ri * inv_s) <= tol * inv_s


@kernel()
def stray_codes(points: np.ndarray, t_ns: np.ndarray, ring: np.ndarray,
                tolerance_m: float, tolerance_rel: float, lines: bool) -> np.ndarray:
    """(N,) int8: ``STRAY`` for a stray return, a point whose range neither the two points
    before it along its ring nor the two after it continue within ``tolerance_m +
    tolerance_rel * r``, and that no point of an adjacent ring (id -1 or +1) among the
    ``SUPPORT_SIDE`` fired before its time and as many at or after it lies within that of
    (module docstring); ``SUPPORTED`` where its ring does not continue it but such an adjacent
    ring's point lies at its range; ``CONTINUED`` otherwise, and for a point with fewer than two
    ring neighbours on both sides. ``lines``: the ids are a Livox cloud's lasers, along which a
    side continues a point where its ray meets the straight line through the side's two points
    (:func:`_meets_the_line`), and a point no side continues is ``SUPPORTED`` where the line
    through its two neighbours meets its ray, or a neighbour that nothing continues either lies
    at its range (module docstring)."""
    n = points.shape[0]
    order, starts = _ring_order(ring, t_ns)
    lo = ring[order[0]] if n else 0
    r = np.empty(n)
    ring_sorted = np.empty(n, np.int64)
    t_sorted = np.empty(n, np.int64)
    q = np.empty((n if lines else 0, 3))
    for i in range(n):
        x, y, z = points[order[i], 0], points[order[i], 1], points[order[i], 2]
        r[i] = np.sqrt(x * x + y * y + z * z)
        ring_sorted[i] = ring[order[i]]
        t_sorted[i] = t_ns[order[i]]
        if lines:
            q[i, 0], q[i, 1], q[i, 2] = x, y, z
    judged = np.zeros(n, np.bool_)
    fits = np.zeros(n, np.bool_)  # a side continues it
    between = np.zeros(n, np.bool_)  # along a laser: the line through its neighbours does
    for i in range(n):
        tol = tolerance_m + tolerance_rel * r[i]
        if i >= 2 and ring_sorted[i - 2] == ring_sorted[i]:
            judged[i] = True
            if lines:
                fits[i] = _meets_the_line(q, r, i, i - 1, i - 2, tol,
                                          2.0 * r[i - 1] - r[i - 2])
            else:
                fits[i] = abs(r[i] - (2.0 * r[i - 1] - r[i - 2])) <= tol
        if not fits[i] and i + 2 < n and ring_sorted[i + 2] == ring_sorted[i]:
            judged[i] = True
            if lines:
                fits[i] = _meets_the_line(q, r, i, i + 1, i + 2, tol,
                                          2.0 * r[i + 1] - r[i + 2])
            else:
                fits[i] = abs(r[i] - (2.0 * r[i + 1] - r[i + 2])) <= tol
        if (lines and judged[i] and not fits[i] and 1 <= i < n - 1
                and ring_sorted[i - 1] == ring_sorted[i] == ring_sorted[i + 1]):
            between[i] = _meets_the_line(q, r, i, i + 1, i - 1, tol,
                                         0.5 * (r[i - 1] + r[i + 1]))
    code = np.zeros(n, np.int8)
    for i in range(n):
        if not judged[i] or fits[i]:
            continue
        tol = tolerance_m + tolerance_rel * r[i]
        if lines:  # on a surface the trace crossed in two or three firings: between its
            # neighbours, or next to one at its range that no side continues either (next to a
            # continued one, as a ghost behind it, it stays stray); dropped in a dirty sweep, as
            # the points an adjacent ring supports
            seen = between[i]
            for j in (i - 1, i + 1):
                if (0 <= j < n and ring_sorted[j] == ring_sorted[i] and not fits[j]
                        and not between[j] and abs(r[i] - r[j]) <= tol):
                    seen = True
            if seen:
                code[order[i]] = SUPPORTED
                continue
        code[order[i]] = STRAY
        for step in (-1, 1):  # a thin thing that an adjacent ring sees too is no stray return
            k = ring_sorted[i] + step - lo
            if k < 0 or k >= starts.shape[0]:
                continue  # no such ring
            a = starts[k]
            b = starts[k + 1] if k + 1 < starts.shape[0] else n
            j = _first_at_or_after(t_sorted, a, b, t_sorted[i])
            for c in range(max(a, j - SUPPORT_SIDE), min(b, j + SUPPORT_SIDE)):
                if abs(r[c] - r[i]) <= tol:
                    code[order[i]] = SUPPORTED
                    break
            if code[order[i]] == SUPPORTED:
                break
    return code


def stray_returns(points: np.ndarray, t_ns: np.ndarray, ring: np.ndarray,
                  tolerance_m: float, tolerance_rel: float, lines: bool = False) -> np.ndarray:
    """(N,) bool: the stray returns (``stray_codes`` == ``STRAY``)."""
    return stray_codes(points, t_ns, ring, tolerance_m, tolerance_rel, lines) == STRAY
