"""Point-to-plane measurement model: residual, range-adaptive gate and H rows (lio-design.md §6.3).

Inputs are undistorted, downsampled LiDAR-frame points ``p_L`` (m) and world planes
``nᵀx + d = 0`` (``|n| = 1``). World point ``p_W = R (R_LI p_L + t_LI) + p``.
"""

from __future__ import annotations

import numpy as np

from adalio.jit import kernel
from adalio.lio import so3

GATE_FACTOR = 81.0
"""Accept a residual iff ``|p_L| > 81 r²`` (FAST-LIO2's ``s > 0.9`` test, §6.3)."""


@kernel(inline="always")
def _world_point(points_lidar, i, M, t):
    """``M p_L + t`` of row i, with ``M = R R_LI`` and ``t = R t_LI + p`` (§1)."""
    x, y, z = points_lidar[i, 0], points_lidar[i, 1], points_lidar[i, 2]
    return (M[0, 0] * x + M[0, 1] * y + M[0, 2] * z + t[0],
            M[1, 0] * x + M[1, 1] * y + M[1, 2] * z + t[1],
            M[2, 0] * x + M[2, 1] * y + M[2, 2] * z + t[2])


@kernel()
def points_to_world(points_lidar, R, p, R_LI, t_LI):
    """``p_W = R (R_LI p_L + t_LI) + p`` for all points (§1)."""
    n = points_lidar.shape[0]
    M = so3.mul(R, R_LI)
    t = so3.mul_vec(R, t_LI) + p
    out = np.empty((n, 3))
    for i in range(n):
        out[i, 0], out[i, 1], out[i, 2] = _world_point(points_lidar, i, M, t)
    return out


@kernel()
def point_to_plane(points_lidar, R, p, R_LI, t_LI, normals, d, selected, estimate_extrinsic):
    """Residuals and Jacobian rows of the accepted points (§6.3), all points in one call.

    For each point with ``selected[i]``: ``r = nᵀ p_W + d``; accepted iff ``|p_L| > 81 r²``.
    Row (12 columns, error order p, θ, θ_LI, t_LI) with ``p_I = R_LI p_L + t_LI``, ``c = Rᵀ n``:
    ``[nᵀ, ([p_I]× c)ᵀ, ([p_L]× R_LIᵀ c)ᵀ, cᵀ]`` (extrinsic columns zero unless estimated).
    Returns ``(H (m,12), r (m,), accepted (n,) bool)``, rows in point order.
    """
    n = points_lidar.shape[0]
    accepted = np.zeros(n, dtype=np.bool_)
    res = np.empty(n)
    M = so3.mul(R, R_LI)
    tw = so3.mul_vec(R, t_LI) + p
    m = 0
    for i in range(n):
        if not selected[i]:
            continue
        x, y, z = points_lidar[i, 0], points_lidar[i, 1], points_lidar[i, 2]
        wx, wy, wz = _world_point(points_lidar, i, M, tw)
        r = d[i]
        r += normals[i, 0] * wx
        r += normals[i, 1] * wy
        r += normals[i, 2] * wz
        if np.sqrt(x * x + y * y + z * z) > GATE_FACTOR * r * r:
            accepted[i] = True
            res[i] = r
            m += 1
    H = np.zeros((m, 12))
    r_out = np.empty(m)
    j = 0
    for i in range(n):
        if not accepted[i]:
            continue
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        cx = R[0, 0] * nx + R[1, 0] * ny + R[2, 0] * nz
        cy = R[0, 1] * nx + R[1, 1] * ny + R[2, 1] * nz
        cz = R[0, 2] * nx + R[1, 2] * ny + R[2, 2] * nz
        lx, ly, lz = points_lidar[i, 0], points_lidar[i, 1], points_lidar[i, 2]
        ix = R_LI[0, 0] * lx + R_LI[0, 1] * ly + R_LI[0, 2] * lz + t_LI[0]
        iy = R_LI[1, 0] * lx + R_LI[1, 1] * ly + R_LI[1, 2] * lz + t_LI[1]
        iz = R_LI[2, 0] * lx + R_LI[2, 1] * ly + R_LI[2, 2] * lz + t_LI[2]
        H[j, 0] = nx
        H[j, 1] = ny
        H[j, 2] = nz
        H[j, 3] = iy * cz - iz * cy
        H[j, 4] = iz * cx - ix * cz
        H[j, 5] = ix * cy - iy * cx
        if estimate_extrinsic:
            ex = R_LI[0, 0] * cx + R_LI[1, 0] * cy + R_LI[2, 0] * cz
            ey = R_LI[0, 1] * cx + R_LI[1, 1] * cy + R_LI[2, 1] * cz
            ez = R_LI[0, 2] * cx + R_LI[1, 2] * cy + R_LI[2, 2] * cz
            H[j, 6] = ly * ez - lz * ey
            H[j, 7] = lz * ex - lx * ez
            H[j, 8] = lx * ey - ly * ex
            H[j, 9] = cx
            H[j, 10] = cy
            H[j, 11] = cz
        r_out[j] = res[i]
        j += 1
    return H, r_out, accepted


@kernel()
def residual_weights(points_lidar, accepted, R, p, R_LI, t_LI, normals, mu, lam_mid, counts,
                     group_id, n_groups, plane_variance, share):
    """1/sigma factor of each accepted row (point order) of :func:`point_to_plane`.

    The row's variance relative to the point noise is the product of
    ``plane_variance``: 1 + 1/k + rho²/(k lambda_mid), the fitted plane's offset and tilt
    uncertainty at the point's in-plane distance rho from the k neighbours' centroid ``mu``
    (lambda_mid their middle covariance eigenvalue); and ``share``: the number of accepted rows
    in the row's ``group_id`` (rows sharing their nearest map point count as one measurement).
    """
    n = points_lidar.shape[0]
    size = np.zeros(n_groups if share else 0, np.int64)
    m = 0
    for i in range(n):
        if accepted[i]:
            m += 1
            if share:
                size[group_id[i]] += 1
    w = np.empty(m)
    M = so3.mul(R, R_LI)
    tw = so3.mul_vec(R, t_LI) + p
    j = 0
    for i in range(n):
        if not accepted[i]:
            continue
        var = 1.0
        if plane_variance:
            wx, wy, wz = _world_point(points_lidar, i, M, tw)
            ox, oy, oz = wx - mu[i, 0], wy - mu[i, 1], wz - mu[i, 2]
            along = ox * normals[i, 0] + oy * normals[i, 1] + oz * normals[i, 2]
            rho2 = max(ox * ox + oy * oy + oz * oz - along * along, 0.0)
            k = float(max(counts[i], 1))
            var = 1.0 + 1.0 / k + rho2 / (k * max(lam_mid[i], 1e-12))
        if share:
            var *= size[group_id[i]]
        w[j] = 1.0 / np.sqrt(var)
        j += 1
    return w
