"""Local plane fits to the k nearest map neighbours of each scan point (lio-design.md §6.2).

Neighbours are world-frame points in metres, as returned by :meth:`adalio.lio.ivox.IVox.knn`
(``nbrs (M,k,3)``, first ``counts[i]`` rows valid). A plane is ``{x : n . x + d = 0}`` with
``|n| = 1``; both methods return ``d >= 0`` (n points from the plane towards the world origin).

* ``'ls'`` (Faster-LIO parity): least squares on ``a^T x = -1`` through the 3x3 normal equations
  ``(A^T A) a = -A^T 1``, ``n = a/|a|``, ``d = 1/|a|``. This parameterisation cannot represent a
  plane through the world origin (``|a| -> inf``, ``A^T A`` singular): when the estimated
  reciprocal condition number of ``A^T A`` is below ``LS_MIN_RCOND`` or the solution is not
  finite, that point falls back to the PCA fit (it is not marked invalid for that reason).
* ``'pca'``: normal = eigenvector of the smallest eigenvalue of the neighbour covariance (cyclic
  Jacobi in numba), ``d = -n . mean``.

A plane is valid iff ``counts >= max(min_neighbors, 3)``, the fit is finite and non-degenerate
(neighbours not collinear), **every** neighbour satisfies ``|n . q_i + d| <= margin_m``, and the
neighbours span the plane: sqrt(middle eigenvalue of their covariance) >= ``min_extent_m``
(adalio addition; 0 disables it). A tight cluster of neighbours (a few cm across) passes the
margin test whatever its fitted normal, which is then arbitrary and acts as a fake constraint.
Rows with a fit keep it even when invalid by margin; rows without one are NaN.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from adalio.errors import ConfigError, InputError
from adalio.jit import kernel

LS_MIN_RCOND = 1e-10
"""LS falls back to PCA when the reciprocal condition number of A^T A (estimated as
det / (trace * sum of principal 2x2 minors), within a factor 9 of lambda_min / lambda_max) is
below this: the neighbours' plane passes (numerically) through the origin (lio-design.md §6.2)."""
PCA_MIN_REL_SPREAD = 1e-12
"""PCA fit rejected when the middle covariance eigenvalue is below this fraction of the largest
(collinear or coincident neighbours: the normal is undefined)."""
PLANE_METHODS = ("ls", "pca")
PARALLEL_MIN_ROWS = 16384
"""Batches with fewer rows run single-threaded: an LS fit costs ~0.1 us and a PCA fit ~0.5 us per
row, so thread wake-up and scheduling (several ms on the shared 2-core dev machine) dominate
below this size; see benchmarks/bench_map_kernels.py."""
_JACOBI_SWEEPS = 12


@kernel()
def _jacobi_eigen(c: np.ndarray, v: np.ndarray):
    """Eigen-decomposition of a symmetric 3x3 matrix by cyclic Jacobi rotations (§6.2 PCA).

    ``c`` becomes diagonal (the eigenvalues), ``v`` receives the eigenvectors as columns.
    Returns the column indices of the (smallest, middle, largest) eigenvalue.
    """
    for r in range(3):
        for col in range(3):
            v[r, col] = 1.0 if r == col else 0.0
    for _ in range(_JACOBI_SWEEPS):
        off = abs(c[0, 1]) + abs(c[0, 2]) + abs(c[1, 2])
        scale = abs(c[0, 0]) + abs(c[1, 1]) + abs(c[2, 2])
        if off <= 1e-15 * scale or off == 0.0:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            apq = c[p, q]
            if apq == 0.0:
                continue
            theta = (c[q, q] - c[p, p]) / (2.0 * apq)
            t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            cs = 1.0 / np.sqrt(t * t + 1.0)
            sn = t * cs
            for r in range(3):
                crp = c[r, p]
                crq = c[r, q]
                c[r, p] = cs * crp - sn * crq
                c[r, q] = sn * crp + cs * crq
            for r in range(3):
                cpr = c[p, r]
                cqr = c[q, r]
                c[p, r] = cs * cpr - sn * cqr
                c[q, r] = sn * cpr + cs * cqr
            for r in range(3):
                vrp = v[r, p]
                vrq = v[r, q]
                v[r, p] = cs * vrp - sn * vrq
                v[r, q] = sn * vrp + cs * vrq
    i0 = 0
    i2 = 0
    for i in range(1, 3):
        if c[i, i] < c[i0, i0]:
            i0 = i
        if c[i, i] > c[i2, i2]:
            i2 = i
    if i0 == i2:
        i2 = (i0 + 1) % 3
    return i0, 3 - i0 - i2, i2


