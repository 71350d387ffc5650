"""iVox: the incremental voxel hash map of Faster-LIO (lio-design.md §7).

All points are in the world frame, in metres. A point p belongs to the voxel with integer key
round(p / resolution_m) (round half up, so voxel centres sit at key * resolution_m). Voxels live in
an open-addressing hash table held in numpy arrays; each voxel stores up to
``max_points_per_voxel`` points in fixed-size blocks taken from a shared pool.

Deviations from upstream, documented in lio-design.md §7:

* Per-voxel cap: once a voxel holds ``max_points_per_voxel`` points, a new point replaces the
  oldest one of that voxel (upstream lists grow without bound).
* Recency: every inserted point stamps its voxel with a global, strictly increasing sequence
  number (queries never refresh it). After each ``add_points`` call, if more than
  ``capacity_voxels`` voxels exist, the voxels with the oldest stamps are evicted in one batch
  until ``capacity_voxels - capacity_voxels // EVICT_SLACK_DIVISOR`` remain (upstream evicts one
  voxel per insertion and keeps exactly ``capacity``). The slack makes the O(voxels) compaction
  and rehash happen once per many scans instead of every scan once the map is full.
* kNN returns the exact k nearest of all points of the searched voxels with squared distance
  < max_range_m**2, sorted ascending (upstream only guarantees element 0 is the nearest).
* One point per cell (``cell_m > 0``, set to ``map.map_leaf_m`` by :meth:`IVox.from_config`): a
  point is inserted only if no stored point lies in its cell floor(p / cell_m), so earlier rows
  of the same batch count, and a point overwritten or evicted frees its cell. The stored points
  are counted per cell in a hash table, for every cell edge used so far (a scan may use a finer
  one), updated on insertion and overwrite and recounted after an eviction: one lookup per row
  instead of a scan of the voxels overlapping its cell. Upstream's rule (lio-design.md §7) lets
  a cell accumulate points creeping towards its centre; plane fits over such clusters have
  arbitrary normals and act as fake constraints (degenerate corridors "stick").
* Which point a cell keeps (``cell_point``, ``map.cell_point``): ``"first"`` (the default)
  keeps the first point to reach it. With it, a sensor descending past a wall fills each cell
  from its top, so the wall's map points form horizontal layers one cell apart (README, Session
  35). ``"uniform"`` keeps, of the points that reached the cell within ``sample_batches``
  insertions (``add_points`` calls: scans) of its first, the one of highest
  :func:`cell_priority` (a hash of its coordinates): a uniform sample of them (the reservoir
  rule), so the kept point's place in the cell owes nothing to the order of the sweeps; after
  those insertions the cell is fixed, as with ``"first"``. With ``sample_batches`` 0 it is never
  fixed: a later point replaces the kept one with probability 1/n once n points have reached
  the cell, and the map follows the poses of later scans. The replaced point is looked for among
  the points of the new point's own voxel; one stored in the neighbouring voxel (a cell across a
  voxel boundary) is kept, as with ``"first"``. The occupancy table stamps a cell with the
  insertion that first counted it and keeps the stamp while it keeps the cell, across recounts
  (a cell emptied by the per-voxel cap keeps its stamp; a recount drops emptied cells, and
  fixes the cells of a newly used cell edge).
* Returns per point (an addition, for the map written out): each stored point counts the rows
  that reached its cell, itself and the rows skipped there since (``would_store`` counts the rows
  it finds taken, ``add_points`` the rows its batch skips or samples), as the returns of that
  cell. A skipped row counts for the cell's last stored point, of whatever edge, so the rows of
  a coarse cell are all counted among its stored points when the edges nest (0.2 m and 0.1 m do):
  :meth:`IVox.points_with_returns` sums them per cell of ``map_leaf_m``. A point overwritten,
  removed or evicted takes its count with it. Queries never read it.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from adalio.config import MapConfig
from adalio.errors import ConfigError, InputError
from adalio.jit import kernel

BLOCK_POINTS = 8
"""Points per storage block of a voxel (memory granularity, not an algorithm constant)."""
_BLOCK_SHIFT = 3
_BOX_SLACK = 1e-6
NEARBY_TYPES = (0, 6, 18, 26)
EVICT_SLACK_DIVISOR = 16
"""A batch eviction frees capacity // EVICT_SLACK_DIVISOR extra voxels (amortises compaction)."""
PARALLEL_MIN_ROWS = 16384
"""Batches with fewer queries run single-threaded. On the shared 2-core dev machine the
numba-parallel kNN was never faster below ~16k queries (thread wake-up and scheduling cost
several ms); see benchmarks/bench_map_kernels.py."""

_MAX_ABS_KEY = 4.0e15
_PACK_HALF = 1 << 20
"""Cells within ±_PACK_HALF of the origin pack into one int64 (21 bits per axis)."""
_MIN_ROWS = 1024
_S_NV, _S_NP, _S_NBLOCKS, _S_NFREE, _S_SEQ = range(5)


def _as_int64(value: int) -> np.int64:
    return np.int64(value - (1 << 64) if value >= (1 << 63) else value)


_HASH_X = _as_int64(0x9E3779B97F4A7C15)
_HASH_Y = _as_int64(0xC2B2AE3D27D4EB4F)
_HASH_Z = _as_int64(0x165667B19E3779F9)


@kernel()
def hash_key3(kx: int, ky: int, kz: int, mask: int) -> int:
    """Slot of an integer voxel key in a power-of-two open-addressing table (§7 "Hash")."""
    h = kx * _HASH_X + ky * _HASH_Y + kz * _HASH_Z
    h ^= h >> 29
    h *= _HASH_Z
    h ^= h >> 32
    return h & mask


