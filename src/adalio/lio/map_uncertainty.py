"""Map uncertainty: the world-frame pose covariance a scan inherits from the map it registered to.

The filter treats the map as exact, so its covariance ``P`` is the pose uncertainty *relative to
the map*. The map itself was placed by earlier, uncertain poses: a part of the map inserted by
scan ``j`` is displaced rigidly by that scan's pose error ``(δp_j, δφ_j)`` (world frame), so a map
point ``x`` sits at ``x + δp_j + δφ_j × (x - p_j)``. A pose registered against that part of the
map follows it: its error is ``δp = δp_j - [p_k - p_j]× δφ_j``, ``δφ = δφ_j``, i.e. the map's
covariance transported with the lever arm ``d = p_k - p_j`` (VoxelMap and PV-LIO carry the
inserting pose's covariance with every map point for the same reason)::

    T(d) = [[I, -[d]×], [0, I]],    W_map,k = Σ_j c_j T(d_j) W_j T(d_j)ᵀ / Σ_j c_j

over the scans ``j`` that inserted the map points the scan matched (``c_j`` correspondences
each), and the scan's world covariance is ``W_k = W_rel,k + W_map,k``, where ``W_rel,k`` is the
filter's pose covariance turned into world axes (position, then small world rotations). ``W_k``
is stored as the covariance of the map cells scan ``k`` is the first to fill, so the uncertainty
accumulates as the map is extended (odometry drift) and stays put while the sensor re-observes
the same map. The first scan anchors the world: ``W_0 = 0``.
With ``filter.sigmas_deskew_noise`` every later ``W_k`` also holds the rotation the gyro's
noise puts into that scan's undistortion (:func:`deskew_covariance`), added after the bound
below (it is independent of the map's error and of the registration's bias), and so does the
map that scan extends. The first scan's own is left out: ``W_0`` with it made the bound (then
with ``α`` from the position traces alone) scale its rotation by ``1/α`` with ``α`` near 0 (a
map of rotation and hardly any position near the start), and the height sigmas of the spiral's
first 25 s grew by up to 2x for it.

The two terms are not independent. Where the scans are weakly constrained (a spiral shaft, a
stairwell's height) each scan's registration is biased the same way as the scans that built the
map it registers to, so ``W_rel,k`` and ``W_map,k`` are positively correlated and the map error
grows with the distance travelled, not with its square root (measured: the 1 s increments of the
error are correlated from one second to the next by +0.5 to +0.9 there, by -0.2 to -0.4 in the
open hall; ``benchmarks/bench_modes.py``). The correlation is unknown, so by default
(``filter.map_error_correlated``) ``W_k`` is the bound that holds for any correlation between
two errors ``a`` and ``b``: ``Cov(a + b) ⪯ (1 + α) Cov(a) + (1 + 1/α) Cov(b)`` for every
``α > 0``. ``α`` is balanced over the six axes (:func:`world_covariance`; each axis, position
and rotation, counts alike, so none is inflated without limit: until session 45 ``α = sqrt(tr
W_map,pp / tr W_rel,pp)`` minimised the position trace alone and scaled a rotation held with
hardly any position by ``1/α``). Along a chain of map extensions the standard deviations add
up instead of their variances. ``filter.map_error_correlated: false`` adds them as independent.

Chosen approximations, conservative or neutral for the 3σ test: the map errors of different
scans are averaged (fully correlated, not independent, which would shrink ``W_map``), and in a
direction no scan constrains, the IMU growth since then is in both terms, so the sum over-states
it by up to 2x in variance (4x with the bound).
Provenance is kept per ``cell_m`` cell (first scan to insert a point there), not per point,
and from regular strides of the inserted and matched points (``MAX_*_SAMPLES``).
The trajectory is unchanged: this only feeds the reported sigmas.
"""

from __future__ import annotations

import numpy as np

from adalio.jit import kernel
from adalio.lio import so3
from adalio.lio.ivox import hash_key3

MAX_MATCHED_SAMPLES = 512
"""The owners' mean is taken over at most this many matched points (a regular stride)."""
MAX_INSERTED_SAMPLES = 1024
"""Cells are claimed from at most this many of a scan's inserted points (a regular stride): a
cell a scan fills holds several of its points, and a cell missed is claimed by a scan or two
later, with nearly the same covariance."""
_OFFSET = 1 << 20
"""Cell indices are shifted by this before packing 21 bits per axis (±2^20 cells)."""
_MASK21 = (1 << 21) - 1


