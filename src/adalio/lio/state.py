"""Filter state on the manifold and its 23-dof error state (lio-design.md §2).

Frames: ``W`` world, ``I`` IMU/body, ``L`` LiDAR. ``R``/``p`` = pose of I in W, ``R_LI``/``t_LI``
map LiDAR points into the IMU frame (``p_I = R_LI p_L + t_LI``), ``v`` world velocity (m/s),
``b_g`` (rad/s), ``b_a`` (m/s²), ``g`` world gravity (m/s², fixed norm, on S²).

Error-state order (IKFoM / Faster-LIO): p 0–2, θ 3–5, θ_LI 6–8, t_LI 9–11, v 12–14, b_g 15–17,
b_a 18–20, g 21–22.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from adalio.lio import so3

DIM = 23
P_ = slice(0, 3)
TH = slice(3, 6)
TH_LI = slice(6, 9)
T_LI = slice(9, 12)
V = slice(12, 15)
BG = slice(15, 18)
BA = slice(18, 21)
G = slice(21, 23)


@dataclass
class State:
    """The manifold state; ``g_anchor`` is the fixed frame of the S² tangent basis."""

    p: np.ndarray = field(default_factory=lambda: np.zeros(3))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    R_LI: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_LI: np.ndarray = field(default_factory=lambda: np.zeros(3))
    v: np.ndarray = field(default_factory=lambda: np.zeros(3))
    b_g: np.ndarray = field(default_factory=lambda: np.zeros(3))
    b_a: np.ndarray = field(default_factory=lambda: np.zeros(3))
    g: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    g_anchor: np.ndarray = field(default_factory=lambda: so3.anchor_frame([0.0, 0.0, -1.0]))

    def lidar_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """``(R_WL, p_WL)``: the LiDAR frame's rotation and origin in the world."""
        return self.R @ self.R_LI, self.R @ self.t_LI + self.p

    def copy(self) -> State:
        return State(self.p.copy(), self.R.copy(), self.R_LI.copy(), self.t_LI.copy(),
                     self.v.copy(), self.b_g.copy(), self.b_a.copy(), self.g.copy(),
                     self.g_anchor)

    def boxplus(self, delta: np.ndarray) -> State:
        """``x ⊞ δ`` for a (23,) error-state vector."""
        d = np.asarray(delta, dtype=np.float64)
        return State(
            p=self.p + d[P_],
            R=self.R @ so3.exp(d[TH].copy()),
            R_LI=self.R_LI @ so3.exp(d[TH_LI].copy()),
            t_LI=self.t_LI + d[T_LI],
            v=self.v + d[V],
            b_g=self.b_g + d[BG],
            b_a=self.b_a + d[BA],
            g=so3.s2_boxplus(self.g, d[G].copy(), self.g_anchor),
            g_anchor=self.g_anchor,
        )

    def boxminus(self, other: State) -> np.ndarray:
        """``self ⊟ other`` as a (23,) vector."""
        out = np.empty(DIM)
        out[P_] = self.p - other.p
        out[TH] = so3.log(other.R.T @ self.R)
        out[TH_LI] = so3.log(other.R_LI.T @ self.R_LI)
        out[T_LI] = self.t_LI - other.t_LI
        out[V] = self.v - other.v
        out[BG] = self.b_g - other.b_g
        out[BA] = self.b_a - other.b_a
        out[G] = so3.s2_boxminus(self.g, other.g, self.g_anchor)
        return out

    def T_world_imu(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.p
        return T


def initial_covariance(estimate_extrinsic: bool) -> np.ndarray:
    """P₀ (§4): identity except extrinsic 1e-5 (1e-10 if not estimated), b_g 1e-4, b_a 1e-3, g 1e-5."""
    P = np.eye(DIM)
    ext = 1e-5 if estimate_extrinsic else 1e-10
    for sl, val in ((TH_LI, ext), (T_LI, ext), (BG, 1e-4), (BA, 1e-3), (G, 1e-5)):
        idx = np.arange(sl.start, sl.stop)
        P[idx, idx] = val
    return P


def condition_on_rest(P: np.ndarray, state: State, gyro_mean_var: float,
                      accel_mean_var: float) -> np.ndarray:
    """P conditioned on what a still window measured (adalio's rule, lio-design.md §4).

    At rest the mean gyro reading is ``b_g`` and the mean specific force is ``-Rᵀg + b_a``, each
    known to the variance of its window mean. The static initialization already put the state
    there (zero residual), so only the covariance changes: a Kalman update with
    ``H = [I on b_g]`` and ``H = [I on b_a, Rᵀ[g]× B(g) on g]``. The attitude is left out, since
    the world frame is defined by the IMU at that instant. What this adds to P is the
    correlation: a horizontal accelerometer bias and a gravity tilt are inseparable at rest, but
    their sum is known to millimetres per second squared. Without it the filter may take a
    LiDAR pull along a weak direction (a corridor's axis) as a bias plus a tilt and integrate
    the error at the sum's prior spread (about 0.04 m/s² here)."""
    B = so3.s2_basis(state.g, state.g_anchor)
    H = np.zeros((6, DIM))
    H[0:3, BG] = np.eye(3)
    H[3:6, BA] = np.eye(3)
    H[3:6, G] = state.R.T @ so3.hat(state.g) @ B
    Rn = np.diag([gyro_mean_var] * 3 + [accel_mean_var] * 3)
    return joseph_update(P, H, Rn)[1]


def joseph_update(P: np.ndarray, H: np.ndarray,
                  Rn: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """(Kalman gain, posterior covariance) of a linear measurement ``H`` with noise ``Rn`` on the
    error state (an (m, m) matrix, or a variance ``σ²`` for ``σ² I``), the posterior in Joseph
    form ``(I − KH) P (I − KH)ᵀ + K Rn Kᵀ`` and symmetrized, so it stays symmetric positive
    definite."""
    iso = np.ndim(Rn) == 0
    S = H @ P @ H.T + (Rn * np.eye(H.shape[0]) if iso else Rn)
    K = np.linalg.solve(S, H @ P).T
    A = np.eye(P.shape[0]) - K @ H
    out = A @ P @ A.T + (Rn * (K @ K.T) if iso else K @ Rn @ K.T)
    return K, 0.5 * (out + out.T)


def rest_velocity_update(P: np.ndarray, v: np.ndarray, var_v: float, gate: float,
                         P_gate: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """A zero-velocity measurement (``H = [I on v]``, noise ``var_v`` per axis) on the error
    state: (error-state correction, posterior covariance, normalised innovation squared), or
    None where the innovation's squared Mahalanobis length exceeds ``gate`` (the filter's
    velocity refutes rest), that length taken with ``P_gate``'s velocity block if given (the
    discounted covariance) and ``P``'s otherwise."""
    innov = -np.asarray(v, dtype=np.float64)
    Pg = P if P_gate is None else P_gate
    nis = float(innov @ np.linalg.solve(Pg[V, V] + var_v * np.eye(3), innov))
    if not nis <= gate:
        return None
    K, P_post = joseph_update(P, _velocity_rows(P.shape[0]), var_v)
    return K @ innov, P_post, nis


def rest_velocity_covariance(P: np.ndarray, var_v: float) -> np.ndarray:
    """``P`` after the same zero-velocity measurement (covariance only)."""
    return joseph_update(P, _velocity_rows(P.shape[0]), var_v)[1]


def _velocity_rows(dim: int) -> np.ndarray:
    """``H = [I on v]`` (3, dim) of the error state."""
    H = np.zeros((3, dim))
    H[:, V] = np.eye(3)
    return H


def pose_covariance_world(R_world_imu: np.ndarray, P: np.ndarray) -> np.ndarray:
    """6x6 covariance of (world position, small rotation about the world axes) from the
    error-state covariance ``P``. The position error is already world-frame; ``R ⊞ δθ =
    R Exp(δθ)`` puts δθ in the body frame, and the same rotation seen in the world frame is
    ``R δθ``: ``W = G P_pose Gᵀ`` with ``G = diag(I, R)``."""
    G = np.zeros((6, 6))
    G[:3, :3] = np.eye(3)
    G[3:, 3:] = R_world_imu
    idx = np.r_[np.arange(P_.start, P_.stop), np.arange(TH.start, TH.stop)]
    return G @ P[np.ix_(idx, idx)] @ G.T


def anchored_covariance(R_world_imu: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``P`` at the pose that anchors the map and so defines the world frame: that pose's
    position and its rotation about the world vertical (yaw) have no error by definition, so
    those components, and their correlations with the rest of the state, are removed
    (``M P Mᵀ`` with ``M`` zero on the position and ``I − Rᵀ e_z e_zᵀ R`` on the body-frame
    attitude error, whose world-frame rotation is ``R δθ``). Roll, pitch, velocity and biases
    keep their uncertainty: gravity, not the map, defines the first two."""
    M = np.eye(P.shape[0])
    M[P_, P_] = 0.0
    u = np.asarray(R_world_imu, dtype=np.float64).T[:, 2]  # Rᵀ e_z: world z in the body frame
    M[TH, TH] = np.eye(3) - np.outer(u, u)
    out = M @ P @ M.T
    return 0.5 * (out + out.T)


def sigmas_from_world_covariance(W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position sigmas in m, rotation sigmas about world x, y, z in degrees) of a 6x6 W."""
    sig = np.sqrt(np.clip(np.diag(W), 0.0, None))
    return sig[:3], np.degrees(sig[3:])


def world_sigmas(R_world_imu: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-frame standard deviations of the pose from the error-state covariance ``P``:
    ``sqrt(diag(P_pp))`` in metres and, in degrees, those of ``R P_θθ Rᵀ``, a small rotation
    about the world x, y, z axes (see :func:`pose_covariance_world`)."""
    return sigmas_from_world_covariance(pose_covariance_world(R_world_imu, P))