@kernel()
def _fit_pca(nbrs: np.ndarray, cnt: int, c: np.ndarray, v: np.ndarray, out_n: np.ndarray) -> float:
    """PCA plane through the neighbour mean (§6.2 option); returns d, or NaN if degenerate.

    ``c``, ``v`` are 3x3 scratch arrays; the unit normal is written to ``out_n``.
    """
    mx, my, mz = _scatter(nbrs, cnt, c)
    i_min, i_mid, i_max = _jacobi_eigen(c, v)
    if not (c[i_mid, i_mid] > PCA_MIN_REL_SPREAD * c[i_max, i_max]):
        return np.nan
    norm = np.sqrt(v[0, i_min] ** 2 + v[1, i_min] ** 2 + v[2, i_min] ** 2)
    nx = v[0, i_min] / norm
    ny = v[1, i_min] / norm
    nz = v[2, i_min] / norm
    d = -(nx * mx + ny * my + nz * mz)
    flip = d < 0.0
    if d == 0.0:
        big = nx
        if abs(ny) > abs(big):
            big = ny
        if abs(nz) > abs(big):
            big = nz
        flip = big < 0.0
    if flip:
        nx, ny, nz, d = -nx, -ny, -nz, -d
    out_n[0] = nx
    out_n[1] = ny
    out_n[2] = nz
    return d + 0.0


@kernel()
def _scatter(nbrs: np.ndarray, cnt: int, c: np.ndarray) -> tuple[float, float, float]:
    """Centroid of the first cnt neighbours; their scatter matrix sum (x-mu)(x-mu)^T -> ``c``."""
    mx = 0.0
    my = 0.0
    mz = 0.0
    for j in range(cnt):
        mx += nbrs[j, 0]
        my += nbrs[j, 1]
        mz += nbrs[j, 2]
    mx /= cnt
    my /= cnt
    mz /= cnt
    c[:, :] = 0.0
    for j in range(cnt):
        dx = nbrs[j, 0] - mx
        dy = nbrs[j, 1] - my
        dz = nbrs[j, 2] - mz
        c[0, 0] += dx * dx
        c[0, 1] += dx * dy
        c[0, 2] += dx * dz
        c[1, 1] += dy * dy
        c[1, 2] += dy * dz
        c[2, 2] += dz * dz
    c[1, 0] = c[0, 1]
    c[2, 0] = c[0, 2]
    c[2, 1] = c[1, 2]
    return mx, my, mz


@kernel()
def _middle_eigenvalue(c: np.ndarray) -> float:
    """Middle eigenvalue of a symmetric 3x3 matrix, closed form (trigonometric solution of the
    characteristic cubic)."""
    a00 = c[0, 0]
    a01 = c[0, 1]
    a02 = c[0, 2]
    a11 = c[1, 1]
    a12 = c[1, 2]
    a22 = c[2, 2]
    q = (a00 + a11 + a22) / 3.0
    b00 = a00 - q
    b11 = a11 - q
    b22 = a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
    if not p2 > 1e-30 * (q * q + 1e-300):
        return q
    p = np.sqrt(p2 / 6.0)
    det = (
        b00 * (b11 * b22 - a12 * a12)
        - a01 * (a01 * b22 - a12 * a02)
        + a02 * (a01 * a12 - b11 * a02)
    )
    r = det / (2.0 * p * p * p)
    r = min(max(r, -1.0), 1.0)
    phi = np.arccos(r) / 3.0
    e_max = q + 2.0 * p * np.cos(phi)
    e_min = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return max(3.0 * q - e_max - e_min, 0.0)


@kernel()
def _middle_variance(nbrs: np.ndarray, cnt: int, c: np.ndarray) -> float:
    """Middle eigenvalue (m²) of the covariance (divided by cnt) of the first cnt neighbours;
    ``c`` is 3x3 scratch."""
    _scatter(nbrs, cnt, c)
    return _middle_eigenvalue(c) / cnt


@kernel()
def _fit_ls(nbrs: np.ndarray, cnt: int, out_n: np.ndarray) -> float:
    """a^T x = -1 least squares via 3x3 normal equations (§6.2); NaN when it must fall back."""
    s00 = 0.0
    s01 = 0.0
    s02 = 0.0
    s11 = 0.0
    s12 = 0.0
    s22 = 0.0
    b0 = 0.0
    b1 = 0.0
    b2 = 0.0
    for j in range(cnt):
        x = nbrs[j, 0]
        y = nbrs[j, 1]
        z = nbrs[j, 2]
        s00 += x * x
        s01 += x * y
        s02 += x * z
        s11 += y * y
        s12 += y * z
        s22 += z * z
        b0 -= x
        b1 -= y
        b2 -= z
    c00 = s11 * s22 - s12 * s12
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    c11 = s00 * s22 - s02 * s02
    c12 = s01 * s02 - s00 * s12
    c22 = s00 * s11 - s01 * s01
    det = s00 * c00 + s01 * c01 + s02 * c02
    if not (det > LS_MIN_RCOND * (s00 + s11 + s22) * (c00 + c11 + c22)):
        return np.nan
    ax = (c00 * b0 + c01 * b1 + c02 * b2) / det
    ay = (c01 * b0 + c11 * b1 + c12 * b2) / det
    az = (c02 * b0 + c12 * b1 + c22 * b2) / det
    norm = np.sqrt(ax * ax + ay * ay + az * az)
    if not (np.isfinite(norm) and norm > 0.0):
        return np.nan
    d = 1.0 / norm
    out_n[0] = ax / norm
    out_n[1] = ay / norm
    out_n[2] = az / norm
    return d


