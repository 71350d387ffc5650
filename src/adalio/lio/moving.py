"""Points on moving things (people walking by), told by where the LiDAR has seen through.

A spinning LiDAR sees along each ray up to its return: the space in front of it is free at that
time. A static surface never lies in space a ray has passed through; a moving one does:

* **Seen through (the map)**: a map point that lies in front of the current sweep's returns
  along the same direction, by more than the margin, is no longer there. It is removed from the
  map (:meth:`adalio.lio.ivox.IVox.remove_points`), so it neither pulls the next scans nor stays
  in the map written out. Only the map points inserted in the last ``map.moving_window_s`` are
  tested (a trail is seen through while its walker is still in view), and only those no return
  of the sweep lies next to (``map.moving_surface_check``): a point on the edge of a surface the
  sweep still sees (a stair's nosing, a wall's end, a rail), placed a few centimetres off by the
  poses in between, is passed by rays that hit the surface behind it although nothing moved.
  With ``map.moving_surface_check_behind`` off, returns behind a point along its ray do not keep
  it, only those beside or in front of it: the back of someone walking away stands behind the
  trail they left, which is then carved (the corridor with people gains, the shaft loses).
* **In free space (the sweep)**: a point of the current sweep that lies in space an earlier
  sweep (about ``map.moving_lookback_s`` before) saw through is on something that moved there,
  as a person walking towards the sensor. It takes no part in the update and is not inserted.
* **The same body** (``map.moving_body_m``, 0.3 m by default): a point of the sweep within
  ``map.moving_body_m`` of one of its points in free space, or of a point seen through lately,
  is on the same moving thing (the tests above catch a third to two thirds of a walker's
  points: those next to nearer floor or wall returns, and the back of someone walking away,
  which stands behind its own trail, stay unjudged), and is kept out as they are, unless the
  map holds a point within the margin or its cell of it (the larger; a map keeps one point per
  cell): there it is on a surface the map already holds (the floor under the walker's feet, a
  wall beside them).
* **Near what was seen through (probation)**: a point of the sweep within
  ``map.moving_near_m`` of a point seen through lately (the back of someone walking away, whose
  last positions are the trail just removed) enters the map ``map.moving_probation_s`` late,
  unless a sweep sees through it meanwhile (:class:`MovingPoints`). Every other point enters at
  once: the newest map is what the rows at its leading edge need.

This is the visibility (ray-casting) principle of free-space carving in occupancy mapping
(OctoMap), of the offline map cleaners Removert and ERASOR and of M-detector's occlusion tests
for moving points in LiDAR streams, in its simplest form: one range image per sweep, the
nearest return per pixel, and a point is in free space only if every non-empty pixel of its
3x3 neighbourhood returned farther than it by the margin, with returns on all four sides of
it, so a surface seen at a grazing angle, the edge of the field of view or a rod between two
rays is not taken for free space.

Frames: a range image is in the LiDAR frame of its sweep's end (the undistorted points); poses
``(R_WL, p_WL)`` map that frame into the world. Ranges in metres, angles in radians.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from adalio.jit import kernel
from adalio.lio.map_uncertainty import cell_keys


@kernel()
def _atan2(y: float, x: float) -> float:
    """atan2 to within 2.1e-4 rad (0.012°, largest at 45°; a cubic in the tangent's square on
    [0, 1]): pixels of a degree need no more, and images and queries use the same function."""
    ax = abs(x)
    ay = abs(y)
    hi = max(ax, ay)
    if hi == 0.0:
        return 0.0
    a = min(ax, ay) / hi
    s = a * a
    r = ((-0.0464964749 * s + 0.15931422) * s - 0.327622764) * s * a + a
    if ay > ax:
        r = 0.5 * np.pi - r
    if x < 0.0:
        r = np.pi - r
    if y < 0.0:
        r = -r
    return r


@kernel()
def _pixel(x: float, y: float, z: float, r: float, pixel: float, n_el: int, n_az: int):
    """(row, col) of a direction: rows even in the sine of the elevation (within 5 % of even in
    elevation up to ±18°, 8 % to ±22.5°, where spinning LiDARs look), columns in azimuth."""
    row = min(max(int((z / r + 1.0) / pixel), 0), n_el - 1)
    col = min(int((_atan2(y, x) + np.pi) / pixel), n_az - 1)
    return row, col


@kernel()
def _in_lidar(points_world: np.ndarray, i: int, R_WL: np.ndarray, p_WL: np.ndarray):
    """Row ``i`` of ``points_world`` in the LiDAR frame of the pose ``(R_WL, p_WL)``."""
    dx = points_world[i, 0] - p_WL[0]
    dy = points_world[i, 1] - p_WL[1]
    dz = points_world[i, 2] - p_WL[2]
    return (R_WL[0, 0] * dx + R_WL[1, 0] * dy + R_WL[2, 0] * dz,
            R_WL[0, 1] * dx + R_WL[1, 1] * dy + R_WL[2, 1] * dz,
            R_WL[0, 2] * dx + R_WL[1, 2] * dy + R_WL[2, 2] * dz)


@kernel()
def nearest_image(points_lidar: np.ndarray, pixel_rad: float) -> np.ndarray:
    """(rows, cols, 4) over the sphere in pixels of about ``pixel_rad`` (:func:`_pixel`): per
    pixel the nearest return in it, its (x, y, z) in the LiDAR frame and its range (all 0: no
    return)."""
    n_el = int(np.ceil(2.0 / pixel_rad))
    n_az = int(np.ceil(2.0 * np.pi / pixel_rad))
    near = np.zeros((n_el, n_az, 4))
    for i in range(points_lidar.shape[0]):
        x = points_lidar[i, 0]
        y = points_lidar[i, 1]
        z = points_lidar[i, 2]
        r = np.sqrt(x * x + y * y + z * z)
        if not r > 0.0:
            continue
        row, col = _pixel(x, y, z, r, pixel_rad, n_el, n_az)
        if near[row, col, 3] == 0.0 or r < near[row, col, 3]:
            near[row, col, 0] = x
            near[row, col, 1] = y
            near[row, col, 2] = z
            near[row, col, 3] = r
    return near


@kernel()
def bracketed_image(near: np.ndarray) -> np.ndarray:
    """(rows, cols) from :func:`nearest_image`: per pixel, the nearest return among the
    non-empty pixels of its 3x3 neighbourhood (azimuth wrapping round) where returns bracket it
    (a non-empty pixel in the row above and below, the column left and right), else 0
    (unknown). A point nearer than that value by the margin lies in space the rays all round it
    passed: free space. The bracket keeps the edge of what the sweep saw (the field of view's
    top and bottom ring, which graze floor and ceiling, the ends of the returns) unknown:
    nothing beyond them vouches for it."""
    n_el, n_az = near.shape[0], near.shape[1]
    lo_row = n_el
    hi_row = -1
    for row in range(n_el):
        for col in range(n_az):
            if near[row, col, 3] > 0.0:
                lo_row = min(lo_row, row)
                hi_row = max(hi_row, row)
                break
    out = np.zeros((n_el, n_az))
    for row in range(max(lo_row, 1), min(hi_row + 1, n_el - 1)):
        for col in range(n_az):
            low = np.inf
            below = False
            above = False
            left = False
            right = False
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    v = near[row + dr, (col + dc) % n_az, 3]
                    if v > 0.0:
                        low = min(low, v)
                        below |= dr < 0
                        above |= dr > 0
                        left |= dc < 0
                        right |= dc > 0
            if below and above and left and right:
                out[row, col] = low
    return out


@kernel()
def range_image(points_lidar: np.ndarray, pixel_rad: float) -> np.ndarray:
    """:func:`bracketed_image` of the sweep ``points_lidar`` (LiDAR frame)."""
    return bracketed_image(nearest_image(points_lidar, pixel_rad))


@kernel()
def in_free_space(points_world: np.ndarray, R_WL: np.ndarray, p_WL: np.ndarray,
                  img: np.ndarray, pixel_rad: float, margin_m: float,
                  margin_fraction: float) -> np.ndarray:
    """(N,) bool: each world point lies in space the sweep of ``img`` (:func:`range_image`,
    taken at ``R_WL, p_WL``) saw through: nearer than every return around its direction by
    ``margin_m + margin_fraction * range``."""
    n_el, n_az = img.shape
    out = np.zeros(points_world.shape[0], np.bool_)
    for i in range(points_world.shape[0]):
        x, y, z = _in_lidar(points_world, i, R_WL, p_WL)
        r = np.sqrt(x * x + y * y + z * z)
        if not r > 0.0:
            continue
        row, col = _pixel(x, y, z, r, pixel_rad, n_el, n_az)
        v = img[row, col]
        out[i] = v > r + margin_m + margin_fraction * r
    return out


@kernel()
def seen_through(points_world: np.ndarray, R_WL: np.ndarray, p_WL: np.ndarray,
                 img: np.ndarray, near: np.ndarray, pixel_rad: float, margin_m: float,
                 margin_fraction: float, behind: bool) -> np.ndarray:
    """(N,) bool: each world point lies in free space (:func:`in_free_space`, ``img``) and no
    return of the sweep (``near``, :func:`nearest_image`, the nearest of each pixel) lies
    within ``margin_m + (margin_fraction + pixel_rad) * range`` of it (the margin, and one
    pixel's width at its range): a point on the edge of a surface the sweep still sees beside
    it (a stair's nosing, a wall's end, a rail) that the poses of the scans in between placed a
    few centimetres off is not taken for something that moved away. With ``behind`` false only
    the returns beside or in front of the point count (their range at most the point's plus
    ``margin_m``), not those behind it along its ray, which are what the rays through it hit
    (the back of someone walking away stands behind the trail they left)."""
    out = in_free_space(points_world, R_WL, p_WL, img, pixel_rad, margin_m, margin_fraction)
    n_el, n_az = near.shape[0], near.shape[1]
    for i in range(points_world.shape[0]):
        if not out[i]:
            continue
        x, y, z = _in_lidar(points_world, i, R_WL, p_WL)
        r = np.sqrt(x * x + y * y + z * z)
        row, col = _pixel(x, y, z, r, pixel_rad, n_el, n_az)
        reach = margin_m + (margin_fraction + pixel_rad) * r
        # every pixel holding a direction within the reach's angle of the point's: rows are
        # even in the sine of the elevation, columns narrow with its cosine
        ang = np.arcsin(min(reach / r, 1.0)) if reach < r else np.pi
        cos_el = np.sqrt(max(1.0 - (z / r) ** 2, 0.0))
        h_row = min(int(np.ceil(ang / pixel_rad)) + 1, n_el)
        h_col = n_az // 2 + 1
        if ang < 0.5 * np.pi and cos_el > np.sin(ang):
            # the azimuth half-width of the cone round the point's direction
            h_col = min(int(np.ceil(np.arcsin(np.sin(ang) / cos_el) / pixel_rad)) + 1, h_col)
        reach2 = reach * reach
        for row2 in range(max(row - h_row, 0), min(row + h_row + 1, n_el)):
            for dc in range(-h_col, h_col + 1):
                col2 = (col + dc) % n_az
                rn = near[row2, col2, 3]
                if rn == 0.0 or (not behind and rn > r + margin_m):  # none; behind the point
                    continue
                ex = near[row2, col2, 0] - x
                ey = near[row2, col2, 1] - y
                ez = near[row2, col2, 2] - z
                if ex * ex + ey * ey + ez * ez < reach2:
                    out[i] = False
                    break
            if not out[i]:
                break
    return out


_CELL_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)],
                         dtype=np.float64)


def near_any(points: np.ndarray, sources: np.ndarray, radius_m: float) -> np.ndarray:
    """(N,) bool: each point lies within ``radius_m`` of one of ``sources`` (both (., 3), same
    frame). Only the points in the cells of edge ``radius_m`` next to a source's are measured
    (a sweep has tens of thousands of points, the sources a few hundred)."""
    out = np.zeros(points.shape[0], np.bool_)
    if not sources.shape[0] or not points.shape[0] or not radius_m > 0.0:
        return out
    # the 27 cells round each source's, by their centres (each well inside its cell)
    centres = (np.floor(sources / radius_m)[:, None, :] + _CELL_OFFSETS + 0.5) * radius_m
    near_cells = np.unique(cell_keys(centres.reshape(-1, 3), radius_m))
    keys = cell_keys(np.ascontiguousarray(points, dtype=np.float64), radius_m)
    at = np.minimum(np.searchsorted(near_cells, keys), near_cells.size - 1)
    idx = np.flatnonzero(near_cells[at] == keys)
    if idx.size:
        dist = cKDTree(sources).query(points[idx], distance_upper_bound=radius_m)[0]
        out[idx] = dist < radius_m
    return out


class SweepImage(NamedTuple):
    """A sweep's range images (LiDAR frame of its end)."""

    free: np.ndarray
    """:func:`bracketed_image`: where its rays passed."""
    nearest: np.ndarray
    """:func:`nearest_image`: its nearest return per pixel."""


@dataclass
class _Sweep:
    t_ns: int
    R_WL: np.ndarray
    p_WL: np.ndarray
    img: np.ndarray


@dataclass
class MovingPoints:
    """The sweeps' range images and the map's young points, for one run.

    A sweep's points near where a sweep saw through lately (within ``near_m``, over the last
    lookback) wait ``probation_ns`` before they enter the map (:meth:`admit`, :meth:`matured`):
    there something is walking by, and its points have moved on by then, so the map never offers
    them as neighbours to the sweeps right after (whose rows they would pull along with the
    walker), and the sweeps in between see through the space they left (:meth:`carve`). Points
    elsewhere enter at once, as without moving things."""

    pixel_rad: float
    margin_m: float
    margin_fraction: float
    lookback_ns: int
    window_ns: int
    probation_ns: int
    near_m: float
    body_m: float = 0.0
    surface_check: bool = True
    """Carve only points no return of the sweep lies next to (:func:`seen_through`)."""
    surface_check_behind: bool = True
    """With ``surface_check``: returns behind a point along its ray count too (False: only
    those beside or in front of it)."""
    _sweeps: deque = field(default_factory=deque)
    _pending: deque = field(default_factory=deque)
    """(t_ns, world points, map cell edge) waiting to enter the map."""
    _recent: deque = field(default_factory=deque)
    """(t_ns, world points stored in the map at t_ns), over the last window."""
    _seen: deque = field(default_factory=deque)
    """(t_ns, points seen through at t_ns), over the last lookback."""
    removed: int = 0
    """Points seen through so far: removed from the map or from those waiting to enter it."""
    dropped: int = 0
    """Sweep points kept out of the update and the map so far (in free space, or on the same
    body as such a point or one seen through)."""

    @classmethod
    def from_config(cls, cfg) -> MovingPoints:
        """From the ``map`` config section."""
        return cls(np.radians(cfg.moving_pixel_deg), cfg.moving_margin_m,
                   cfg.moving_margin_fraction, round(cfg.moving_lookback_s * 1e9),
                   round(cfg.moving_window_s * 1e9), round(cfg.moving_probation_s * 1e9),
                   cfg.moving_near_m, cfg.moving_body_m, cfg.moving_surface_check,
                   cfg.moving_surface_check_behind)

    def image(self, points_lidar: np.ndarray) -> SweepImage:
        near = nearest_image(np.ascontiguousarray(points_lidar, dtype=np.float64),
                             self.pixel_rad)
        return SweepImage(bracketed_image(near), near)

    def carve(self, ivox, img: SweepImage, R_WL: np.ndarray, p_WL: np.ndarray,
              t_ns: int) -> int:
        """Drop the points waiting to enter the map and remove from ``ivox`` those stored
        within the window that the sweep ``img`` (at ``R_WL, p_WL``) saw through
        (:func:`seen_through`; with ``surface_check`` off, :func:`in_free_space` alone);
        returns how many."""
        while self._recent and self._recent[0][0] < t_ns - self.window_ns:
            self._recent.popleft()
        while self._seen and self._seen[0][0] < t_ns - self.lookback_ns:
            self._seen.popleft()
        n = 0
        for queue, in_map in ((self._pending, False), (self._recent, True)):
            if not queue:
                continue
            pts = np.concatenate([q[1] for q in queue])
            if self.surface_check:
                free = seen_through(pts, R_WL, p_WL, img.free, img.nearest, self.pixel_rad,
                                    self.margin_m, self.margin_fraction,
                                    self.surface_check_behind)
            else:
                free = in_free_space(pts, R_WL, p_WL, img.free, self.pixel_rad,
                                     self.margin_m, self.margin_fraction)
            if not free.any():
                continue
            n += int(free.sum())
            self._seen.append((int(t_ns), pts[free]))
            if in_map:
                ivox.remove_points(pts[free])
            ends = np.cumsum([len(q[1]) for q in queue])
            kept = deque((q[0], q[1][~g], *q[2:]) for q, g in
                         zip(queue, np.split(free, ends[:-1]), strict=True) if not g.all())
            if in_map:
                self._recent = kept
            else:
                self._pending = kept
        self.removed += n
        return n

    def moving(self, points_world: np.ndarray, t_ns: int, ivox=None,
               cell_m: float = 0.0) -> np.ndarray:
        """(N,) bool: the sweep's points (world, at its predicted pose) in space the sweep about
        ``lookback_ns`` earlier saw through, and those within ``body_m`` of one of them or of a
        point seen through within the lookback (call :meth:`carve` first), unless the map
        ``ivox`` holds a point within the margin or its cell ``cell_m`` of them, the larger (a
        surface the map holds: the floor under a walker's feet, a wall beside them)."""
        past = None
        for s in self._sweeps:
            if s.t_ns <= t_ns - self.lookback_ns:
                past = s
        out = np.zeros(points_world.shape[0], np.bool_)
        if past is not None:
            out = in_free_space(points_world, past.R_WL, past.p_WL, past.img, self.pixel_rad,
                                self.margin_m, self.margin_fraction)
        if self.body_m > 0.0:
            sources = np.concatenate([points_world[out], *(p for _, p in self._seen)])
            body = near_any(points_world, sources, self.body_m) & ~out
            on_map_m = max(self.margin_m, cell_m)
            if ivox is not None and on_map_m > 0.0 and body.any():
                rows = np.flatnonzero(body)
                body[rows[ivox.knn(points_world[rows], 1, on_map_m)[1] > 0]] = False
            out |= body
        self.dropped += int(out.sum())
        return out

    def add_sweep(self, img: SweepImage, R_WL: np.ndarray, p_WL: np.ndarray,
                  t_ns: int) -> None:
        """Keep the sweep's image (where its rays passed) at its updated pose."""
        self._sweeps.append(_Sweep(int(t_ns), np.array(R_WL), np.array(p_WL), img.free))
        while len(self._sweeps) > 1 and self._sweeps[1].t_ns <= t_ns - self.lookback_ns:
            self._sweeps.popleft()

    def admit(self, points_world: np.ndarray, cell_m: float, t_ns: int) -> np.ndarray:
        """The points that may enter the map now; those near where a sweep saw through lately
        wait for their probation (:meth:`matured`)."""
        if not self._seen or not points_world.shape[0] or not self.near_m > 0.0:
            return points_world
        wait = near_any(points_world, np.concatenate([p for _, p in self._seen]), self.near_m)
        if wait.any():
            self._pending.append((int(t_ns), np.ascontiguousarray(points_world[wait]), cell_m))
        return points_world[~wait]

    def matured(self, t_ns: int) -> list[tuple[np.ndarray, float]]:
        """(points, cell edge) whose probation is over at ``t_ns``, no longer waiting."""
        out = []
        while self._pending and self._pending[0][0] <= t_ns - self.probation_ns:
            _, pts, cell = self._pending.popleft()
            out.append((pts, cell))
        return out

    def waiting(self) -> list[tuple[np.ndarray, float]]:
        """(points, cell edge) still on probation."""
        return [(pts, cell) for _, pts, cell in self._pending]

    def stored(self, points_world: np.ndarray, t_ns: int) -> None:
        """Points the map stored at ``t_ns``: seen through within the window, they leave it."""
        if points_world.shape[0]:
            self._recent.append((int(t_ns), np.ascontiguousarray(points_world)))
