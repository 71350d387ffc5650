"""Point-to-plane measurement model: residual, range-adaptive gate and H rows (lio-design.md §6.3).

Inputs are undistorted, downsampled LiDAR-frame points ``p_L`` (m) and world planes
``nᵀx + d = 0`` (``|n| = 1``). World point ``p_W = R (R_LI p_L + t_LI) + p``.
"""

from __future__ import annotations

import numpy as np

from adalio.jit import kernel
from adalio.lio import so3
from adalio.lio.plane import _scatter

GATE_FACTOR = 81.0
"""Accept a residual iff ``|p_L| > 81 r²`` (FAST-LIO2's ``s > 0.9`` test, §6.3)."""

MAD_TO_SIGMA = 1.4826
"""A Gaussian's standard deviation per median absolute deviation."""

KERNEL_WIDTH = {"huber": 1.345, "geman_mcclure": 3.0}
"""Each kernel's usual width in units of the residual's sigma (``filter.robust_scale: 0``):
Huber's 1.345 keeps 95 % of least squares' efficiency on Gaussian noise; Geman-McClure's
3 sigma leaves a Gaussian's rows nearly whole and silences rows far beyond it."""


def robust_row_factors(r: np.ndarray, H_pose: np.ndarray, P_pose: np.ndarray | None,
                       kernel_name: str, scale: float) -> np.ndarray:
    """Square roots of the IRLS weights of residuals ``r`` (m,) with pose rows ``H_pose`` (m,6),
    both already scaled by the rows' own weights (the factors multiply rows of ``H`` and ``r``).

    Each row's kernel width is ``scale`` times the spread the residual has if the row is right:
    ``κ_i² = scale² (σ̂² + h_i P h_iᵀ)``, with ``σ̂ = 1.4826 median|r|`` the scan's own residual
    noise (a robust estimate: the sensor's noise is never configured) and ``h_i P h_iᵀ`` what the
    prediction's pose covariance ``P_pose`` (error order [δp, δθ]) adds; so a row that corrects
    an error the filter knows it may have is not taken for an outlier. ``P_pose=None``: no such
    term. Weights: ``huber`` ``min(1, κ/|r|)`` (convex: a constant pull beyond κ),
    ``geman_mcclure`` ``(κ²/(κ²+r²))²`` (redescending: a row far off its plane stops pulling),
    ``none`` 1. ``scale`` 0: the kernel's usual width (:data:`KERNEL_WIDTH`).
    """
    m = r.shape[0]
    if kernel_name == "none" or m == 0:
        return np.ones(m)
    scale = scale if scale > 0 else KERNEL_WIDTH[kernel_name]
    sigma = MAD_TO_SIGMA * float(np.median(np.abs(r)))
    k2 = np.full(m, sigma * sigma)
    if P_pose is not None:
        k2 += pose_quadratic(H_pose, P_pose)
    k2 = scale * scale * np.maximum(k2, 1e-18)
    r2 = r * r
    if kernel_name == "geman_mcclure":
        return k2 / (k2 + r2)
    if kernel_name == "huber":
        return np.sqrt(np.minimum(1.0, np.sqrt(k2 / np.maximum(r2, 1e-36))))
    raise ValueError(f"unknown robust kernel {kernel_name!r}")


@kernel()
def pose_quadratic(H_pose, P_pose):
    """``h_i P h_iᵀ`` of every row ``h_i`` of ``H_pose`` (m,6): numpy's
    ``einsum("ij,jk,ik->i", H, P, H)`` bit for bit (one running sum, j outer, k inner), without
    its generic three-operand loop."""
    m = H_pose.shape[0]
    out = np.empty(m)
    for i in range(m):
        s = 0.0
        for j in range(6):
            for k in range(6):
                s += (H_pose[i, j] * P_pose[j, k]) * H_pose[i, k]
        out[i] = s
    return out


@kernel()
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
def _body_and_normal(points_lidar, i, R, R_LI, t_LI, normals):
    """``p_I = R_LI p_L + t_LI`` and ``c = Rᵀ n`` of row i (the body-frame point and normal)."""
    nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
    lx, ly, lz = points_lidar[i, 0], points_lidar[i, 1], points_lidar[i, 2]
    return (R_LI[0, 0] * lx + R_LI[0, 1] * ly + R_LI[0, 2] * lz + t_LI[0],
            R_LI[1, 0] * lx + R_LI[1, 1] * ly + R_LI[1, 2] * lz + t_LI[1],
            R_LI[2, 0] * lx + R_LI[2, 1] * ly + R_LI[2, 2] * lz + t_LI[2],
            R[0, 0] * nx + R[1, 0] * ny + R[2, 0] * nz,
            R[0, 1] * nx + R[1, 1] * ny + R[2, 1] * nz,
            R[0, 2] * nx + R[1, 2] * ny + R[2, 2] * nz)


