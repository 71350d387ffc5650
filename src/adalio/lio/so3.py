"""SO(3) and S² helpers for the error-state filter (lio-design.md §1-§2).

Conventions: right perturbation ``R ⊞ δθ = R·Exp(δθ)``, ``R_a ⊟ R_b = Log(R_bᵀ R_a)``; angles in
radians. Gravity lives on the sphere of radius ``|g|`` with a 2-D tangent basis ``B(g)`` anchored
at a fixed unit axis ``a`` (singular only at ``g = −|g|·a``; the filter picks ``a`` along the
gravity measured at initialization, so the singularity is never approached).
"""

from __future__ import annotations

import numpy as np

from adalio.jit import kernel

_SMALL = 1e-10


# Small dense products as plain loops. Numba's ``@`` calls BLAS: for 3x3 operands the call costs
# more than the arithmetic, and each layout combination is a separate, slow compilation. A
# transposed operand is passed as ``M.T``.
@kernel()
def mul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A B`` for small matrices, skipping the zeros of ``A`` (a sparse left factor, such as the
    filter's F, costs only its nonzeros)."""
    n, k = A.shape
    m = B.shape[1]
    out = np.zeros((n, m))
    for i in range(n):
        for j in range(k):
            a = A[i, j]
            if a != 0.0:
                for c in range(m):
                    out[i, c] += a * B[j, c]
    return out


@kernel()
def mul_vec(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``A x``."""
    n, k = A.shape
    out = np.zeros(n)
    for i in range(n):
        s = 0.0
        for j in range(k):
            s += A[i, j] * x[j]
        out[i] = s
    return out


@kernel()
def hat(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix ``[v]×``."""
    out = np.zeros((3, 3))
    out[0, 1] = -v[2]
    out[0, 2] = v[1]
    out[1, 0] = v[2]
    out[1, 2] = -v[0]
    out[2, 0] = -v[1]
    out[2, 1] = v[0]
    return out


@kernel()
def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` of two 3-vectors."""
    out = np.empty(3)
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


@kernel()
def exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues ``Exp(φ)``."""
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    K = hat(phi)
    if theta2 < _SMALL:
        return np.eye(3) + K + 0.5 * mul(K, K)
    theta = np.sqrt(theta2)
    return np.eye(3) + (np.sin(theta) / theta) * K + ((1.0 - np.cos(theta)) / theta2) * mul(K, K)


@kernel()
def log(R: np.ndarray) -> np.ndarray:
    """``Log(R)`` in (-π, π]."""
    cos_t = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    cos_t = min(1.0, max(-1.0, cos_t))
    w = np.empty(3)
    w[0] = R[2, 1] - R[1, 2]
    w[1] = R[0, 2] - R[2, 0]
    w[2] = R[1, 0] - R[0, 1]
    theta = np.arccos(cos_t)
    if theta < 1e-6:
        return 0.5 * w
    if np.pi - theta < 1e-4:
        B = 0.5 * (R + np.eye(3))
        k = 0
        for i in range(3):
            if B[i, i] > B[k, k]:
                k = i
        axis = B[:, k] / np.sqrt(max(B[k, k], 1e-300))
        if axis[0] * w[0] + axis[1] * w[1] + axis[2] * w[2] < 0.0:
            axis = -axis
        return theta * axis
    return (theta / (2.0 * np.sin(theta))) * w


@kernel()
def jr(phi: np.ndarray) -> np.ndarray:
    """Right Jacobian ``J_r(φ) = I − (1−cos θ)/θ² [φ]× + (θ−sin θ)/θ³ [φ]×²`` (§1)."""
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    K = hat(phi)
    if theta2 < _SMALL:
        return np.eye(3) - 0.5 * K + (1.0 / 6.0) * mul(K, K)
    theta = np.sqrt(theta2)
    return (np.eye(3) - ((1.0 - np.cos(theta)) / theta2) * K
            + ((theta - np.sin(theta)) / (theta2 * theta)) * mul(K, K))


@kernel()
def jr_inv(phi: np.ndarray) -> np.ndarray:
    """Inverse right Jacobian."""
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    K = hat(phi)
    if theta2 < _SMALL:
        return np.eye(3) + 0.5 * K + (1.0 / 12.0) * mul(K, K)
    theta = np.sqrt(theta2)
    c = 1.0 / theta2 - (1.0 + np.cos(theta)) / (2.0 * theta * np.sin(theta))
    return np.eye(3) + 0.5 * K + c * mul(K, K)


def exp_batch(phi: np.ndarray) -> np.ndarray:
    """Batched Rodrigues: (N,3) rotation vectors -> (N,3,3) matrices."""
    phi = np.asarray(phi, dtype=np.float64)
    theta2 = np.einsum("ij,ij->i", phi, phi)
    small = theta2 < _SMALL
    theta = np.sqrt(theta2)
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    x, y, z = phi[:, 0], phi[:, 1], phi[:, 2]
    out = np.empty((phi.shape[0], 3, 3))
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    out[:, 0, 0] = 1.0 - b * (yy + zz)
    out[:, 1, 1] = 1.0 - b * (xx + zz)
    out[:, 2, 2] = 1.0 - b * (xx + yy)
    out[:, 0, 1] = -a * z + b * xy
    out[:, 1, 0] = a * z + b * xy
    out[:, 0, 2] = a * y + b * xz
    out[:, 2, 0] = -a * y + b * xz
    out[:, 1, 2] = -a * x + b * yz
    out[:, 2, 1] = a * x + b * yz
    return out


def rotation_to_z(u: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the unit vector ``u`` to +z (Rodrigues: ``I + W + W²/(1 +
    c)`` with ``W = [u × z]×``, ``c = u·z``); ``diag(1, -1, -1)`` for ``u`` at -z, where no
    axis is the smallest."""
    u = np.asarray(u, dtype=np.float64)
    c = float(u[2])
    if c < -1.0 + 1e-9:
        return np.diag([1.0, -1.0, -1.0])
    W = hat(np.cross(u, [0.0, 0.0, 1.0]))
    return np.eye(3) + W + W @ W / (1.0 + c)


def anchor_frame(axis: np.ndarray) -> np.ndarray:
    """Orthonormal right-handed 3×3 frame whose first column is the unit ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    helper = np.eye(3)[int(np.argmin(np.abs(a)))]
    b1 = np.cross(a, helper)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(a, b1)
    return np.column_stack([a, b1, b2])


@kernel()
def s2_basis(g: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """Tangent basis ``B(g)`` (3×2, orthonormal, ⟂ g) of the gravity sphere (§2).

    ``B(g) = R_{a→u} [e1 e2]`` where ``(a, e1, e2) = anchor`` columns, ``u = g/|g|`` and
    ``R_{a→u} = I + [w]× + [w]×²/(1 + aᵀu)``, ``w = a × u``. With ``a = e_x`` this is IKFoM's basis.
    """
    u = g / np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    a = anchor[:, 0].copy()
    w = cross(a, u)
    W = hat(w)
    Rau = np.eye(3) + W + mul(W, W) / (1.0 + a[0] * u[0] + a[1] * u[1] + a[2] * u[2])
    return mul(Rau, anchor[:, 1:3])


@kernel()
def s2_boxplus(g: np.ndarray, delta: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """``g ⊞ δ = Exp(B(g) δ) g`` (§2)."""
    return mul_vec(exp(mul_vec(s2_basis(g, anchor), delta)), g)


@kernel()
def s2_boxminus(ga: np.ndarray, gb: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """``g_a ⊟ g_b = θ B(g_b)ᵀ u``, θ = ∠(g_b, g_a), u = unit(g_b × g_a) (§2)."""
    c = cross(gb, ga)
    sn = np.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2])
    cs = gb[0] * ga[0] + gb[1] * ga[1] + gb[2] * ga[2]
    B = s2_basis(gb, anchor)
    if sn < 1e-300:
        return np.zeros(2)
    theta = np.arctan2(sn, cs)
    return (theta / sn) * mul_vec(B.T, c)