def nearby_offsets(nearby_type: int) -> np.ndarray:
    """Integer voxel offsets searched around the query voxel (§7 "Neighbourhoods").

    Order: centre, 6 faces, 12 edges, 8 corners; NEARBY0/6/18/26 take the first 1/7/19/27 rows.
    """
    if nearby_type not in NEARBY_TYPES:
        raise ConfigError(f"map.nearby_type must be one of 0, 6, 18, 26, got {nearby_type!r}")
    offs = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)]
    offs.sort(key=lambda o: (abs(o[0]) + abs(o[1]) + abs(o[2]), o))
    n = {0: 1, 6: 7, 18: 19, 26: 27}[nearby_type]
    return np.ascontiguousarray(np.array(offs[:n], dtype=np.int64))


@kernel()
def _key_of(x: float, y: float, z: float, resolution_m: float):
    """(ok, kx, ky, kz) = floor(p / s + 1/2), i.e. round(p / s) half up (§7 "Key")."""
    fx = np.floor(x / resolution_m + 0.5)
    fy = np.floor(y / resolution_m + 0.5)
    fz = np.floor(z / resolution_m + 0.5)
    ok = abs(fx) < _MAX_ABS_KEY and abs(fy) < _MAX_ABS_KEY and abs(fz) < _MAX_ABS_KEY
    if not ok:
        return False, 0, 0, 0
    return True, np.int64(fx), np.int64(fy), np.int64(fz)


@kernel()
def _lookup(table: np.ndarray, vkeys: np.ndarray, kx: int, ky: int, kz: int) -> int:
    """Voxel id of a key by linear probing, or -1 if absent."""
    mask = table.shape[0] - 1
    h = hash_key3(kx, ky, kz, mask)
    while True:
        v = table[h]
        if v < 0:
            return -1
        if vkeys[v, 0] == kx and vkeys[v, 1] == ky and vkeys[v, 2] == kz:
            return v
        h = (h + 1) & mask


@kernel()
def _rebuild_table(table: np.ndarray, vkeys: np.ndarray, nv: int) -> None:
    table[:] = -1
    mask = table.shape[0] - 1
    for v in range(nv):
        h = hash_key3(vkeys[v, 0], vkeys[v, 1], vkeys[v, 2], mask)
        while table[h] >= 0:
            h = (h + 1) & mask
        table[h] = v


@kernel()
def _occ_slot(okeys: np.ndarray, si: int, kx: int, ky: int, kz: int, insert: bool) -> int:
    """Slot of cell (kx, ky, kz) of edge number ``si`` in the occupancy table (linear probing;
    an empty slot has ``okeys[slot, 0] == -1``); -1 when absent and not ``insert``."""
    mask = okeys.shape[0] - 1
    h = hash_key3(kx, ky, kz + si * _HASH_Y, mask)
    while True:
        if okeys[h, 0] < 0:
            if not insert:
                return -1
            okeys[h, 0] = si
            okeys[h, 1] = kx
            okeys[h, 2] = ky
            okeys[h, 3] = kz
            return h
        if okeys[h, 0] == si and okeys[h, 1] == kx and okeys[h, 2] == ky and okeys[h, 3] == kz:
            return h
        h = (h + 1) & mask


@kernel()
def _cell_of(x: float, y: float, z: float, cell_m: float):
    """(ok, cx, cy, cz): the cell floor(p / cell_m) of p; not ok beyond ±_MAX_ABS_KEY cells."""
    cx = np.floor(x / cell_m)
    cy = np.floor(y / cell_m)
    cz = np.floor(z / cell_m)
    if not (abs(cx) < _MAX_ABS_KEY and abs(cy) < _MAX_ABS_KEY and abs(cz) < _MAX_ABS_KEY):
        return False, 0, 0, 0
    return True, np.int64(cx), np.int64(cy), np.int64(cz)


@kernel()
def _occ_add(okeys: np.ndarray, ocount: np.ndarray, ostate: np.ndarray, cell_sizes: np.ndarray,
             x: float, y: float, z: float, delta: int, v: int, j: int) -> None:
    """Count a stored point in (``delta`` = 1) or out of (-1) its cell of every tracked edge; a
    point counted in is recorded as its cells' last (voxel ``v``, slot ``j``), columns 4-5, and a
    cell's first point stamps it with the insertion number ``ostate[1]``, column 6."""
    for si in range(cell_sizes.shape[0]):
        ok, cx, cy, cz = _cell_of(x, y, z, cell_sizes[si])
        if not ok:
            continue
        h = _occ_slot(okeys, si, cx, cy, cz, delta > 0)
        if h < 0:
            continue
        if ocount[h] < 0:
            ocount[h] = 0
            ostate[0] += 1
            okeys[h, 6] = ostate[1]
        ocount[h] += delta
        if delta > 0:
            okeys[h, 4] = v
            okeys[h, 5] = j


@kernel()
def _occ_rebuild(okeys: np.ndarray, ocount: np.ndarray, ostate: np.ndarray,
                 cell_sizes: np.ndarray, nv: int, cap: int, vtotal: np.ndarray,
                 vblocks: np.ndarray, pool: np.ndarray) -> None:
    """The occupancy table counted afresh from every stored point (``ostate[0]``: cells)."""
    for h in range(okeys.shape[0]):
        okeys[h, 0] = -1
        ocount[h] = -1
    ostate[0] = 0
    for v in range(nv):
        for j in range(min(vtotal[v], cap)):
            b = vblocks[v, j >> _BLOCK_SHIFT]
            s = j & (BLOCK_POINTS - 1)
            _occ_add(okeys, ocount, ostate, cell_sizes, pool[b, s, 0], pool[b, s, 1],
                     pool[b, s, 2], np.int64(1), v, j)
    for h in range(okeys.shape[0]):  # until _copy_stamps restores a counted cell's stamp
        okeys[h, 6] = _FIXED


