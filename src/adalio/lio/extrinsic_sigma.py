"""The LiDAR-IMU extrinsic's own uncertainty in the reported sigmas (``sensor.extrinsic_rotation_sigma_deg``, ``sensor.extrinsic_translation_sigma_m``).

The filter uses ``T_imu_lidar``'s rotation as exact. If it is off by a small rotation ``θ``
(IMU frame, ``R_used = Exp(θ) R_true``), the first scan is put into the world through it, so
the map is turned by ``φ = R₀ θ`` about the first pose (``R₀``: the IMU's attitude there), and
every later scan registers against that turned map: the LiDAR's poses follow it, and the
IMU's are the LiDAR's through the same rotation. So, against a truth aligned on the first
pose, a pose at ``p`` with attitude ``R`` is off by

    δp = φ × (p - p₀) = -[p - p₀]× R₀ θ,       δφ = φ - R θ = (R₀ - R) θ

(world frame; measured on the simulator's walks with 0.3° off: this explains the errors after
aligning the first pose to within 0.1-0.6 cm rms per axis in the hall and 0.5-2.4 cm in the
corridor, where they reach 7.6 and 27 cm and the sigmas without it held 8-33 % of the scans
along one axis; README, Outputs, *Uncertainty*). No update
sees it: the map moves with it. So the reported world covariance adds ``G M Gᵀ`` with
``G = [-[p - p₀]× R₀; R₀ - R]`` and ``M`` the second moment of ``θ``: the prior
``σ² I`` of ``sensor.extrinsic_rotation_sigma_deg``, or, once the rotation check has an
estimate ``e`` of covariance ``C`` (read as ``e / κ`` of covariance ``C / κ²``: it sees the
share ``κ = extrinsic_check.SEEN_SHARE`` of a rotation error), the posterior's ``V + m mᵀ`` with
``V = (I/σ² + C⁻¹)⁻¹``, ``m = V C⁻¹ e`` (the filter still uses ``θ = 0``, so its error is the
whole ``θ``, whose mean square given the estimate is the posterior's variance plus its mean
squared). Where the estimate contradicts the prior (a config that claims 0.1° for a rotation
1° off), the prior's variance is first widened to what makes the estimate most likely
(:func:`prior_scale`), so a wrong claim cannot shrink what the data show. The error is the
same for every scan (a systematic one), so it is added to the reported covariance only,
outside the map's provenance (``map_uncertainty``), which would count it again through every
map extension. The trajectory is unchanged.

The translation (the lever arm) alike: off by ``δ`` (IMU frame), the first scan's points are
shifted by ``R₀ δ``, the LiDAR's later positions follow that map, and the IMU's are the LiDAR's
less ``R δ``: ``δp = (R₀ - R) δ``, no attitude error (measured with 3 cm off in the hall: it
explains the errors to within 0.2-0.7 cm rms per axis). ``G = [R₀ - R; 0]``, ``M`` from
``sensor.extrinsic_translation_sigma_m`` and the lever arm check's estimate across the rig's
vertical (it holds no information along it).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

MAX_PRIOR_SCALE = 1e4
"""The prior's variance is widened at most this much (100 times its deviation) where the check's
estimate contradicts it (:func:`prior_scale`)."""


def _held(w: np.ndarray) -> np.ndarray:
    """The eigenvalues of an estimate's covariance that hold information: finite, and above
    rounding against the largest (a projected covariance, such as the lever arm check's across
    the vertical, keeps ~1e-20 along what it projected out: that is no information, not
    certainty)."""
    finite = np.isfinite(w)
    top = float(np.max(w[finite])) if finite.any() else 0.0
    return finite & (w > 1e-14 * top) & (w > 0.0)


def prior_scale(prior_var_rad2: float, estimate_rad: np.ndarray,
                estimate_cov_rad2: np.ndarray) -> float:
    """The factor ``s ≥ 1`` on the prior's variance that makes the check's estimate most likely
    (type-II maximum likelihood: ``e ~ N(0, s σ² I + C)``): 1 while the estimate is within what
    the prior allows, and about ``(|e|² - c²) / σ²`` along the estimate where it lies beyond (a
    rotation 1° off in a config that claims 0.1°: the configured deviation is contradicted by
    the data, so it is not allowed to shrink the estimate to a tenth). Directions the check
    holds no information about (a deviation that is not finite and positive) are left out."""
    w, U = np.linalg.eigh(0.5 * (estimate_cov_rad2 + estimate_cov_rad2.T))
    z2 = (U.T @ estimate_rad) ** 2
    seen = _held(w)
    w, z2 = w[seen], z2[seen]
    if not w.size or not np.all(np.isfinite(z2)):
        return 1.0

    def nll(log_s: float) -> float:
        v = np.exp(log_s) * prior_var_rad2 + w
        return float(np.sum(np.log(v) + z2 / v))

    res = minimize_scalar(nll, bounds=(0.0, np.log(MAX_PRIOR_SCALE)), method="bounded",
                          options={"xatol": 1e-4})
    best = float(res.x) if nll(float(res.x)) < nll(0.0) else 0.0
    return float(np.exp(best))


def posterior(prior_sigma_rad: float, estimate_rad: np.ndarray,
              estimate_cov_rad2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3,) mean ``m`` and (3,3) covariance ``V`` of the extrinsic's rotation error (rad; or of
    its translation error, m, with the arguments in metres) given an estimate ``estimate_rad``
    of covariance ``estimate_cov_rad2`` and the prior ``N(0, σ² I)``, its variance widened by
    :func:`prior_scale` where the estimate contradicts it: ``V = (I/σ² + C⁻¹)⁻¹``,
    ``m = V C⁻¹ e``. Directions whose deviation is not finite and positive hold no information
    (``m`` is 0 and ``V`` the prior's there). ``σ`` must be positive."""
    C = np.asarray(estimate_cov_rad2, dtype=np.float64)
    e = np.asarray(estimate_rad, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(C)) and np.all(np.isfinite(e))):
        return np.zeros(3), np.eye(3) * prior_sigma_rad**2
    w, U = np.linalg.eigh(0.5 * (C + C.T))
    held = _held(w)
    info = (U[:, held] / w[held]) @ U[:, held].T
    prior_var = prior_sigma_rad**2 * prior_scale(prior_sigma_rad**2, e, C)
    lam, Q = np.linalg.eigh(np.eye(3) / prior_var + 0.5 * (info + info.T))
    V = (Q / lam) @ Q.T  # positive definite: the prior's term is
    return V @ info @ e, 0.5 * (V + V.T)