@kernel()
def fit_plane(nbrs: np.ndarray, cnt: int, use_ls: bool, scratch: np.ndarray,
              out_n: np.ndarray) -> float:
    """The plane through the first ``cnt`` neighbours (§6.2): LS, or PCA where LS must fall
    back. Writes the unit normal to ``out_n`` and returns d; NaN (and a NaN normal) if neither
    method gives one. ``scratch`` is (2,3,3)."""
    d = np.nan
    if use_ls:
        d = _fit_ls(nbrs, cnt, out_n)
    if not np.isfinite(d):
        d = _fit_pca(nbrs, cnt, scratch[0], scratch[1], out_n)
    if not np.isfinite(d):
        out_n[:] = np.nan
    return d


@kernel()
def within_margin(nbrs: np.ndarray, cnt: int, n: np.ndarray, d: float, margin_m: float) -> bool:
    """The all-neighbours margin test of §6.2: every |n . q_j + d| <= margin_m."""
    for j in range(cnt):
        r = n[0] * nbrs[j, 0] + n[1] * nbrs[j, 1] + n[2] * nbrs[j, 2] + d
        if not abs(r) <= margin_m:
            return False
    return True


@kernel()
def within_support(nbrs: np.ndarray, cnt: int, n: np.ndarray, mx: float, my: float, mz: float,
                   qx: float, qy: float, qz: float) -> bool:
    """The query ``q`` lies within its neighbours' span along the plane: its in-plane offset
    ``o`` from the neighbours' centroid ``(mx, my, mz)`` is no longer than the farthest
    neighbour's projection on it, ``|o|² <= max_j (q_j - mu) . o``. A query beyond every
    neighbour would be matched to an extrapolated plane (a leading edge of the map, a curved
    wall seen from its mapped side), whose error grows with the distance instead of averaging
    out (README, "Planes within their support")."""
    ox = qx - mx
    oy = qy - my
    oz = qz - mz
    along = ox * n[0] + oy * n[1] + oz * n[2]
    ox -= along * n[0]
    oy -= along * n[1]
    oz -= along * n[2]
    o2 = ox * ox + oy * oy + oz * oz
    reach = 0.0
    for j in range(cnt):
        reach = max(reach, (nbrs[j, 0] - mx) * ox + (nbrs[j, 1] - my) * oy
                    + (nbrs[j, 2] - mz) * oz)
    return o2 <= reach


@kernel()
def elevation_spread(nbrs: np.ndarray, cnt: int, origin: np.ndarray, axis: np.ndarray) -> float:
    """The spread (max - min, rad) of the elevation angles of the first ``cnt`` neighbours seen
    from ``origin`` about the unit ``axis``: ``asin(axis . u_j)`` with ``u_j`` the unit
    direction from ``origin`` to neighbour ``j``. A spinning LiDAR's ring is a cone of one
    elevation about its spin axis, so neighbours that one ring laid down from (near) ``origin``
    have a spread of about 0, and the plane fitted to them is the cone's tangent plane: it
    contains the rays, whatever the surface's tilt about the ring. Neighbours at ``origin``
    itself are skipped; if none is left, infinity (nothing to judge). The extremes
    are taken on the sines (asin is monotone), so two asin per call, not one per neighbour."""
    lo = np.inf
    hi = -np.inf
    for j in range(cnt):
        dx = nbrs[j, 0] - origin[0]
        dy = nbrs[j, 1] - origin[1]
        dz = nbrs[j, 2] - origin[2]
        r = np.sqrt(dx * dx + dy * dy + dz * dz)
        if not r > 0.0:
            continue
        s = (dx * axis[0] + dy * axis[1] + dz * axis[2]) / r
        lo = min(lo, s)
        hi = max(hi, s)
    if not hi >= lo:
        return np.inf
    return np.arcsin(min(max(hi, -1.0), 1.0)) - np.arcsin(min(max(lo, -1.0), 1.0))