@kernel()
def _pose_row_variance(points_lidar, i, R, R_LI, t_LI, normals, P_pose):
    """``h P_pose hᵀ``: the variance the pose covariance ``P_pose`` ([δp, δθ]) gives row i's
    residual, with ``h = [nᵀ, ([p_I]× c)ᵀ]`` its pose columns."""
    ix, iy, iz, cx, cy, cz = _body_and_normal(points_lidar, i, R, R_LI, t_LI, normals)
    h = (normals[i, 0], normals[i, 1], normals[i, 2],
         iy * cz - iz * cy, iz * cx - ix * cz, ix * cy - iy * cx)
    v = 0.0
    for a in range(6):
        for b in range(6):
            v += h[a] * P_pose[a, b] * h[b]
    return v


@kernel()
def point_to_plane(points_lidar, R, p, R_LI, t_LI, normals, d, selected, estimate_extrinsic,
                   P_pose, gate_sigmas):
    """Residuals and Jacobian rows of the accepted points (§6.3), all points in one call.

    For each point with ``selected[i]``: ``r = nᵀ p_W + d``; accepted iff ``|p_L| > 81 r²``
    (FAST-LIO2's range gate) or ``r² ≤ gate_sigmas² h P_pose hᵀ`` (the residual lies within
    ``gate_sigmas`` standard deviations of what the predicted pose's covariance ``P_pose``
    (6×6, [δp, δθ]) allows: after seconds without a scan the prediction may be decimetres off,
    beyond the range gate, and the rows that would correct it must not be the ones rejected;
    ``gate_sigmas`` 0: the range gate alone).
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
        ok = np.sqrt(x * x + y * y + z * z) > GATE_FACTOR * r * r
        if not ok and gate_sigmas > 0.0:
            ok = r * r <= gate_sigmas * gate_sigmas * _pose_row_variance(
                points_lidar, i, R, R_LI, t_LI, normals, P_pose)
        if ok:
            accepted[i] = True
            res[i] = r
            m += 1
    H = np.zeros((m, 12))
    r_out = np.empty(m)
    j = 0
    for i in range(n):
        if not accepted[i]:
            continue
        ix, iy, iz, cx, cy, cz = _body_and_normal(points_lidar, i, R, R_LI, t_LI, normals)
        H[j, 0] = normals[i, 0]
        H[j, 1] = normals[i, 1]
        H[j, 2] = normals[i, 2]
        H[j, 3] = iy * cz - iz * cy
        H[j, 4] = iz * cx - ix * cz
        H[j, 5] = ix * cy - iy * cx
        if estimate_extrinsic:
            lx, ly, lz = points_lidar[i, 0], points_lidar[i, 1], points_lidar[i, 2]
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


@kernel()
def normal_noise_information(points_lidar, accepted, R, R_LI, t_LI, normals, neighbours, counts,
                             w):
    """The part of the accepted rows' ``HᵀH`` (pose columns [δp, δθ]) that the noise of the
    fitted plane normals fakes, divided by the point noise σ² (errors in variables).

    A row's Jacobian is ``h = B n`` with ``B = [I; [p_I]× Rᵀ]`` and the *fitted* normal ``n``.
    Fitted to k neighbours with point noise σ², the normal tilts towards each in-plane principal
    direction ``e_j`` of the neighbours (spread variance ``λ_j``) with variance ``σ²/(k λ_j)``:
    ``Cov(n) = σ² N``, ``N = (P S P)⁺ / k`` (``S`` the neighbours' covariance, ``P = I − n nᵀ``).
    So ``E[h hᵀ] = h̄ h̄ᵀ + σ² B N Bᵀ``: the rows claim ``Σ w² B N Bᵀ`` (over σ²) of
    information that the surface does not hold, e.g. height from walls whose fitted normals
    lean by noise. Returns ``Σ w² B N Bᵀ`` (times σ² it is comparable with ``HᵀH``); ``w`` are the rows' weights (:func:`residual_weights`, 1
    without), rows in point order. A row whose neighbours span no plane (``P S P`` singular)
    claims nothing real: its whole ``w² h hᵀ`` is returned.
    """
    F, _ = normal_noise_terms(points_lidar, accepted, R, np.zeros(3), R_LI, t_LI, normals,
                              np.empty((0, 3)), neighbours, counts, w, 1.0, np.bool_(False))
    return F


@kernel()
def normal_noise_terms(points_lidar, accepted, R, p, R_LI, t_LI, normals, mu, neighbours, counts,
                       w, sigma2, empirical):
    """``(F, b)``: what the noise of the fitted normals fakes in the accepted rows' ``HᵀH``
    (``F``, 6×6, pose columns [δp, δθ]) and the bias it puts into their ``Hᵀr`` (``b``, 6).

    ``F = Σ w² σ_i² B N Bᵀ`` as :func:`normal_noise_information` (which is ``F`` with
    ``σ_i² = 1``). The residual ``r = n̂ᵀ(p_W − μ)`` of the same fitted normal carries the same
    tilt: ``r = r̄ + δnᵀ ℓ`` with ``ℓ = p_W − μ`` the point's lever arm from the neighbours'
    centroid ``mu``, so ``E[h r] = h̄ r̄ + B E[δn δnᵀ] ℓ`` and ``b = Σ w² σ_i² B N ℓ`` (errors in
    variables; the corrected score of Fuller's estimator). It is the pull of a plane fitted to a
    thin strip of map points on a query beyond it: towards the strip (e.g. walls holding a moving
    scan at the height of the ring lines the map was made of). Without ``mu`` rows
    (``mu.shape[0] == 0``) ``b`` is zero.

    ``σ_i²``, the point noise along the normal: ``sigma2``, or with ``empirical`` the
    neighbours' own scatter about their plane, ``k nᵀ S n / (k − 3)`` (unbiased for k > 3
    points and a plane's 3 parameters; ``sigma2`` for k = 3). A row whose neighbours span no
    plane adds its whole ``w² h hᵀ`` to ``F`` (times ``sigma2`` unless ``empirical``) and nothing
    to ``b``.
    """
    N, plane = normal_noise_matrices(accepted, normals, neighbours, counts, sigma2, empirical)
    return normal_noise_sums(points_lidar, accepted, R, p, R_LI, t_LI, mu, N, plane, w)


@kernel()
def normal_noise_matrices(rows, normals, neighbours, counts, sigma2, empirical):
    """``(N, plane)`` of :func:`normal_noise_terms` for each scan point with ``rows[i]``: ``N[i]``
    the covariance of its fitted normal times ``σ_i²`` (3×3, world axes; ``n nᵀ σ_i²`` where the
    neighbours span no plane) and ``plane[i]`` whether they span one. They depend only on the
    search's neighbours and normals, not on the pose: the filter's iterations between two
    searches reuse them (:func:`normal_noise_sums`). Points without ``rows[i]``: zeros."""
    n_pts = normals.shape[0]
    out = np.zeros((n_pts, 3, 3))
    plane = np.zeros(n_pts, np.bool_)
    S = np.zeros((3, 3))
    A = np.zeros((3, 3))
    for i in range(n_pts):
        if not rows[i]:
            continue
        N = out[i]
        c = counts[i]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        nv = (nx, ny, nz)
        _scatter(neighbours[i], c, S)  # the neighbours' scatter about their centroid
        S /= c
        # A = P S P + n nᵀ with P = I − n nᵀ: S − n(nᵀS) − (S n)nᵀ + n (nᵀ S n) nᵀ + n nᵀ;
        # (P S P)⁺ = A⁻¹ − n nᵀ
        Sn0 = S[0, 0] * nx + S[0, 1] * ny + S[0, 2] * nz
        Sn1 = S[1, 0] * nx + S[1, 1] * ny + S[1, 2] * nz
        Sn2 = S[2, 0] * nx + S[2, 1] * ny + S[2, 2] * nz
        Sn = (Sn0, Sn1, Sn2)
        nSn = nx * Sn0 + ny * Sn1 + nz * Sn2
        for a in range(3):
            for b in range(3):
                A[a, b] = (S[a, b] - nv[a] * Sn[b] - Sn[a] * nv[b] + nv[a] * nSn * nv[b]
                           + nv[a] * nv[b])
        det = (A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
               - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
               + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]))
        if det > 1e-300 and np.isfinite(det):
            inv_det = 1.0 / det
            N[0, 0] = (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]) * inv_det
            N[0, 1] = (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) * inv_det
            N[0, 2] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) * inv_det
            N[1, 0] = (A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]) * inv_det
            N[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) * inv_det
            N[1, 2] = (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) * inv_det
            N[2, 0] = (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]) * inv_det
            N[2, 1] = (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) * inv_det
            N[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) * inv_det
            s2 = nSn * c / (c - 3.0) if empirical and c > 3 else sigma2
            for a in range(3):
                for b in range(3):
                    N[a, b] = (N[a, b] - nv[a] * nv[b]) / c * s2
            plane[i] = True
        else:  # no plane: the whole row's information is fake (B n nᵀ Bᵀ = h hᵀ)
            s2 = 1.0 if empirical else sigma2
            for a in range(3):
                for b in range(3):
                    N[a, b] = nv[a] * nv[b] * s2
    return out, plane


@kernel()
def normal_noise_sums(points_lidar, accepted, R, p, R_LI, t_LI, mu, N_rows, plane, w):
    """``(F, b)`` of :func:`normal_noise_terms` at the pose ``(R, p)`` from the rows' normal
    covariances ``N_rows`` and ``plane`` (:func:`normal_noise_matrices`, computed for at least
    the ``accepted`` points); ``w`` the accepted rows' weights in point order."""
    # With q = R p_I (the lever arm in world axes), [p_I]× Rᵀ = Rᵀ [q]×, so B N Bᵀ is
    # [[N, −N [q]× R], [Rᵀ [q]× N, −Rᵀ [q]× N [q]× R]]: the world-frame sums
    # X = Σ w² N, Y = Σ w² N [q]×, Z = Σ w² [q]× N [q]× are rotated once at the end; so is
    # the bias, B v = [v; Rᵀ (q × v)] with v = N ℓ.
    X = np.zeros((3, 3))
    bp = np.zeros(3)
    bq = np.zeros(3)
    with_bias = mu.shape[0] > 0
    Y = np.zeros((3, 3))
    Z = np.zeros((3, 3))
    NQ = np.zeros((3, 3))
    n_pts = points_lidar.shape[0]
    j = 0
    for i in range(n_pts):
        if not accepted[i]:
            continue
        N = N_rows[i]
        # q = R (R_LI l + t_LI)
        lx, ly, lz = points_lidar[i, 0], points_lidar[i, 1], points_lidar[i, 2]
        ix = R_LI[0, 0] * lx + R_LI[0, 1] * ly + R_LI[0, 2] * lz + t_LI[0]
        iy = R_LI[1, 0] * lx + R_LI[1, 1] * ly + R_LI[1, 2] * lz + t_LI[1]
        iz = R_LI[2, 0] * lx + R_LI[2, 1] * ly + R_LI[2, 2] * lz + t_LI[2]
        qx = R[0, 0] * ix + R[0, 1] * iy + R[0, 2] * iz
        qy = R[1, 0] * ix + R[1, 1] * iy + R[1, 2] * iz
        qz = R[2, 0] * ix + R[2, 1] * iy + R[2, 2] * iz
        ww = w[j] * w[j]
        j += 1
        if with_bias and plane[i]:  # v = N ℓ, ℓ = q + p − μ (the lever arm from the centroid)
            arm_x = qx + p[0] - mu[i, 0]
            arm_y = qy + p[1] - mu[i, 1]
            arm_z = qz + p[2] - mu[i, 2]
            v0 = N[0, 0] * arm_x + N[0, 1] * arm_y + N[0, 2] * arm_z
            v1 = N[1, 0] * arm_x + N[1, 1] * arm_y + N[1, 2] * arm_z
            v2 = N[2, 0] * arm_x + N[2, 1] * arm_y + N[2, 2] * arm_z
            bp[0] += ww * v0
            bp[1] += ww * v1
            bp[2] += ww * v2
            bq[0] += ww * (qy * v2 - qz * v1)
            bq[1] += ww * (qz * v0 - qx * v2)
            bq[2] += ww * (qx * v1 - qy * v0)
        # NQ = N [q]×, column by column ([q]× columns: (0, qz, −qy), (−qz, 0, qx), (qy, −qx, 0))
        for a in range(3):
            NQ[a, 0] = N[a, 1] * qz - N[a, 2] * qy
            NQ[a, 1] = N[a, 2] * qx - N[a, 0] * qz
            NQ[a, 2] = N[a, 0] * qy - N[a, 1] * qx
        for a in range(3):
            for b in range(3):
                X[a, b] += ww * N[a, b]
                Y[a, b] += ww * NQ[a, b]
        # Z += [q]× NQ, rows of [q]×: (0, −qz, qy), (qz, 0, −qx), (−qy, qx, 0)
        for b in range(3):
            Z[0, b] += ww * (qy * NQ[2, b] - qz * NQ[1, b])
            Z[1, b] += ww * (qz * NQ[0, b] - qx * NQ[2, b])
            Z[2, b] += ww * (qx * NQ[1, b] - qy * NQ[0, b])
    out = np.zeros((6, 6))
    for a in range(3):
        for b in range(3):
            out[a, b] = 0.5 * (X[a, b] + X[b, a])
            t = 0.0  # −(Y R)[a, b]
            for e in range(3):
                t -= Y[a, e] * R[e, b]
            out[a, 3 + b] = t
            out[3 + b, a] = t
    for a in range(3):
        for b in range(a, 3):
            t = 0.0  # −(Rᵀ Z R)[a, b]
            for e in range(3):
                for f in range(3):
                    t -= R[e, a] * Z[e, f] * R[f, b]
            out[3 + a, 3 + b] = t
            out[3 + b, 3 + a] = t
    bias = np.zeros(6)
    for a in range(3):
        bias[a] = bp[a]
        bias[3 + a] = R[0, a] * bq[0] + R[1, a] * bq[1] + R[2, a] * bq[2]  # Rᵀ bq
    return out, bias