@kernel()
def _count_return(h: int, okeys: np.ndarray, nv: int, cap: int, vblocks: np.ndarray,
                  returns: np.ndarray) -> None:
    """A row that reached the occupied cell in occupancy slot ``h`` counts as a return of the
    cell's last stored point (``okeys[h, 4:6]``, recorded when it was stored and recounted
    after an eviction). Where that point has left since (removed, or overwritten by the voxel's
    cap) while another stays in the cell, the row counts for the slot: lost if it is empty (not
    gathered; a point stored there starts at 1), for its new point otherwise."""
    v = okeys[h, 4]
    j = okeys[h, 5]
    if 0 <= v < nv and 0 <= j < cap:
        returns[vblocks[v, j >> _BLOCK_SHIFT], j & (BLOCK_POINTS - 1)] += 1


@kernel()
def _copy_stamps(old_keys: np.ndarray, old_count: np.ndarray, okeys: np.ndarray) -> None:
    """Each cell of the old occupancy table still counted in the new one keeps its stamp."""
    for h in range(old_keys.shape[0]):
        if old_count[h] < 0 or old_keys[h, 0] < 0:
            continue
        h2 = _occ_slot(okeys, old_keys[h, 0], old_keys[h, 1], old_keys[h, 2], old_keys[h, 3],
                       False)
        if h2 >= 0:
            okeys[h2, 6] = old_keys[h, 6]


CELL_POINTS = ("first", "uniform")
"""Which point a map cell keeps (module docstring)."""
_PRIORITY_SCALE = 1.0e5
"""Coordinates are hashed at 10 µm (points closer than that share a priority)."""
_PRIORITY_MASK = (1 << 52) - 1
_FIXED = -(1 << 60)
"""Insertion stamp of a cell whose sampling window is over."""


@kernel()
def _priority(x: float, y: float, z: float) -> int:
    return hash_key3(np.int64(np.floor(x * _PRIORITY_SCALE)),
                     np.int64(np.floor(y * _PRIORITY_SCALE)),
                     np.int64(np.floor(z * _PRIORITY_SCALE)), np.int64(_PRIORITY_MASK))


@kernel()
def _priorities(points: np.ndarray) -> np.ndarray:
    out = np.empty(points.shape[0], np.int64)
    for i in range(points.shape[0]):
        out[i] = _priority(points[i, 0], points[i, 1], points[i, 2])
    return out


def cell_priority(points_world: np.ndarray) -> np.ndarray:
    """(N,) int64 pseudo-random priority of world points (a hash of their coordinates at 10 µm):
    with ``cell_point="uniform"`` a cell keeps the highest of the points that reached it."""
    return _priorities(_as_points(points_world, "points_world"))


@kernel()
def _in_cell(pool: np.ndarray, vblocks: np.ndarray, v: int, j: int, cx: int, cy: int, cz: int,
             cell_m: float) -> bool:
    b = vblocks[v, j >> _BLOCK_SHIFT]
    s = j & (BLOCK_POINTS - 1)
    ok, qx, qy, qz = _cell_of(pool[b, s, 0], pool[b, s, 1], pool[b, s, 2], cell_m)
    return ok and qx == cx and qy == cy and qz == cz


@kernel()
def _keep_uniform(x: float, y: float, z: float, cx: int, cy: int, cz: int, cell_m: float, h: int,
                  v: int, nv: int, cap: int, vstamp: np.ndarray, vtotal: np.ndarray,
                  vblocks: np.ndarray, pool: np.ndarray, cell_sizes: np.ndarray,
                  okeys: np.ndarray, ocount: np.ndarray, ostate: np.ndarray, seq: int) -> int:
    """Cell (cx, cy, cz) (occupancy slot ``h``) is occupied: the point (x, y, z) takes the slot
    of the lowest-priority point of that cell stored in voxel ``v`` if its priority is higher.
    A cell holding one point whose recorded slot still holds a point of the cell is decided
    from that slot alone; otherwise voxel ``v`` is scanned. Returns the next sequence number."""
    best = -1
    best_prio = _PRIORITY_MASK + 1
    lv = okeys[h, 4]
    lj = okeys[h, 5]
    if (ocount[h] == 1 and 0 <= lv < nv and 0 <= lj < min(vtotal[lv], cap)
            and _in_cell(pool, vblocks, lv, lj, cx, cy, cz, cell_m)):
        if lv == v:  # the cell's one point; in another voxel it is kept
            b = vblocks[v, lj >> _BLOCK_SHIFT]
            s = lj & (BLOCK_POINTS - 1)
            best = lj
            best_prio = _priority(pool[b, s, 0], pool[b, s, 1], pool[b, s, 2])
    else:
        for j in range(min(vtotal[v], cap)):
            if not _in_cell(pool, vblocks, v, j, cx, cy, cz, cell_m):
                continue
            b = vblocks[v, j >> _BLOCK_SHIFT]
            s = j & (BLOCK_POINTS - 1)
            prio = _priority(pool[b, s, 0], pool[b, s, 1], pool[b, s, 2])
            if prio < best_prio:
                best_prio = prio
                best = j
    if best < 0 or _priority(x, y, z) <= best_prio:
        return seq
    b = vblocks[v, best >> _BLOCK_SHIFT]
    s = best & (BLOCK_POINTS - 1)
    _occ_add(okeys, ocount, ostate, cell_sizes, pool[b, s, 0], pool[b, s, 1], pool[b, s, 2],
             np.int64(-1), v, best)
    _occ_add(okeys, ocount, ostate, cell_sizes, x, y, z, np.int64(1), v, best)
    pool[b, s, 0] = x
    pool[b, s, 1] = y
    pool[b, s, 2] = z
    vstamp[v] = seq
    return seq + 1