@kernel()
def _fit_row(
    i: int,
    nbrs: np.ndarray,
    counts: np.ndarray,
    min_count: int,
    margin_m: float,
    min_extent_m: float,
    use_ls: bool,
    scratch: np.ndarray,
    normals: np.ndarray,
    dist: np.ndarray,
    valid: np.ndarray,
) -> None:
    """Plane fit of row i, the all-neighbours margin test of lio-design.md §6.2 and the
    in-plane extent test."""
    cnt = min(counts[i], nbrs.shape[1])
    if cnt < min_count:
        return
    d = fit_plane(nbrs[i], cnt, use_ls, scratch, normals[i])
    dist[i] = d
    if not (np.isfinite(d) and within_margin(nbrs[i], cnt, normals[i], d, margin_m)):
        return
    if min_extent_m > 0.0:
        lam_mid = _middle_variance(nbrs[i], cnt, scratch[0])
        if not lam_mid >= min_extent_m * min_extent_m:
            return
    valid[i] = True


@kernel()
def _fit_planes_serial(
    nbrs, counts, min_count, margin_m, min_extent_m, use_ls, normals, dist, valid
):
    """All rows, one thread."""
    scratch = np.empty((2, 3, 3))
    for i in range(nbrs.shape[0]):
        _fit_row(
            i,
            nbrs,
            counts,
            min_count,
            margin_m,
            min_extent_m,
            use_ls,
            scratch,
            normals,
            dist,
            valid,
        )


@kernel(parallel=True)
def _fit_planes_parallel(
    nbrs, counts, min_count, margin_m, min_extent_m, use_ls, normals, dist, valid
):
    """All rows; rows are independent (own scratch), so the result is deterministic."""
    scratch = np.empty((nbrs.shape[0], 2, 3, 3))
    for i in prange(nbrs.shape[0]):
        _fit_row(
            i,
            nbrs,
            counts,
            min_count,
            margin_m,
            min_extent_m,
            use_ls,
            scratch[i],
            normals,
            dist,
            valid,
        )


def fit_planes(
    nbrs: np.ndarray,
    counts: np.ndarray,
    min_neighbors: int,
    margin_m: float,
    method: str = "ls",
    min_extent_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane n . x + d = 0 through each row's neighbours, with the §6.2 validity test.

    ``nbrs`` (M,k,3) world points (first ``counts[i]`` used), ``method`` 'ls' or 'pca' (see the
    module docstring). ``min_extent_m``: a plane whose neighbours have an in-plane spread
    sqrt(middle covariance eigenvalue) below this is invalid (0 disables the test).
    Returns ``(normals (M,3), d (M,), valid (M,) bool)``.
    """
    if method not in PLANE_METHODS:
        raise ConfigError(f"filter.plane_fit must be 'ls' or 'pca', got {method!r}")
    nb = np.ascontiguousarray(nbrs, dtype=np.float64)
    cn = np.ascontiguousarray(counts, dtype=np.int64)
    if nb.ndim != 3 or nb.shape[2] != 3 or cn.shape != (nb.shape[0],):
        raise InputError(
            f"nbrs must be (M, k, 3) and counts (M,), got {np.shape(nbrs)}, {np.shape(counts)}"
        )
    m = nb.shape[0]
    normals = np.full((m, 3), np.nan)
    dist = np.full(m, np.nan)
    valid = np.zeros(m, np.bool_)
    kernel = _fit_planes_parallel if m >= PARALLEL_MIN_ROWS else _fit_planes_serial
    if not (np.isfinite(min_extent_m) and min_extent_m >= 0.0):
        raise ConfigError(f"plane min_extent_m must be >= 0 metres, got {min_extent_m!r}")
    kernel(
        nb,
        cn,
        max(int(min_neighbors), 3),
        float(margin_m),
        float(min_extent_m),
        method == "ls",
        normals,
        dist,
        valid,
    )
    return normals, dist, valid


@kernel()
def _neighbour_moments(nbrs, counts):
    """Centroid (M,3) and middle covariance eigenvalue (M,) of each row's first counts[i]
    neighbours (NaN / 0 for rows with fewer than 3)."""
    m = nbrs.shape[0]
    mu = np.full((m, 3), np.nan)
    lam_mid = np.zeros(m)
    c = np.empty((3, 3))
    for i in range(m):
        cnt = min(counts[i], nbrs.shape[1])
        if cnt < 3:
            continue
        mu[i, 0], mu[i, 1], mu[i, 2] = _scatter(nbrs[i], cnt, c)
        lam_mid[i] = _middle_eigenvalue(c) / cnt
    return mu, lam_mid


def neighbour_moments(nbrs: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid (M,3) and middle covariance eigenvalue lambda_mid (M,) (m²) of each row's first
    ``counts[i]`` neighbours; rows with fewer than 3 give NaN / 0."""
    nb = np.ascontiguousarray(nbrs, dtype=np.float64)
    cn = np.ascontiguousarray(counts, dtype=np.int64)
    return _neighbour_moments(nb, cn)
