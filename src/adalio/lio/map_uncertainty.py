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

The two terms are not independent. Where the scans are weakly constrained (a spiral shaft, a
stairwell's height) each scan's registration is biased the same way as the scans that built the
map it registers to, so ``W_rel,k`` and ``W_map,k`` are positively correlated and the map error
grows with the distance travelled, not with its square root (measured: the 1 s increments of the
error are correlated from one second to the next by +0.5 to +0.9 there, by -0.2 to -0.4 in the
open hall; ``benchmarks/bench_modes.py``). The correlation is unknown, so by default
(``filter.map_error_correlated``) ``W_k`` is the bound that holds for any correlation between
two errors ``a`` and ``b``: ``Cov(a + b) ⪯ (1 + α) Cov(a) + (1 + 1/α) Cov(b)`` for every
``α > 0``, with ``α = sqrt(tr W_map,pp / tr W_rel,pp)``, the value that minimises the position
trace, which then is ``(sqrt(tr W_rel,pp) + sqrt(tr W_map,pp))²``: the position standard
deviations of a chain of map extensions add up instead of their variances
(:func:`world_covariance`). ``filter.map_error_correlated: false`` adds them as independent.

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

MAX_MATCHED_SAMPLES = 512
"""The owners' mean is taken over at most this many matched points (a regular stride)."""
MAX_INSERTED_SAMPLES = 1024
"""Cells are claimed from at most this many of a scan's inserted points (a regular stride): a
cell a scan fills holds several of its points, and a cell missed is claimed by a scan or two
later, with nearly the same covariance."""
_OFFSET = 1 << 20
"""Cell indices are shifted by this before packing 21 bits per axis (±2^20 cells)."""


def world_covariance(W_rel: np.ndarray, W_map: np.ndarray, correlated: bool) -> np.ndarray:
    """The 6x6 world covariance ``W_k`` of a pose from the filter's ``W_rel`` and the map's
    ``W_map``: their sum (``correlated=False``), or the bound
    ``(1 + α) W_rel + (1 + 1/α) W_map`` with ``α = sqrt(tr W_map,pp / tr W_rel,pp)`` on the
    covariance of the sum of two errors whatever their correlation (module doc). The bound is
    the sum when either position block is zero (the other term then holds no position error to
    correlate with), and it is tight when one error is a positive multiple of the other."""
    W_rel = np.asarray(W_rel, dtype=np.float64)
    W_map = np.asarray(W_map, dtype=np.float64)
    a, b = float(np.trace(W_rel[:3, :3])), float(np.trace(W_map[:3, :3]))
    if not (correlated and a > 0.0 and b > 0.0):
        return W_rel + W_map
    alpha = np.sqrt(b / a)
    return (1.0 + alpha) * W_rel + (1.0 + 1.0 / alpha) * W_map


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
def _cell_keys(points: np.ndarray, cell_m: float) -> np.ndarray:
    """One int64 per point: its cell (x, y, z) shifted by _OFFSET, 21 bits each (non-finite
    rows and cells beyond ±2^20 are clipped to the edge)."""
    n = points.shape[0]
    keys = np.empty(n, np.int64)
    top = (1 << 21) - 1
    for i in range(n):
        key = 0
        for a in range(3):
            v = points[i, a] / cell_m
            c = int(np.floor(v)) + _OFFSET if np.isfinite(v) and abs(v) < 2.0**21 else 0
            key = (key << 21) | min(max(c, 0), top)
        keys[i] = key
    return keys


@kernel()
def _mean_transported(scans: np.ndarray, weights: np.ndarray, covariances: np.ndarray,
                      positions: np.ndarray, p_world: np.ndarray) -> np.ndarray:
    """sum_i weights[i] transport(covariances[scans[i]], p_world - positions[scans[i]])."""
    out = np.zeros((6, 6))
    for i in range(scans.shape[0]):
        j = scans[i]
        out += weights[i] * transport(covariances[j], p_world - positions[j])
    return out


class MapProvenance:
    """Which scan first filled each map cell, and each such scan's world pose covariance."""

    def __init__(self, cell_m: float) -> None:
        if not cell_m > 0:
            raise ValueError("MapProvenance: cell_m must be > 0")
        self.cell_m = float(cell_m)
        self._keys = np.empty(0, np.int64)
        self._owner = np.empty(0, np.int64)
        self._positions = np.empty((64, 3))
        self._covariances = np.empty((64, 6, 6))
        self._n_scans = 0
        """Scans kept: only those that own at least one cell."""

    def __len__(self) -> int:
        return int(self._keys.shape[0])

    def _pack(self, points_world: np.ndarray) -> np.ndarray:
        return _cell_keys(np.ascontiguousarray(points_world, dtype=np.float64), self.cell_m)

    def owners(self, points_world: np.ndarray) -> np.ndarray:
        """Index of the scan that first filled each point's cell (-1: no scan recorded)."""
        keys = self._pack(points_world)
        out = np.full(keys.shape[0], -1, np.int64)
        if len(self):
            pos = np.minimum(np.searchsorted(self._keys, keys), len(self) - 1)
            found = self._keys[pos] == keys
            out[found] = self._owner[pos[found]]
        return out

    def map_covariance(self, p_world: np.ndarray, matched_world: np.ndarray) -> np.ndarray:
        """W_map (6x6) for a pose at ``p_world`` registered against the map points
        ``matched_world`` (M, 3): the mean of their owners' covariances, each transported by
        its lever arm (over a regular stride of at most ``MAX_MATCHED_SAMPLES`` of them). Zero
        when nothing matched a recorded cell."""
        if not self._n_scans or matched_world.shape[0] == 0:
            return np.zeros((6, 6))
        stride = -(-matched_world.shape[0] // MAX_MATCHED_SAMPLES)
        own = self.owners(matched_world[::stride])
        own = own[own >= 0]
        if own.shape[0] == 0:
            return np.zeros((6, 6))
        counts = np.bincount(own)
        scans = np.flatnonzero(counts)
        counts = counts[scans]
        return _mean_transported(scans, counts / counts.sum(), self._covariances,
                                 self._positions, np.asarray(p_world, dtype=np.float64))

    def add_scan(self, p_world: np.ndarray, W_world: np.ndarray,
                 inserted_world: np.ndarray) -> int:
        """The cells of ``inserted_world`` not yet owned become this scan's, and its pose and
        world covariance are kept. Returns the scan's index, or -1 if it owns no new cell (then
        nothing is kept: no map point will ever refer to it)."""
        stride = max(1, -(-inserted_world.shape[0] // MAX_INSERTED_SAMPLES))
        keys = self._pack(inserted_world[::stride])
        if len(self) and keys.shape[0]:
            pos = np.minimum(np.searchsorted(self._keys, keys), len(self) - 1)
            keys = keys[self._keys[pos] != keys]
        if not keys.shape[0]:
            return -1
        j = self._n_scans
        if j == self._positions.shape[0]:
            self._positions = np.concatenate([self._positions, np.empty_like(self._positions)])
            self._covariances = np.concatenate([self._covariances,
                                                np.empty_like(self._covariances)])
        self._positions[j] = p_world
        self._covariances[j] = W_world
        self._n_scans = j + 1
        keys = np.unique(keys)
        at = np.searchsorted(self._keys, keys)  # sorted insertion points of the sorted keys
        self._keys = np.insert(self._keys, at, keys)
        self._owner = np.insert(self._owner, at, j)
        return j


__all__ = ["MapProvenance", "transport", "world_covariance"]