@kernel()
def _insert_points(
    points: np.ndarray,
    start: int,
    resolution_m: float,
    cap: int,
    cell_m: float,
    table: np.ndarray,
    vkeys: np.ndarray,
    vstamp: np.ndarray,
    vtotal: np.ndarray,
    vblocks: np.ndarray,
    pool: np.ndarray,
    free_blocks: np.ndarray,
    state: np.ndarray,
    cell_index: int,
    cell_sizes: np.ndarray,
    okeys: np.ndarray,
    ocount: np.ndarray,
    ostate: np.ndarray,
    uniform: bool,
    sample_batches: int,
    stored: np.ndarray,
    returns: np.ndarray,
) -> int:
    """Sequential, deterministic insertion of world points into their round(p/s) voxels (§7).

    Processes rows from ``start`` on; a voxel holding ``cap`` points overwrites its oldest point
    (ring order). With ``cell_m > 0`` a row whose cell floor(p / cell_m) already holds a stored
    point is skipped, or with ``uniform`` may take that point's slot (:func:`_keep_uniform`)
    while the insertion ``ostate[1]`` is within ``sample_batches`` of the cell's first (0: ever):
    ``cell_sizes[cell_index] == cell_m``, and the occupancy table (``okeys``,
    ``ocount``, ``ostate``) counts the stored points per cell of every edge in ``cell_sizes``; it
    must have room for ``len(cell_sizes)`` new cells per row. Stops before a row that might need
    a voxel, table slot or block the arrays do not have, and returns that row (``len(points)``
    when done) so the caller can grow them. ``state`` = [nv, n_points, n_blocks, n_free, seq]
    is updated in place. ``stored[row]`` is set for each row stored (a new point, or one that
    took a point's slot in its cell). ``returns`` (blocks, BLOCK_POINTS) counts each stored
    point's returns: 1 when stored, +1 for each later row skipped or sampled in its cell (a row
    that takes a point's slot keeps that slot's count).
    """
    mask = table.shape[0] - 1
    nv = state[_S_NV]
    n_points = state[_S_NP]
    n_blocks = state[_S_NBLOCKS]
    n_free = state[_S_NFREE]
    seq = state[_S_SEQ]
    i = start
    while i < points.shape[0]:
        if nv >= vkeys.shape[0] or 2 * (nv + 1) > table.shape[0]:
            break
        if n_free == 0 and n_blocks >= pool.shape[0]:
            break
        row = i
        i += 1
        ok, kx, ky, kz = _key_of(points[row, 0], points[row, 1], points[row, 2], resolution_m)
        if not ok:
            continue
        if cell_m > 0.0:
            ok, cx, cy, cz = _cell_of(points[row, 0], points[row, 1], points[row, 2], cell_m)
            if ok:
                h = _occ_slot(okeys, cell_index, cx, cy, cz, np.bool_(False))
                if h >= 0 and ocount[h] > 0:
                    _count_return(h, okeys, nv, cap, vblocks, returns)
                    if uniform and (sample_batches <= 0
                                    or ostate[1] - okeys[h, 6] < sample_batches):
                        v = _lookup(table, vkeys, kx, ky, kz)
                        if v >= 0:
                            before = seq
                            seq = _keep_uniform(points[row, 0], points[row, 1], points[row, 2],
                                                cx, cy, cz, cell_m, h, v, nv, cap, vstamp,
                                                vtotal, vblocks, pool, cell_sizes, okeys,
                                                ocount, ostate, seq)
                            stored[row] = seq > before
                    continue
        h = hash_key3(kx, ky, kz, mask)
        while True:
            v = table[h]
            if v < 0:
                v = nv
                table[h] = v
                vkeys[v, 0] = kx
                vkeys[v, 1] = ky
                vkeys[v, 2] = kz
                vtotal[v] = 0
                nv += 1
                break
            if vkeys[v, 0] == kx and vkeys[v, 1] == ky and vkeys[v, 2] == kz:
                break
            h = (h + 1) & mask
        t = vtotal[v]
        if t < cap:
            slot = t
            if slot % BLOCK_POINTS == 0:
                if n_free > 0:
                    n_free -= 1
                    b = free_blocks[n_free]
                else:
                    b = n_blocks
                    n_blocks += 1
                vblocks[v, slot >> _BLOCK_SHIFT] = b
            n_points += 1
        else:
            slot = t % cap
        b = vblocks[v, slot >> _BLOCK_SHIFT]
        j = slot & (BLOCK_POINTS - 1)
        if t >= cap:  # the oldest point of the voxel leaves its cells
            _occ_add(okeys, ocount, ostate, cell_sizes, pool[b, j, 0], pool[b, j, 1],
                     pool[b, j, 2], np.int64(-1), v, slot)
        _occ_add(okeys, ocount, ostate, cell_sizes, points[row, 0], points[row, 1],
                 points[row, 2], np.int64(1), v, slot)
        pool[b, j, 0] = points[row, 0]
        pool[b, j, 1] = points[row, 1]
        pool[b, j, 2] = points[row, 2]
        returns[b, j] = 1
        vtotal[v] = t + 1
        vstamp[v] = seq
        seq += 1
        stored[row] = True
    state[_S_NV] = nv
    state[_S_NP] = n_points
    state[_S_NBLOCKS] = n_blocks
    state[_S_NFREE] = n_free
    state[_S_SEQ] = seq
    return i