def error_second_moment(prior_sigma_rad: float, estimate_rad: np.ndarray | None = None,
                        estimate_cov_rad2: np.ndarray | None = None) -> np.ndarray:
    """(3,3) ``E[θ θᵀ]`` of the extrinsic's rotation error (rad²; or of its translation error,
    m², with the arguments in metres): ``σ² I`` with no estimate,
    else the posterior's ``V + m mᵀ`` given the check's estimate ``estimate_rad`` of covariance
    ``estimate_cov_rad2`` (module doc; :func:`posterior`), the prior widened by
    :func:`prior_scale` where the estimate contradicts it. Directions whose deviation is not
    finite and positive hold no information. Zero when the prior is zero (the value taken as
    exact)."""
    if not prior_sigma_rad > 0:
        return np.zeros((3, 3))
    if estimate_rad is None or estimate_cov_rad2 is None:
        return np.eye(3) * prior_sigma_rad**2
    m, V = posterior(prior_sigma_rad, estimate_rad, estimate_cov_rad2)
    M = V + np.outer(m, m)
    return 0.5 * (M + M.T)


def _sandwich(G: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``G M Gᵀ``, symmetrized, for ``G`` (..., 6, 3): one per pose."""
    W = G @ np.asarray(M, dtype=np.float64) @ np.swapaxes(G, -1, -2)
    return 0.5 * (W + np.swapaxes(W, -1, -2))


def extrinsic_rotation_covariance(M_rad2: np.ndarray, R_anchor: np.ndarray, R: np.ndarray,
                                  d_m: np.ndarray) -> np.ndarray:
    """(6,6) world covariance (position, small world rotation) that a rotation error of second
    moment ``M_rad2`` (IMU frame) puts into a pose of attitude ``R`` at ``d_m`` from the first
    pose, whose attitude is ``R_anchor``: ``G M Gᵀ``, ``G = [-[d]× R_anchor; R_anchor - R]``
    (module doc). ``R`` (..., 3, 3) and ``d_m`` (..., 3) may hold many poses (the same leading
    dimensions): (..., 6, 6)."""
    d = np.asarray(d_m, dtype=np.float64)
    skew = np.zeros(d.shape + (3,))
    skew[..., 0, 1], skew[..., 0, 2], skew[..., 1, 2] = -d[..., 2], d[..., 1], -d[..., 0]
    skew -= np.swapaxes(skew, -1, -2)
    turn = R_anchor - np.asarray(R, dtype=np.float64)
    return _sandwich(np.concatenate([-skew @ R_anchor, turn], axis=-2), M_rad2)


def extrinsic_translation_covariance(M_m2: np.ndarray, R_anchor: np.ndarray,
                                     R: np.ndarray) -> np.ndarray:
    """(6,6) world covariance (position, small world rotation) that a translation error of
    second moment ``M_m2`` (IMU frame) puts into a pose of attitude ``R``, the first pose's
    being ``R_anchor``: ``G M Gᵀ``, ``G = [R_anchor - R; 0]`` (module doc). ``R`` (..., 3, 3)
    may hold many poses: (..., 6, 6)."""
    turn = R_anchor - np.asarray(R, dtype=np.float64)
    return _sandwich(np.concatenate([turn, np.zeros_like(turn)], axis=-2), M_m2)


__all__ = ["error_second_moment", "extrinsic_rotation_covariance",
           "extrinsic_translation_covariance", "posterior", "prior_scale"]
