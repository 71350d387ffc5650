"""Iterated error-state Kalman update with the "small-H" gain (lio-design.md §6.4).

The measurement callback returns, at a state iterate, the stacked point-to-plane Jacobian rows
``H`` (m×12, error columns p, θ, θ_LI, t_LI) and residuals ``r`` (m,); the filter consumes
``h = −r`` with isotropic variance ``R = laser_point_cov`` (m²). 23×23 algebra in numpy.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from adalio.config import FilterConfig
from adalio.lio import so3
from adalio.lio.state import DIM, State

Measure = Callable[[State, bool], tuple[np.ndarray, np.ndarray]]
"""``measure(x, research) -> (H (m,12), r (m,))``; ``research`` asks for a new kNN + plane fit."""
NoiseTerms = Callable[[State], tuple[np.ndarray, np.ndarray]]
"""``noise_terms(x) -> (F (6,6), b (6,))``: what the fitted normals' noise fakes in the pose
block of the last evaluation's ``HᵀH`` and the bias it puts into ``Hᵀr``, both in ``HᵀH``'s units
(``measurement.normal_noise_terms``)."""

_SO3_BLOCKS = (slice(3, 6), slice(6, 9))


@dataclass
class UpdateResult:
    state: State
    P: np.ndarray
    iterations: int
    """Measurement evaluations performed (≤ max_iterations + 1)."""
    H: np.ndarray
    """(m,12) rows accepted at the last evaluation (after any pose projection)."""
    converged: bool
    lidar_normal: tuple[np.ndarray, np.ndarray] | None = None
    """(HᵀH, −Hᵀr) of the pose block at the last evaluation (6x6, 6), or None without rows."""
    lidar_from: State | None = None
    """The iterate the last evaluation was made at (:attr:`lidar_step` starts there)."""

    @property
    def lidar_step(self) -> np.ndarray | None:
        """(6,) [δp, δθ]: the LiDAR-only Gauss-Newton step from ``lidar_from``, ``(HᵀH)⁺ Hᵀr``
        of the pose block (no prior), on its well-conditioned eigen-directions; None without
        rows. Solved only when asked (the IMU time offset check)."""
        if self.lidar_normal is None:
            return None
        A, g = self.lidar_normal
        w, V = np.linalg.eigh(0.5 * (A + A.T))
        keep = w > 1e-6 * max(float(w[-1]), 1e-300)
        return V[:, keep] @ ((V[:, keep].T @ g) / w[keep])


def _reprojection(dx: np.ndarray) -> np.ndarray:
    """J of §6.4 step 2: identity with ``A(δθ)ᵀ = J_r(δθ)`` on the SO(3) blocks (S² block: I)."""
    J = np.eye(DIM)
    for sl in _SO3_BLOCKS:
        J[sl, sl] = so3.jr(dx[sl].copy())
    return J


def _claim_metric(claimed: np.ndarray, fake: np.ndarray, upper: float | None = None):
    """``(A^½, M, A^-½, μ, V)`` on the range of ``A = claimed`` (``A = U Λ Uᵀ``, ``A^½ = U
    Λ^½``, ``A^-½ = U Λ^-½``) with ``M = clip(I − A^-½ᵀ fake A^-½, 0, upper)``, the share of
    each whitened direction that is not ``fake``, and ``V diag(μ) Vᵀ`` that matrix before the
    clip (``μ ≤ 0``: a direction all fake); None when ``claimed`` holds nothing."""
    lam, U = np.linalg.eigh(0.5 * (claimed + claimed.T))
    keep = lam > lam.max(initial=0.0) * 1e-12
    if not np.any(keep):
        return None
    U, root = U[:, keep], np.sqrt(lam[keep])
    W = U / root  # columns: whitened directions
    mu, V = np.linalg.eigh(np.eye(root.size) - W.T @ fake @ W)
    mid = (V * np.clip(mu, 0.0, upper)) @ V.T
    return U * root, mid, W, mu, V


def real_information(claimed: np.ndarray, fake: np.ndarray) -> np.ndarray:
    """The part of an information matrix ``claimed`` (symmetric PSD) that is not ``fake``
    (PSD, the expected spurious part), kept between 0 and ``claimed``: in the metric of
    ``claimed`` (``A = U Λ Uᵀ``, whitening ``W = Λ^-½ Uᵀ`` on its range),
    ``A^½ max(I − W fake Wᵀ, 0) A^½``. Unlike clipping ``claimed − fake`` itself, this never
    grants information along a direction that ``claimed`` does not hold."""
    return real_information_and_height_blind(claimed, fake)[0]


def height_blind(claimed: np.ndarray, fake: np.ndarray,
                 up_world: np.ndarray | None = None) -> bool:
    """Whether the information ``claimed`` (6x6 pose block, [δp world, δθ]) holds its height
    (the position along ``up_world``, the world's unit up, against gravity; None: the world's
    z) mostly where ``fake`` says it is fake: in the generalized eigenbasis of
    ``(fake, claimed)`` (``fake v = m claimed v``, ``vᵀ claimed v = 1``) the claim's height
    entry ``eᵀ claimed e`` (``e = [up, 0]``) splits as ``Σ_k (eᵀ claimed v_k)²``; the directions
    with ``m_k >= 1`` are those :func:`real_information` drops. True when they hold more than
    half of it (or the claim holds no height at all)."""
    return real_information_and_height_blind(claimed, fake, up_world)[1]


def height_direction(up_world: np.ndarray | None) -> np.ndarray:
    """The pose-error direction ``[up, 0, 0, 0]`` (6,) of the height along the unit
    ``up_world`` (None: the world's z)."""
    e = np.zeros(6)
    e[:3] = (0.0, 0.0, 1.0) if up_world is None else up_world
    return e


def real_information_and_height_blind(claimed: np.ndarray, fake: np.ndarray,
                                      up_world: np.ndarray | None = None
                                      ) -> tuple[np.ndarray, bool]:
    """:func:`real_information` and :func:`height_blind` from one decomposition (the whitened
    directions ``V`` with ``μ = 1 − m``)."""
    parts = _claim_metric(claimed, fake)
    if parts is None:
        return np.zeros_like(claimed), True
    half, mid, _, mu, V = parts
    share = (height_direction(up_world) @ half @ V) ** 2
    total = float(share.sum())
    blind = not total > 0.0 or bool(share[mu <= 0.0].sum() > 0.5 * total)
    return half @ mid @ half.T, blind


def without_direction(J: np.ndarray, e: np.ndarray) -> np.ndarray:
    """The information ``J`` with the coordinate ``eᵀx`` marginalised out:
    ``J − J e eᵀ J / (eᵀ J e)`` (the Schur complement; it holds nothing along ``e`` and only
    what ``J`` says about the rest without knowing ``eᵀx``). ``J`` unchanged if it holds
    nothing along ``e``."""
    Je = J @ e
    d = float(e @ Je)
    if not d > 0.0:
        return J
    out = J - np.outer(Je, Je) / d
    return 0.5 * (out + out.T)


def errors_in_variables(HTH: np.ndarray, HTh: np.ndarray, F: np.ndarray,
                        b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The normal equations ``(HᵀH, −Hᵀr)`` with the pose block corrected for the noise of the
    fitted normals (``filter.errors_in_variables``).

    The gradient loses its expected bias, ``Hᵀr − b``, and the information keeps only what is
    not fake: ``A' = A^½ M A^½`` with ``M = clip(I − A^-½ F A^-½, 0, I)`` (``A`` the pose block,
    ``A^-½`` on its range; as :func:`real_information`), and the gradient is scaled by the
    same ``Q = A^½ M A^-½`` in every direction, so the LiDAR-only step of the corrected
    gradient, ``A⁻¹ (Hᵀr − b)``, is kept where any information is left and only its weight
    against the prior drops. Directions where ``F`` is all of ``A`` contribute nothing.

    With the extrinsic estimated (12 columns), the same correction reaches its columns: a
    row's extrinsic entries are a linear map of its pose entries, ``h_e = L h_p`` with
    ``L = [[−R_LIᵀ[t_LI]×Rᵀ, R_LIᵀ], [Rᵀ, 0]]`` (``measurement.point_to_plane``), so
    ``HᵀH = [I; L] A [I, Lᵀ]`` and ``Hᵀr = [I; L] Hᵀr_p``, and the corrected equations are
    ``[I; L] A' [I, Lᵀ]`` and ``[I; L] Q (Hᵀr_p − b)``. ``L`` is read from the equations
    themselves (``Lᵀ = A⁺ (HᵀH)_pe``). Correcting the pose block alone would leave the
    cross terms at their full size against a smaller pose block: an indefinite ``HᵀH``, whose
    update diverged by hundreds of metres.
    """
    HTH = HTH.copy()
    HTh = HTh.copy()
    A = 0.5 * (HTH[:6, :6] + HTH[:6, :6].T)
    parts = _claim_metric(A, 0.5 * (F + F.T), 1.0)
    if parts is None:
        return HTH, HTh
    half, mid, W, _, _ = parts
    Q = half @ mid @ W.T
    A_real = Q @ A
    A_real = 0.5 * (A_real + A_real.T)
    g_real = Q @ (HTh[:6] + b)  # HTh = −Hᵀr
    if HTH.shape[0] > 6 and np.any(HTH[:6, 6:]):
        Lt = np.linalg.pinv(A, rcond=1e-12, hermitian=True) @ HTH[:6, 6:]
        dA, dg = A_real - A, g_real - HTh[:6]
        HTH[:6, 6:] += dA @ Lt
        HTH[6:, :6] = HTH[:6, 6:].T
        HTH[6:, 6:] += Lt.T @ dA @ Lt
        HTh[6:] += Lt.T @ dg
    HTH[:6, :6] = A_real
    HTh[:6] = g_real
    return HTH, HTh


def iterated_update(x_prior: State, P_prior: np.ndarray, measure: Measure, cfg: FilterConfig,
                    pose_projector: np.ndarray | None = None,
                    noise_terms: NoiseTerms | None = None) -> UpdateResult:
    """IKFoM ``update_iterated_dyn_share_modified`` (§6.4).

    Loop ``j = −1 … N_max−1``: evaluate ``H, r`` at ``x_j`` (re-search while ``research``),
    ``δ̃ = J (x_j ⊟ x̂)``, ``P_j = J P̂ Jᵀ``, ``S = HᵀH/R + P_j⁻¹`` (HᵀH fills the 12×12 corner),
    ``K = S⁻¹ Hᵀ/R``, ``δ = K h + (K H − I) δ̃``, ``x_{j+1} = x_j ⊞ δ``. Converged when every
    ``|δ_i| ≤ ε``; forced before the last iteration; stop after two converged steps or N_max+1
    evaluations. ``P⁺ = (I − K H) P_j``.

    ``pose_projector`` (6×6, error order [δp, δθ]) restricts the update to observable pose
    directions (AdaLIO+, degeneracy.py §3): ``H_pose ← H_pose P_obs`` and the gain rows of the
    pose ``K ← M K`` with ``M = blockdiag(P_obs, I)``, so the pose stays at the prior along
    ``null(P_obs)`` while the other states take their optimal gain (a Schmidt–Kalman "consider"
    update). That gain is not the optimal one, so the covariance is the Joseph form, valid for
    any gain: ``P⁺ = (I − M K H) P_j (I − M K H)ᵀ + M K R Kᵀ Mᵀ``. The short form
    ``(I − K H) P_j`` would shrink the covariance along the held directions and their
    correlations as if the state had moved there.

    ``noise_terms`` (``filter.errors_in_variables``) corrects the normal equations of every
    iteration for the noise of the fitted normals (:func:`errors_in_variables`).
    """
    n_max = cfg.max_iterations
    inv_r = 1.0 / cfg.laser_point_cov
    x = x_prior.copy()
    research = True
    t_conv = 0
    converged = False
    iterations = 0
    P_out = P_prior
    H = np.zeros((0, 12))
    lidar_normal = None
    lidar_from = x
    M = None
    if pose_projector is not None:
        M = np.eye(DIM)
        M[:6, :6] = pose_projector
    for j in range(-1, n_max):
        H, r = measure(x, research or cfg.refit_every_iteration)
        iterations += 1
        if not cfg.estimate_extrinsic and H.shape[0]:
            H[:, 6:12] = 0.0
        if pose_projector is not None and H.shape[0]:
            H[:, :6] = H[:, :6] @ pose_projector
        dx = x.boxminus(x_prior)
        J = _reprojection(dx)
        P_j = J @ P_prior @ J.T
        dx_tilde = J @ dx
        KH = np.zeros((DIM, DIM))
        if H.shape[0] == 0:
            delta = np.zeros(DIM)
        else:
            HTH = H.T @ H
            HTh = -(H.T @ r)
            if noise_terms is not None:
                F, b = noise_terms(x)
                if pose_projector is not None:
                    F = pose_projector.T @ F @ pose_projector
                    b = pose_projector.T @ b
                HTH, HTh = errors_in_variables(HTH, HTh, F, b)
            lidar_normal, lidar_from = (HTH[:6, :6], HTh[:6]), x
            S = np.linalg.inv(P_j)
            S[:12, :12] += HTH * inv_r
            S_inv = np.linalg.inv(S)
            K_h = S_inv[:, :12] @ HTh * inv_r
            KH[:, :12] = S_inv[:, :12] @ HTH * inv_r
            if M is not None:
                K_h = M @ K_h
                KH = M @ KH
            delta = K_h + KH @ dx_tilde - dx_tilde
            if M is not None:  # δ̃ is in range(P_obs) only up to the SO(3) reprojection J
                delta[:6] = pose_projector @ delta[:6]
            if not cfg.estimate_extrinsic:
                delta[6:12] = 0.0
        x = x.boxplus(delta)
        converged = bool(np.all(np.abs(delta) <= cfg.convergence_eps))
        if converged:
            t_conv += 1
        if not t_conv and j == n_max - 2:
            converged = True
        research = converged
        if t_conv > 1 or j == n_max - 1:
            if M is None or H.shape[0] == 0:
                P_out = (np.eye(DIM) - KH) @ P_j
            else:
                A = np.eye(DIM) - KH
                KRK = S_inv[:, :12] @ HTH @ S_inv[:12, :] * inv_r
                P_out = A @ P_j @ A.T + M @ KRK @ M.T
            break
    P_out = 0.5 * (P_out + P_out.T)
    return UpdateResult(state=x, P=P_out, iterations=iterations, H=H, converged=t_conv > 0,
                        lidar_normal=lidar_normal, lidar_from=lidar_from)
