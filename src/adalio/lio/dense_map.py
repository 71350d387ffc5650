"""The dense map (``output.dense_map_voxel_m``, ``adalio run --dense-map``): every still point of
every scan, laid down at its scan's updated pose, one point per voxel of that edge.

The filter's own map (``map.ply``) keeps one point per ``map.map_leaf_m`` cell (0.2 m, 0.1 m
in narrow places): what point-to-plane registration needs, but a sparse picture of a building
for a survey. FAST-LIO writes the cloud a surveyor looks at in the same way (``pcd_save``: each
undistorted sweep at its pose), as do LIO-SAM's and DLIO's map-saving services at a chosen
resolution. Here a voxel keeps the first point to reach it, as a cell of the filter's map does:
points of later sweeps that fall into a held voxel are not stored, so the memory grows with the
surface seen, not with the time spent.

The points are those the scan kept: in range, not dropped as stray returns, not on moving
things (``map.remove_moving``), at ``preprocess.point_filter_num``'s decimation. The cleaning
the filter's map gets later (points seen through by later sweeps, cells of stray returns left
out of ``map.ply``) reaches this map at the end of the run: :meth:`adalio.lio.Odometry.
dense_map_cloud` keeps a point only within one map cell edge of a point of the map written
out.

World frame, metres. The voxel keys are :func:`adalio.lio.map_uncertainty.cell_keys`' (21 bits
per axis: ±2^20 voxels from the world's origin, ±10 km at the smallest edge allowed, 1 cm), the
table its open addressing, so this map compiles no kernel of its own. The points are stored as
float32, as the PLY and PCD files hold them (1 mm steps 16 km from the origin).
"""

from __future__ import annotations

import numpy as np

from adalio.config import DENSE_MAP_MIN_VOXEL_M
from adalio.errors import ConfigError
from adalio.lio.map_uncertainty import _insert, _owners, cell_keys


class DenseMap:
    """Every point offered, one per voxel of ``voxel_m`` (the first to reach it)."""

    def __init__(self, voxel_m: float) -> None:
        if not (np.isfinite(voxel_m) and voxel_m >= DENSE_MAP_MIN_VOXEL_M):
            raise ConfigError(f"output.dense_map_voxel_m must be at least "
                              f"{DENSE_MAP_MIN_VOXEL_M:g} m "
                              f"(or 0: no dense map), got {voxel_m!r}")
        self.voxel_m = float(voxel_m)
        self._keys = np.full(1024, -1, np.int64)
        """Open-addressing table of the held voxels' keys (at most half full)."""
        self._owner = np.full(1024, -1, np.int64)
        """The offer (a running count of the points offered) that filled each voxel: only
        whether a row of a batch is the one that filled its voxel is read from it."""
        self._offered = 0
        self._points = np.empty((1024, 3), np.float32)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def add(self, points_world: np.ndarray) -> int:
        """Store each finite row of ``points_world`` (N, 3) whose voxel holds no point yet (of a
        batch's rows in one voxel, the first); returns how many were stored."""
        pts = np.ascontiguousarray(points_world, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"DenseMap.add: points_world must have shape (N, 3), got "
                             f"{np.shape(points_world)}")
        finite = np.isfinite(pts)
        finite = finite[:, 0] & finite[:, 1] & finite[:, 2]
        if not finite.all():
            pts = pts[finite]
        if not pts.shape[0]:
            return 0
        keys = cell_keys(pts, self.voxel_m)
        size = self._keys.shape[0]
        while 2 * (self._n + keys.shape[0]) > size:
            size *= 2
        if size != self._keys.shape[0]:  # a larger table, the voxels entered again
            held = self._keys >= 0
            old_keys, old_owner = self._keys[held], self._owner[held]
            self._keys, self._owner = np.full(size, -1, np.int64), np.full(size, -1, np.int64)
            _insert(self._keys, self._owner, old_keys, old_owner)
        offer = np.arange(self._offered, self._offered + keys.shape[0], dtype=np.int64)
        self._offered += keys.shape[0]
        new = _insert(self._keys, self._owner, keys, offer)
        if not new:
            return 0
        first = _owners(self._keys, self._owner, keys) == offer
        if self._n + new > self._points.shape[0]:
            grown = np.empty((max(2 * self._points.shape[0], self._n + new), 3), np.float32)
            grown[:self._n] = self._points[:self._n]
            self._points = grown
        self._points[self._n:self._n + new] = pts[first]
        self._n += new
        return int(new)

    def points(self) -> np.ndarray:
        """The points stored (P, 3) float64, world frame, in the order they were stored."""
        return self._points[:self._n].astype(np.float64)


__all__ = ["DenseMap"]