def world_covariance(W_rel: np.ndarray, W_map: np.ndarray, correlated: bool) -> np.ndarray:
    """The 6x6 world covariance ``W_k`` of a pose from the filter's ``W_rel`` and the map's
    ``W_map``: their sum (``correlated=False``), or the bound
    ``(1 + α) W_rel + (1 + 1/α) W_map`` on the covariance of the sum of two errors whatever
    their correlation (module doc), with ``α = r_map / r_rel`` balanced over the six axes:
    ``r² = Σ_a W_aa / v_a`` with ``v_a = (sqrt(W_rel,aa) + sqrt(W_map,aa))²``, each axis's own
    smallest bound, so every axis, position or rotation, counts alike in its own units, and no
    axis's variance exceeds 12 ``v_a``. The bound is the sum when either term is zero, and it
    is tight when one error is a positive multiple of the other."""
    W_rel = np.asarray(W_rel, dtype=np.float64)
    W_map = np.asarray(W_map, dtype=np.float64)
    if not correlated:
        return W_rel + W_map
    a, b = np.maximum(np.diag(W_rel), 0.0), np.maximum(np.diag(W_map), 0.0)
    v = (np.sqrt(a) + np.sqrt(b)) ** 2  # each axis's own smallest bound
    held = v > 0.0
    ra, rb = np.sqrt(np.sum(a[held] / v[held])), np.sqrt(np.sum(b[held] / v[held]))
    if not (ra > 0.0 and rb > 0.0):
        return W_rel + W_map
    return (1.0 + rb / ra) * W_rel + (1.0 + ra / rb) * W_map


def deskew_covariance(q_gyro_rad2_s: float, span_s: float) -> np.ndarray:
    """6x6 world covariance (position, small world rotation) of the rotation the gyro's white
    noise puts into a sweep's undistortion, which the filter treats as exact. Each point is
    moved to the sweep's end by the gyro integrated from its time to the end: a random walk of
    density² ``q_gyro_rad2_s`` (rad²/s) pinned at the end, ``W(τ)`` for a point ``τ`` before
    it. The registration takes its mean over the sweep; for points spread evenly over
    ``span_s`` seconds ``Var(mean W) = q span / 3`` per axis (∫₀ᵀ∫₀ᵀ min(s, t) ds dt / T² =
    T / 3), the same about every axis, so the same in the body and the world frame. Position:
    none (the rotation is about the sensor)."""
    W = np.zeros((6, 6))
    if q_gyro_rad2_s > 0 and span_s > 0:
        W[3:, 3:] = np.eye(3) * (q_gyro_rad2_s * span_s / 3.0)
    return W


@kernel()
def transport(W: np.ndarray, d: np.ndarray) -> np.ndarray:
    """A 6x6 covariance moved by the lever arm d (3,): T(d) W T(d)ᵀ (module doc)."""
    T = np.eye(6)
    # -[d]x in the position-rotation block
    T[0, 4], T[0, 5] = d[2], -d[1]
    T[1, 3], T[1, 5] = -d[2], d[0]
    T[2, 3], T[2, 4] = d[1], -d[0]
    return so3.mul(so3.mul(T, W), T.T)


@kernel()
def _axis_cell(v: float) -> int:
    c = int(np.floor(v)) + _OFFSET if np.isfinite(v) and abs(v) < 2.0**21 else 0
    return min(max(c, 0), _MASK21)


@kernel()
def _cell_key(x: float, y: float, z: float, cell_m: float) -> int:
    """The cell of one point (x, y, z) shifted by _OFFSET, 21 bits each, packed in one
    non-negative int64 (non-finite coordinates and cells beyond ±2^20 are clipped to the edge)."""
    return ((_axis_cell(x / cell_m) << 42) | (_axis_cell(y / cell_m) << 21)
            | _axis_cell(z / cell_m))


@kernel()
def cell_keys(points: np.ndarray, cell_m: float) -> np.ndarray:
    """:func:`_cell_key` of every row."""
    n = points.shape[0]
    keys = np.empty(n, np.int64)
    for i in range(n):
        keys[i] = _cell_key(points[i, 0], points[i, 1], points[i, 2], cell_m)
    return keys


@kernel()
def _slot(keys: np.ndarray, key: int) -> int:
    """The slot of ``key`` in the open-addressing table ``keys`` (power-of-two size, -1 = empty):
    where it is, or the empty slot where it would go."""
    mask = keys.shape[0] - 1
    slot = hash_key3(key >> 42, (key >> 21) & _MASK21, key & _MASK21, mask)
    while keys[slot] >= 0 and keys[slot] != key:
        slot = (slot + 1) & mask
    return slot


@kernel()
def _insert(keys: np.ndarray, owner: np.ndarray, new_keys: np.ndarray,
            new_owner: np.ndarray) -> int:
    """Enter each cell of ``new_keys`` that the table does not hold yet, owned by the same row
    of ``new_owner``; returns how many were entered. The table must have room for all."""
    n = 0
    for i in range(new_keys.shape[0]):
        slot = _slot(keys, new_keys[i])
        if keys[slot] < 0:
            keys[slot] = new_keys[i]
            owner[slot] = new_owner[i]
            n += 1
    return n


@kernel()
def _owners(keys: np.ndarray, owner: np.ndarray, cell_keys: np.ndarray) -> np.ndarray:
    out = np.full(cell_keys.shape[0], -1, np.int64)
    for i in range(cell_keys.shape[0]):
        slot = _slot(keys, cell_keys[i])
        if keys[slot] >= 0:
            out[i] = owner[slot]
    return out