@kernel()
def _evict(
    evict: np.ndarray,
    cap: int,
    table: np.ndarray,
    vkeys: np.ndarray,
    vstamp: np.ndarray,
    vtotal: np.ndarray,
    vblocks: np.ndarray,
    free_blocks: np.ndarray,
    state: np.ndarray,
) -> None:
    """Drop the voxels flagged in ``evict`` (§7 LRU), compact the survivors in id order, rehash."""
    nv = state[_S_NV]
    n_free = state[_S_NFREE]
    n_points = state[_S_NP]
    w = 0
    for v in range(nv):
        count = min(vtotal[v], cap)
        if evict[v]:
            for blk in range((count + BLOCK_POINTS - 1) // BLOCK_POINTS):
                free_blocks[n_free] = vblocks[v, blk]
                n_free += 1
            n_points -= count
            continue
        if w != v:
            for c in range(vkeys.shape[1]):
                vkeys[w, c] = vkeys[v, c]
            vstamp[w] = vstamp[v]
            vtotal[w] = vtotal[v]
            for c in range(vblocks.shape[1]):
                vblocks[w, c] = vblocks[v, c]
        w += 1
    state[_S_NV] = w
    state[_S_NFREE] = n_free
    state[_S_NP] = n_points
    _rebuild_table(table, vkeys, w)


@kernel()
def _knn_row(
    qi: int,
    queries: np.ndarray,
    k: int,
    max_d2: float,
    resolution_m: float,
    offsets: np.ndarray,
    cap: int,
    store: tuple,
    out_nbrs: np.ndarray,
    out_d2: np.ndarray,
) -> int:
    """k nearest map points of query ``qi`` among its neighbourhood voxels (§7 "kNN").

    Candidates are the points of the query voxel round(q/s) and its ``offsets`` neighbours with
    squared distance < max_d2; the output row is kept sorted ascending by insertion (ties keep the
    first candidate in offset/slot order). A neighbour voxel whose (slightly inflated) box is no
    closer than the current bound is skipped, which cannot change the result. ``out_nbrs[qi]``
    must be NaN-filled and ``out_d2[qi]`` inf-filled. ``store`` = (table, vkeys, vtotal, vblocks,
    pool) of the map. Returns the number of neighbours found.
    """
    table, vkeys, vtotal, vblocks, pool = store
    half = 0.5 * resolution_m * (1.0 + _BOX_SLACK)
    qx = queries[qi, 0]
    qy = queries[qi, 1]
    qz = queries[qi, 2]
    ok, kx, ky, kz = _key_of(qx, qy, qz, resolution_m)
    if not ok:
        return 0
    cnt = 0
    bound = max_d2
    for o in range(offsets.shape[0]):
        vx = kx + offsets[o, 0]
        vy = ky + offsets[o, 1]
        vz = kz + offsets[o, 2]
        bx = max(abs(qx - vx * resolution_m) - half, 0.0)
        by = max(abs(qy - vy * resolution_m) - half, 0.0)
        bz = max(abs(qz - vz * resolution_m) - half, 0.0)
        if not bx * bx + by * by + bz * bz < bound:
            continue
        v = _lookup(table, vkeys, vx, vy, vz)
        if v < 0:
            continue
        for j in range(min(vtotal[v], cap)):
            b = vblocks[v, j >> _BLOCK_SHIFT]
            s = j & (BLOCK_POINTS - 1)
            px = pool[b, s, 0]
            py = pool[b, s, 1]
            pz = pool[b, s, 2]
            d2 = (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2
            if not d2 < bound:
                continue
            pos = cnt if cnt < k else k - 1
            while pos > 0 and d2 < out_d2[qi, pos - 1]:
                out_d2[qi, pos] = out_d2[qi, pos - 1]
                out_nbrs[qi, pos, 0] = out_nbrs[qi, pos - 1, 0]
                out_nbrs[qi, pos, 1] = out_nbrs[qi, pos - 1, 1]
                out_nbrs[qi, pos, 2] = out_nbrs[qi, pos - 1, 2]
                pos -= 1
            out_d2[qi, pos] = d2
            out_nbrs[qi, pos, 0] = px
            out_nbrs[qi, pos, 1] = py
            out_nbrs[qi, pos, 2] = pz
            if cnt < k:
                cnt += 1
            if cnt == k:
                bound = out_d2[qi, k - 1]
    return cnt


@kernel()
def _knn_serial(
    queries, k, max_d2, resolution_m, offsets, cap, store, out_nbrs, out_d2, out_counts
):
    """kNN of every query row (§7), one thread."""
    for qi in range(queries.shape[0]):
        out_counts[qi] = _knn_row(
            qi, queries, k, max_d2, resolution_m, offsets, cap, store, out_nbrs, out_d2
        )


@kernel(parallel=True)
def _knn_parallel(
    queries, k, max_d2, resolution_m, offsets, cap, store, out_nbrs, out_d2, out_counts
):
    """kNN of every query row (§7); rows are independent, so the result is deterministic."""
    for qi in prange(queries.shape[0]):
        out_counts[qi] = _knn_row(
            qi, queries, k, max_d2, resolution_m, offsets, cap, store, out_nbrs, out_d2
        )


@kernel()
def _gather_points(
    nv: int, n_points: int, cap: int, vtotal: np.ndarray, vblocks: np.ndarray, pool: np.ndarray,
    returns: np.ndarray,
):
    """(stored points (P,3), their returns (P,)) in voxel order."""
    out = np.empty((n_points, 3), np.float64)
    counts = np.empty(n_points, np.int64)
    w = 0
    for v in range(nv):
        for j in range(min(vtotal[v], cap)):
            blk, slot = vblocks[v, j >> _BLOCK_SHIFT], j & (BLOCK_POINTS - 1)
            if np.isnan(pool[blk, slot, 0]):  # removed (remove_points)
                continue
            for c in range(3):
                out[w, c] = pool[blk, slot, c]
            counts[w] = returns[blk, slot]
            w += 1
    return out[:w], counts[:w]


@kernel()
def _cells_taken(points: np.ndarray, cell_m: float, cell_index: int, okeys: np.ndarray,
                 ocount: np.ndarray, nv: int, cap: int, vblocks: np.ndarray,
                 returns: np.ndarray) -> np.ndarray:
    """(N,) bool: the cell floor(p / cell_m) of each point holds a stored point; each such row
    counts as a return of the cell (:func:`_count_return`)."""
    out = np.zeros(points.shape[0], np.bool_)
    for i in range(points.shape[0]):
        ok, cx, cy, cz = _cell_of(points[i, 0], points[i, 1], points[i, 2], cell_m)
        if ok:
            h = _occ_slot(okeys, cell_index, cx, cy, cz, np.bool_(False))
            out[i] = h >= 0 and ocount[h] > 0
            if out[i]:
                _count_return(h, okeys, nv, cap, vblocks, returns)
    return out


@kernel()
def _remove_points(points: np.ndarray, resolution_m: float, cap: int, table: np.ndarray,
                   vkeys: np.ndarray, vtotal: np.ndarray, vblocks: np.ndarray, pool: np.ndarray,
                   cell_sizes: np.ndarray, okeys: np.ndarray, ocount: np.ndarray,
                   ostate: np.ndarray, removed: np.ndarray) -> int:
    """Remove each stored point equal to a row of ``points``: its slot is left NaN (skipped by
    kNN, the occupancy recount and ``points()``, and reused by the voxel's ring overwrite) and
    its cells are counted out, so a later point may fill them. ``removed[i]``: row i was
    found. Returns how many were."""
    n = 0
    for i in range(points.shape[0]):
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        ok, kx, ky, kz = _key_of(x, y, z, resolution_m)
        if not ok:
            continue
        v = _lookup(table, vkeys, kx, ky, kz)
        if v < 0:
            continue
        for j in range(min(vtotal[v], cap)):
            b = vblocks[v, j >> _BLOCK_SHIFT]
            s = j & (BLOCK_POINTS - 1)
            if pool[b, s, 0] == x and pool[b, s, 1] == y and pool[b, s, 2] == z:
                _occ_add(okeys, ocount, ostate, cell_sizes, x, y, z, np.int64(-1), v, j)
                pool[b, s, 0] = np.nan
                pool[b, s, 1] = np.nan
                pool[b, s, 2] = np.nan
                removed[i] = True
                n += 1
                break
    return n


def _grow(arr: np.ndarray, n_rows: int) -> np.ndarray:
    if arr.shape[0] >= n_rows:
        return arr
    out = np.empty((n_rows,) + arr.shape[1:], arr.dtype)
    out[: arr.shape[0]] = arr
    return out


class IVox:
    """Incremental voxel map with approximate kNN over a voxel neighbourhood (lio-design.md §7).

    ``IVox(resolution_m, nearby_type, capacity_voxels, max_points_per_voxel, cell_m=0.0,
    cell_point="first", sample_batches=5)``; points in world frame, metres. ``cell_m > 0`` keeps
    at most one point per cell of that edge, chosen by ``cell_point`` and ``sample_batches``.
    See the module docstring for the deviations from upstream.
    """

    def __init__(
        self,
        resolution_m: float = 0.5,
        nearby_type: int = 18,
        capacity_voxels: int = 1_000_000,
        max_points_per_voxel: int = 64,
        cell_m: float = 0.0,
        cell_point: str = "first",
        sample_batches: int = 5,
    ) -> None:
        if not (np.isfinite(resolution_m) and resolution_m > 0.0):
            raise ConfigError(
                f"map.ivox_resolution_m must be a positive number of metres, got {resolution_m!r}"
            )
        if int(capacity_voxels) < 1:
            raise ConfigError(f"map.capacity_voxels must be >= 1, got {capacity_voxels!r}")
        if int(max_points_per_voxel) < 1:
            raise ConfigError(
                f"map.max_points_per_voxel must be >= 1, got {max_points_per_voxel!r}"
            )
        if not (np.isfinite(cell_m) and cell_m >= 0.0):
            raise ConfigError(f"map.map_leaf_m must be a positive number of metres, got {cell_m!r}")
        self.resolution_m = float(resolution_m)
        if cell_point not in CELL_POINTS:
            raise ConfigError(f"map.cell_point must be one of {', '.join(CELL_POINTS)}, got "
                              f"{cell_point!r}")
        if int(sample_batches) < 0:
            raise ConfigError(f"map.cell_sample_scans must be >= 0, got {sample_batches!r}")
        self.cell_m = float(cell_m)
        self.cell_point = cell_point
        self.sample_batches = int(sample_batches)
        self.nearby_type = int(nearby_type)
        self.capacity_voxels = int(capacity_voxels)
        self.max_points_per_voxel = int(max_points_per_voxel)
        self._offsets = nearby_offsets(self.nearby_type)
        blocks_per_voxel = -(-self.max_points_per_voxel // BLOCK_POINTS)
        self._table = np.full(16, -1, np.int64)
        self._vkeys = np.empty((0, 3), np.int64)
        self._vstamp = np.empty(0, np.int64)
        self._vtotal = np.empty(0, np.int64)
        self._vblocks = np.empty((0, blocks_per_voxel), np.int64)
        self._pool = np.empty((0, BLOCK_POINTS, 3), np.float64)
        self._returns = np.empty((0, BLOCK_POINTS), np.int32)
        """Each pool slot's returns (module docstring, *Returns per point*)."""
        self._free = np.empty(0, np.int64)
        self._state = np.zeros(5, np.int64)
        # one-point-per-cell: stored points counted per cell of every cell edge used so far
        self._cell_sizes = np.empty(0, np.float64)
        self._okeys = np.full((16, 7), -1, np.int64)
        self._ocount = np.full(16, -1, np.int64)
        self._ostate = np.zeros(2, np.int64)
        """[cells counted, insertions so far]"""

    @classmethod
    def from_config(cls, cfg: MapConfig) -> IVox:
        """Map built from the ``map`` config section (one point per ``map_leaf_m`` cell)."""
        return cls(
            cfg.ivox_resolution_m,
            cfg.nearby_type,
            cfg.capacity_voxels,
            cfg.max_points_per_voxel,
            cell_m=cfg.map_leaf_m,
            cell_point=cfg.cell_point,
            sample_batches=cfg.cell_sample_scans,
        )

    @property
    def num_voxels(self) -> int:
        return int(self._state[_S_NV])

    @property
    def num_points(self) -> int:
        """Slots in use: the stored points and the slots of removed ones not yet reused."""
        return int(self._state[_S_NP])

    def add_points(self, points_world: np.ndarray, cell_m: float | None = None) -> np.ndarray:
        """Insert (N,3) world points in row order; non-finite rows are skipped, and with
        ``cell_m > 0`` so is a row whose cell already holds a point (§7, module docstring).
        Returns (N,) bool: the rows stored.

        ``cell_m`` overrides the map's cell edge for this batch (None: ``self.cell_m``).
        """
        cell = self.cell_m if cell_m is None else float(cell_m)
        if not (np.isfinite(cell) and cell >= 0.0):
            raise InputError(f"add_points cell_m must be >= 0 metres, got {cell_m!r}")
        pts = _as_points(points_world, "points_world")
        n = pts.shape[0]
        stored = np.zeros(n, np.bool_)
        if n == 0:
            return stored
        self._ostate[1] += 1
        if cell > 0.0 and cell not in self._cell_sizes:
            self._cell_sizes = np.append(self._cell_sizes, cell)
            self._rebuild_occupancy(n)
        cell_index = int(np.flatnonzero(self._cell_sizes == cell)[0]) if cell > 0.0 else -1
        if self._cell_sizes.size and 2 * (self._ostate[0] + self._cell_sizes.size * n) > \
                self._okeys.shape[0]:
            self._rebuild_occupancy(n)
        start = 0
        while start < n:
            self._make_room()
            start = _insert_points(
                pts,
                start,
                self.resolution_m,
                self.max_points_per_voxel,
                cell,
                self._table,
                self._vkeys,
                self._vstamp,
                self._vtotal,
                self._vblocks,
                self._pool,
                self._free,
                self._state,
                cell_index,
                self._cell_sizes,
                self._okeys,
                self._ocount,
                self._ostate,
                self.cell_point == "uniform",
                self.sample_batches,
                stored,
                self._returns,
            )
        nv = self.num_voxels
        if nv > self.capacity_voxels:
            keep = self.capacity_voxels - self.capacity_voxels // EVICT_SLACK_DIVISOR
            n_evict = nv - keep
            oldest = np.argpartition(self._vstamp[:nv], n_evict - 1)[:n_evict]
            evict = np.zeros(nv, np.bool_)
            evict[oldest] = True
            _evict(
                evict,
                self.max_points_per_voxel,
                self._table,
                self._vkeys,
                self._vstamp,
                self._vtotal,
                self._vblocks,
                self._free,
                self._state,
            )
            if self._cell_sizes.size:
                self._rebuild_occupancy(0)
        return stored

    def _rebuild_occupancy(self, n_new: int) -> None:
        """Count the stored points per cell afresh, in a table at most half full once ``n_new``
        more points are in (each adds at most one cell per tracked edge)."""
        need = 2 * self._cell_sizes.size * (self.num_points + n_new)
        size = max(16, 1 << int(need - 1).bit_length())
        # the cells' sampling stamps matter only while a 'uniform' cell can still be replaced
        stamps = self.cell_point == "uniform" and self.sample_batches > 0
        if stamps:
            old_keys, old_count = self._okeys.copy(), self._ocount.copy()
        if size != self._okeys.shape[0]:
            self._okeys = np.empty((size, 7), np.int64)
            self._ocount = np.empty(size, np.int64)
        _occ_rebuild(self._okeys, self._ocount, self._ostate, self._cell_sizes, self.num_voxels,
                     self.max_points_per_voxel, self._vtotal, self._vblocks, self._pool)
        if stamps:
            _copy_stamps(old_keys, old_count, self._okeys)

    def _make_room(self) -> None:
        """Double whichever store is full (voxel rows, hash table at load 1/2, block pool)."""
        nv = self.num_voxels
        if nv >= self._vkeys.shape[0]:
            rows = max(_MIN_ROWS, 2 * self._vkeys.shape[0])
            self._vkeys = _grow(self._vkeys, rows)
            self._vstamp = _grow(self._vstamp, rows)
            self._vtotal = _grow(self._vtotal, rows)
            self._vblocks = _grow(self._vblocks, rows)
        if 2 * (nv + 1) > self._table.shape[0]:
            self._table = np.full(2 * self._table.shape[0], -1, np.int64)
            _rebuild_table(self._table, self._vkeys, nv)
        if self._state[_S_NFREE] == 0 and self._state[_S_NBLOCKS] >= self._pool.shape[0]:
            rows = max(_MIN_ROWS, 2 * self._pool.shape[0])
            self._pool = _grow(self._pool, rows)
            self._returns = _grow(self._returns, rows)
            self._free = _grow(self._free, rows)

    def knn(
        self, queries: np.ndarray, k: int, max_range_m: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """k nearest map points of each query within its neighbourhood voxels (§7, §9.4).

        Returns ``(nbrs (M,k,3), counts (M,) int64, dist2 (M,k))``: rows sorted by ascending
        squared distance, only points with dist2 < max_range_m**2, unused slots NaN / inf.
        Batches of at least ``PARALLEL_MIN_ROWS`` queries run on all numba threads.

        ``max_range_m`` gates every candidate (upstream ``GetClosestPoint(max_range=5.0)``). With
        NEARBY18 no candidate lies farther than about 3 * resolution_m from the query, so a larger
        range is inert; to apply AdaLIO's search radius, gate on ``dist2[:, k-1]`` (farthest of the
        k neighbours) as §9.4 recommends, or pass the radius here to drop far candidates.
        """
        q = _as_points(queries, "queries")
        k = int(k)
        if k < 1:
            raise InputError(f"knn k must be >= 1, got {k}")
        if not max_range_m > 0.0:
            raise InputError(f"knn max_range_m must be > 0 metres, got {max_range_m!r}")
        m = q.shape[0]
        nbrs = np.full((m, k, 3), np.nan)
        dist2 = np.full((m, k), np.inf)
        counts = np.zeros(m, np.int64)
        if m == 0 or self.num_voxels == 0:
            return nbrs, counts, dist2
        kernel = _knn_parallel if m >= PARALLEL_MIN_ROWS else _knn_serial
        kernel(
            q,
            k,
            float(max_range_m) ** 2,
            self.resolution_m,
            self._offsets,
            self.max_points_per_voxel,
            (self._table, self._vkeys, self._vtotal, self._vblocks, self._pool),
            nbrs,
            dist2,
            counts,
        )
        return nbrs, counts, dist2

    def would_store(self, points_world: np.ndarray, cell_m: float | None = None) -> np.ndarray:
        """(N,) bool: rows :meth:`add_points` might store now, by their cells alone: with
        ``cell_point`` "first", a row whose cell holds a point never is. Such a row is counted
        as a return of its cell (module docstring, *Returns per point*): give each row once,
        either here or to ``add_points``."""
        pts = _as_points(points_world, "points_world")
        cell = self.cell_m if cell_m is None else float(cell_m)
        if cell <= 0.0 or self.cell_point != "first" or cell not in self._cell_sizes:
            return np.ones(pts.shape[0], np.bool_)
        index = int(np.flatnonzero(self._cell_sizes == cell)[0])
        return ~_cells_taken(pts, cell, index, self._okeys, self._ocount, self.num_voxels,
                             self.max_points_per_voxel, self._vblocks, self._returns)

    def remove_points(self, points_world: np.ndarray) -> np.ndarray:
        """Remove the stored points equal to rows of ``points_world`` (points seen to have
        moved); returns which rows were found. Their cells are free again."""
        pts = _as_points(points_world, "points_world")
        removed = np.zeros(pts.shape[0], np.bool_)
        if pts.shape[0] and self.num_voxels:
            _remove_points(pts, self.resolution_m, self.max_points_per_voxel, self._table,
                           self._vkeys, self._vtotal, self._vblocks, self._pool,
                           self._cell_sizes, self._okeys, self._ocount, self._ostate, removed)
        return removed

    def points(self) -> np.ndarray:
        """All stored points (P,3) float64, world frame, grouped by voxel in a deterministic order."""
        return self.points_with_returns(0.0)[0]

    def points_with_returns(self, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(points (P,3) as :meth:`points`, returns (P,) int64): how many rows reached each
        point's cell floor(p / cell_m) (module docstring, *Returns per point*), summed over the
        cell's stored points; with ``cell_m`` 0, each point's own count."""
        pts, counts = _gather_points(
            self.num_voxels,
            self.num_points,
            self.max_points_per_voxel,
            self._vtotal,
            self._vblocks,
            self._pool,
            self._returns,
        )
        if cell_m > 0.0 and len(pts) > 1:
            cells = np.floor(pts / cell_m)
            if np.abs(cells).max() < _PACK_HALF:  # one int64 per cell: a far faster unique
                packed = cells.astype(np.int64) + _PACK_HALF
                cells = (packed[:, 0] << 42) | (packed[:, 1] << 21) | packed[:, 2]
                _, inverse = np.unique(cells, return_inverse=True)
            else:
                _, inverse = np.unique(cells, axis=0, return_inverse=True)
            inverse = inverse.reshape(-1)
            counts = np.bincount(inverse, weights=counts).astype(np.int64)[inverse]
        return pts, counts


def _as_points(points: np.ndarray, name: str) -> np.ndarray:
    arr = np.ascontiguousarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {np.shape(points)}")
    return arr
