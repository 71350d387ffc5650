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

World frame, metres. A voxel is held as one bit: the voxels come in blocks of 16 x 16 x 16
(0.8 m at 5 cm), each a 512-byte bitmap, the blocks in an open-addressing set keyed as the map
provenance keys its cells (:func:`adalio.lio.map_uncertainty._slot`). A sweep's points come in
ring order, so consecutive points mostly share a block and its bitmap sits in the cache: the
XT-32's 55k-point sweeps take 0.48 ms each, its 16k-point ones 0.24 ms (the 43 s hall, session
93; one hashed key per voxel took 0.47 ms for 16k points), and the map about 14 bytes a point
(1.6-3.9 thousand blocks for 0.4-1.2 million points).
Voxels beyond ±2^20 of the world's origin (±10 km at the smallest edge allowed, 1 cm) are left
out. The points are stored as float32, as the PLY and PCD files hold them (1 mm steps 16 km from
the origin).
"""

from __future__ import annotations

import numpy as np

from adalio.config import DENSE_MAP_MIN_VOXEL_M
from adalio.errors import ConfigError
from adalio.jit import kernel
from adalio.lio.map_uncertainty import _OFFSET, _insert, _slot

BLOCK_SHIFT = 4
"""A block is 2^4 = 16 voxels along each axis."""
_BLOCK_MASK = (1 << BLOCK_SHIFT) - 1
_BLOCK_WORDS = (1 << (3 * BLOCK_SHIFT)) // 64
"""int64 words of a block's bitmap (16^3 bits)."""
_MAX_VOXEL = float(_OFFSET)


@kernel()
def _add_points(points: np.ndarray, start: int, voxel_m: float, bkeys: np.ndarray,
                bindex: np.ndarray, bits: np.ndarray, store: np.ndarray,
                state: np.ndarray) -> int:
    """From row ``start`` on, store each finite row of ``points`` whose voxel's bit is not set
    yet at ``store[state[0]]`` and set it, ``state[0]`` counting the points stored and
    ``state[1]`` the blocks in use (``bits`` rows; the set ``bkeys`` / ``bindex`` maps a block's
    key to its row). Returns the row to go on from: ``len(points)`` when done, or the first row
    whose new block found ``bits`` or the set (at most half full) without room. ``store`` must
    have room for every row."""
    n = state[0]
    nb = state[1]
    last_key = np.int64(-1)
    row = np.int64(-1)
    for i in range(start, points.shape[0]):
        fx = points[i, 0] / voxel_m
        fy = points[i, 1] / voxel_m
        fz = points[i, 2] / voxel_m
        if not (abs(fx) < _MAX_VOXEL and abs(fy) < _MAX_VOXEL and abs(fz) < _MAX_VOXEL):
            continue  # non-finite, or beyond the keys' reach
        vx = np.int64(np.floor(fx))
        vy = np.int64(np.floor(fy))
        vz = np.int64(np.floor(fz))
        key = ((((vx >> BLOCK_SHIFT) + _OFFSET) << 42) | (((vy >> BLOCK_SHIFT) + _OFFSET) << 21)
               | ((vz >> BLOCK_SHIFT) + _OFFSET))
        if key != last_key:
            slot = _slot(bkeys, key)
            if bkeys[slot] < 0:
                if nb == bits.shape[0] or 2 * (nb + 1) > bkeys.shape[0]:
                    state[0] = n
                    state[1] = nb
                    return i
                bkeys[slot] = key
                bindex[slot] = nb
                nb += 1
            row = bindex[slot]
            last_key = key
        bit = ((vx & _BLOCK_MASK) << (2 * BLOCK_SHIFT)) | ((vy & _BLOCK_MASK) << BLOCK_SHIFT) \
            | (vz & _BLOCK_MASK)
        word = bit >> 6
        mask = np.int64(1) << (bit & 63)
        if bits[row, word] & mask:
            continue
        bits[row, word] |= mask
        store[n, 0] = points[i, 0]
        store[n, 1] = points[i, 1]
        store[n, 2] = points[i, 2]
        n += 1
    state[0] = n
    state[1] = nb
    return points.shape[0]


class DenseMap:
    """Every point offered, one per voxel of ``voxel_m`` (the first to reach it)."""

    def __init__(self, voxel_m: float) -> None:
        if not (np.isfinite(voxel_m) and voxel_m >= DENSE_MAP_MIN_VOXEL_M):
            raise ConfigError(f"output.dense_map_voxel_m must be at least "
                              f"{DENSE_MAP_MIN_VOXEL_M:g} m "
                              f"(or 0: no dense map), got {voxel_m!r}")
        self.voxel_m = float(voxel_m)
        self._bkeys = np.full(64, -1, np.int64)
        """The blocks' keys, an open-addressing set at most half full, and each one's row of
        ``_bits``."""
        self._bindex = np.full(64, -1, np.int64)
        self._bits = np.zeros((16, _BLOCK_WORDS), np.int64)
        self._points = np.empty((1024, 3), np.float32)
        self._state = np.zeros(2, np.int64)
        """[points stored, blocks in use]"""

    def __len__(self) -> int:
        return int(self._state[0])

    def add(self, points_world: np.ndarray) -> int:
        """Store each finite row of ``points_world`` (N, 3) whose voxel holds no point yet (of a
        batch's rows in one voxel, the first); returns how many were stored."""
        pts = np.ascontiguousarray(points_world, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"DenseMap.add: points_world must have shape (N, 3), got "
                             f"{np.shape(points_world)}")
        m, before = pts.shape[0], len(self)
        if before + m > self._points.shape[0]:
            grown = np.empty((max(2 * self._points.shape[0], before + m), 3), np.float32)
            grown[:before] = self._points[:before]
            self._points = grown
        start = 0
        while start < m:
            start = _add_points(pts, np.int64(start), self.voxel_m, self._bkeys, self._bindex,
                                self._bits, self._points, self._state)
            if start < m:  # a new block found no room: more rows, or a larger set
                self._make_room()
        return len(self) - before

    def _make_room(self) -> None:
        """Double the blocks' bitmaps where they are all in use, and the set where one more
        block would fill it past half."""
        nb = int(self._state[1])
        if nb == self._bits.shape[0]:
            bits = np.zeros((2 * nb, _BLOCK_WORDS), np.int64)
            bits[:nb] = self._bits
            self._bits = bits
        if 2 * (nb + 1) > self._bkeys.shape[0]:
            size = 2 * self._bkeys.shape[0]
            held = self._bkeys >= 0  # entered again, as the map provenance grows its table
            keys, index = np.full(size, -1, np.int64), np.full(size, -1, np.int64)
            _insert(keys, index, self._bkeys[held], self._bindex[held])
            self._bkeys, self._bindex = keys, index

    def points(self) -> np.ndarray:
        """The points stored (P, 3) float64, world frame, in the order they were stored."""
        return self._points[:len(self)].astype(np.float64)


__all__ = ["DenseMap"]