@kernel()
def _map_covariance(keys: np.ndarray, owner: np.ndarray, n_scans: int, cell_m: float,
                    max_samples: int, matched: np.ndarray, covariances: np.ndarray,
                    positions: np.ndarray, p_world: np.ndarray) -> np.ndarray:
    """:meth:`MapProvenance.map_covariance` in one pass: the finite rows of ``matched``, every
    ``stride``-th of them (at most ``max_samples``), their cells' owners counted, and the
    owners' covariances transported to ``p_world`` and averaged with those counts as weights,
    in ascending scan order."""
    n = 0
    for i in range(matched.shape[0]):
        if (np.isfinite(matched[i, 0]) and np.isfinite(matched[i, 1])
                and np.isfinite(matched[i, 2])):
            n += 1
    out = np.zeros((6, 6))
    if n == 0:
        return out
    stride = -(-n // max_samples)
    counts = np.zeros(n_scans, np.int64)
    total = 0
    k = 0
    for i in range(matched.shape[0]):
        if not (np.isfinite(matched[i, 0]) and np.isfinite(matched[i, 1])
                and np.isfinite(matched[i, 2])):
            continue
        if k % stride == 0:
            slot = _slot(keys, _cell_key(matched[i, 0], matched[i, 1], matched[i, 2], cell_m))
            if keys[slot] >= 0:
                counts[owner[slot]] += 1
                total += 1
        k += 1
    if total == 0:
        return out
    for j in range(n_scans):
        if counts[j]:
            out += (counts[j] / total) * transport(covariances[j], p_world - positions[j])
    return out


class MapProvenance:
    """Which scan first filled each map cell, and each such scan's world pose covariance."""

    def __init__(self, cell_m: float) -> None:
        if not cell_m > 0:
            raise ValueError("MapProvenance: cell_m must be > 0")
        self.cell_m = float(cell_m)
        # open-addressing table cell key -> owning scan, at most half full
        self._keys = np.full(1024, -1, np.int64)
        self._owner = np.full(1024, -1, np.int64)
        self._n_cells = 0
        self._positions = np.empty((64, 3))
        self._covariances = np.empty((64, 6, 6))
        self._n_scans = 0
        """Scans kept: only those that own at least one cell."""

    def __len__(self) -> int:
        return self._n_cells

    def _pack(self, points_world: np.ndarray) -> np.ndarray:
        return cell_keys(np.ascontiguousarray(points_world, dtype=np.float64), self.cell_m)

    def owners(self, points_world: np.ndarray) -> np.ndarray:
        """Index of the scan that first filled each point's cell (-1: no scan recorded)."""
        return _owners(self._keys, self._owner, self._pack(points_world))

    def map_covariance(self, p_world: np.ndarray, matched_world: np.ndarray) -> np.ndarray:
        """W_map (6x6) for a pose at ``p_world`` registered against the map points
        ``matched_world`` (M, 3; non-finite rows are left out): the mean of their owners'
        covariances, each transported by its lever arm (over a regular stride of at most
        ``MAX_MATCHED_SAMPLES`` of them). Zero when nothing matched a recorded cell."""
        if not self._n_scans or matched_world.shape[0] == 0:
            return np.zeros((6, 6))
        return _map_covariance(self._keys, self._owner, self._n_scans, self.cell_m,
                               MAX_MATCHED_SAMPLES,
                               np.ascontiguousarray(matched_world, dtype=np.float64),
                               self._covariances, self._positions,
                               np.asarray(p_world, dtype=np.float64))

    def add_scan(self, p_world: np.ndarray, W_world: np.ndarray,
                 inserted_world: np.ndarray) -> int:
        """The cells of ``inserted_world`` not yet owned become this scan's, and its pose and
        world covariance are kept. Returns the scan's index, or -1 if it owns no new cell (then
        nothing is kept: no map point will ever refer to it)."""
        stride = max(1, -(-inserted_world.shape[0] // MAX_INSERTED_SAMPLES))
        keys = self._pack(inserted_world[::stride])
        if not keys.shape[0]:
            return -1
        size = self._keys.shape[0]
        while 2 * (self._n_cells + keys.shape[0]) > size:
            size *= 2
        if size != self._keys.shape[0]:  # a larger table, the cells entered again
            held = self._keys >= 0
            old_keys, old_owner = self._keys[held], self._owner[held]
            self._keys, self._owner = np.full(size, -1, np.int64), np.full(size, -1, np.int64)
            _insert(self._keys, self._owner, old_keys, old_owner)
        j = self._n_scans
        claimed = _insert(self._keys, self._owner, keys, np.full(keys.shape[0], j, np.int64))
        if not claimed:
            return -1
        self._n_cells += claimed
        if j == self._positions.shape[0]:
            self._positions = np.concatenate([self._positions, np.empty_like(self._positions)])
            self._covariances = np.concatenate([self._covariances,
                                                np.empty_like(self._covariances)])
        self._positions[j] = p_world
        self._covariances[j] = W_world
        self._n_scans = j + 1
        return j


__all__ = ["MapProvenance", "transport", "world_covariance"]
