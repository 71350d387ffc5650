"""AdaLIO degeneracy detection, parameter switching and scan localizability.

Frames and units: detector inputs are LiDAR-frame points in metres (the scan after undistortion
and voxel downsampling with the *general* leaf, lio-design.md §6.1 step 4). Localizability inputs
are the pose columns of the point-to-plane Jacobian in the estimator's error-state order
``[dp_x, dp_y, dp_z, dtheta_x, dtheta_y, dtheta_z]`` (metres, radians; lio-design.md §2, §6.3) and
the residual variance ``R`` in m².

1. The paper's strategy (AdaLIO, Lim et al., §III-C; lio-design.md §9)
-----------------------------------------------------------------------
Per scan, with ``C`` the downsampled cloud at the general leaf::

    N_down = |C|,    N_near = |{p in C : |p_x| < d_xy and |p_y| < d_xy}|      (z ignored)

Two readings of "few points and most occupied voxels close to the sensor" exist (§9.1, §9.2):

* ``detector='count'`` (the public tech-transfer code, §9.2)::

      degenerate = N_down < tau_n  (trigger 'count')  or  N_near < tau_near  (trigger 'near')

  Note the second test fires when *few* points are near, the opposite of the paper's sentence:
  with a 32-beam LiDAR in a large open hall the ±d_xy box holds little more than the floor ring,
  so this reading flags open halls (measured in ``benchmarks/bench_modes.py``).
* ``detector='near_ratio'`` (the paper's sentence, §9.5)::

      degenerate = N_down < tau_n  and  N_near / N_down > near_ratio        (trigger 'near_ratio')

  An empty scan (N_down = 0) counts as degenerate.

A geometry trigger ('eigen') is added in modes ``adaptive`` / ``adaptive+`` when the caller
reports ``weak_geometry`` (see :func:`is_weak`: translation eigenvalue ratio of the scan's
information below ``min_eigen_ratio``). Hysteresis (§9.2): the degenerate set stays active for
``hold_scans`` scans counting the triggering scan (the public code's counter < 3); held scans
report trigger 'hold'. In degenerate mode the paper's Table I applies: scan leaf 0.2 → 0.1 m,
search radius (the gate on the farthest of the k neighbours, §9.4) 3.0 → 2.0 m, plane residual
margin 0.05 → 0.025 m — the two :class:`~adalio.config.ParamSet` of the config.

2. Localizability (beyond the paper)
------------------------------------
With ``H`` the (m, 6) pose Jacobian of the accepted residuals (row ``[n^T, (p_I x c)^T]``,
§6.3) and isotropic residual variance ``R``, the Fisher information of the pose is::

    I = H^T H / R                       (6x6; reported in (rot xyz, trans xyz) order)

Its eigen-decomposition ``I = V diag(lambda) V^T`` (ascending) gives the weakest direction
``v_0`` (as in Zhang, Kaess & Singh, "On degeneracy of optimization-based state estimation",
ICRA 2016, and Hinduja et al., IROS 2019, cited by the paper). Rotation rows carry m² and
translation rows carry 1, so eigenvalues of the full matrix mix units. The scalar figures are
therefore computed on the 3x3 translation block ``I_tt = sum_j n_j n_j^T / R`` (units 1/m²)::

    translation_ratio = lambda_min(I_tt) / lambda_max(I_tt)
    score             = 1 - sqrt(translation_ratio)    in [0, 1]

``sqrt`` turns information into a ratio of standard deviations: score = 1 - sigma_best /
sigma_worst of the translation; 0 = isotropic, 1 = a translation direction the scan cannot see.
The block (information on translation *given* the rotation) is used rather than its Schur
complement ``I_tt - I_tr I_rr^-1 I_rt`` (information *marginal* over rotation): within one scan
the gyro-propagated prior pins rotation to ~1e-3 rad, so the conditional information is the one
that limits the translation update; the block is also independent of the rotation reference point
and needs no inverse of a possibly singular ``I_rr``. Pure-rotation or coupled degeneracies still
show in ``eigenvalues`` / ``weakest``. With m = 0 everything is zero and score = 1.

3. adaptive+ (refine, then project)
-----------------------------------
When the degenerate set is active in mode ``adaptive+``, the estimator (i) keeps refining: it
halves the scan leaf (not below ``min_voxel_size_m``) and re-runs the update while
``translation_ratio < min_eigen_ratio`` and ``N_down < point_budget``; then (ii) it blocks the
update along directions the scan cannot observe.

"Cannot observe" needs a metric in which rotations and translations compare. A pose error
``delta = (dp, dtheta)`` moves scan point j by ``u_j = dp + dtheta x p_j`` (first order, body
frame lever arm ``p_j``); the scan *sees* only the part along the normal, ``n_j^T u_j = H_j
delta``. The natural question per direction is which fraction of the point motion is visible::

    lambda(delta) = (delta^T I_e delta) / (delta^T M delta),
    M = blockdiag(I_3, J),   J = mean_j (|p_j|² I_3 - p_j p_j^T)   (inertia of the scan, m²)

i.e. the generalised eigenproblem ``I_e v = lambda M v`` (units 1/m², rotation-invariant;
the cross term of the exact point metric, ``mean p_j``, is dropped so that M is independent of
the attitude). With ``W = M^-1/2`` (``Localizability.scaling``) and the scaled information
``I~ = W I_e W``, keep the eigenvectors ``U_k`` of ``I~`` whose eigenvalue >= ratio *
lambda_max(I~)::

    P~ = U_k U_k^T,      P = W P~ W^-1               (:func:`observable_projector`)

``P`` is idempotent; its null space ``W span(U_weak)`` is the weak set, its range the observable
one. Why not the plain eigenvalues of ``I_e``: in a 2 m wide, 40 m long corridor roll moves the
points ~1 m per radian and yaw ~10 m per radian, so relative to yaw the roll information is
~1/100 although roll is well observed; the metric M divides that lever arm out, so only the
corridor axis (information 0) falls below the ratio. If the caller has no points, M falls back
to ``blockdiag(I_3, L² I_3)``, ``L² = tr(I_rr) / tr(I_tt)`` (a scalar RMS moment arm), which
has that roll bias. The estimator uses ``H_pose <- H_pose P`` in the gain and removes the
gain's pose rows along ``null(P)``, so in the IEKF (§6.4), with ``M = blockdiag(P, I)``::

    S = P^T H^T H P / R + P_j^-1,   K = S^-1 H^T / R,   delta = M K h + (M K H P - I) delta~
    P+ = (I - M K H P) P_j (I - M K H P)^T + M K R K^T M^T                       (Joseph form)

the measurement adds no information along ``null(P)`` and the pose stays at the IMU prediction
along it, instead of following noise and unmodelled structure (the "solution remapping" of
Zhang et al. 2016 applied to the IEKF step), while velocity and biases keep their optimal gain
(a Schmidt-Kalman "consider" update). ``M K`` is not the optimal gain, so the covariance needs
the Joseph form: the short form ``(I - K H) P_j`` shrinks the covariance and the correlations
along the held directions as if the pose had moved there. Measured with a residual variance of
0.01 m² in the simulated spiral staircase: with the short form adaptive+ diverged on seeds 0 and
2 (132 m and 1.7 m ATE), with the Joseph form it holds 24 and 9 cm.

4. Re-association probes (adaptive+)
------------------------------------
``H^T H`` overstates what a scan observes when the fitted normals are noisy: on a vertical wall
fitted from a few close map points, a normal tilted by eps adds eps² of "height information",
but when the pose moves up the re-searched neighbours follow the point along the wall and the
residual does not change. Measured in the simulated stairwell, on the flights (no return hits a
horizontal face there, ``benchmarks/bench_observability.py``) every row with |n_z| > 0.3 lay on
a vertical face, and the LiDAR-only optimum stayed wherever it was started (±5 cm) while the
filter claimed sigma_z < 1 cm. So adaptive+ tests the weakest directions by re-association:
for the displacements ``d_k = s W v_k`` along the ``probe_directions`` weakest eigenvectors of
``I~`` (each moves the points by s = ``probe_step_m`` RMS, :func:`weak_directions`), it searches
and fits again at ``x ⊞ d_k`` and ``x ⊟ d_k`` and compares the restoring gradient with the
claim::

    rho_k = d_k^T (g(x + d_k) - g(x - d_k)) / (2 d_k^T H^T H d_k),     g = H^T r

A quadratic cost with real information gives rho = 1 (the central difference also cancels a
constant bias of g); residuals that follow the point give rho ~ 0. Directions with
``rho < min_restoring_ratio`` join the weak set of §3 (:func:`consistent_projector`), so the
IMU prediction holds along them.

5. Which directions the IMU can hold (adaptive+)
------------------------------------------------
Holding a direction trusts the IMU's prediction along it, and the IMU does not predict every
direction equally well. A tilt error projects gravity into the horizontal acceleration at first
order (into the vertical at second order), and a yaw error turns the horizontal velocity, so the
horizontal position is what the prediction gets worst; the height and the attitude it gets well.
And a horizontal direction that the probes find weak is often weak but real: a corridor's axis,
seen by door frames and pilasters, restored 5-40 % of its claim where it was held (OS1-64,
still-start corridor, seed 1), and with a sparser LiDAR its eigenvalue falls below
``observable_eigen_ratio`` of the strongest. So by default
(``adaptive.hold_horizontal`` false) neither test holds a direction that is mostly a horizontal
translation (:func:`mostly_horizontal`: ``|dp_xy|²`` more than half of its mean square point
motion). Measured (README, *Session 30*): the corridor goes from 4.8 (9.8) to 3.6 (5.6) cm, the
still-start corridor on the sensor matrix from 5 of 12 runs beyond 1 m to none, and the spiral
and the stairwell, whose weak directions are height and rotation, do not change.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from adalio.config import AdaptiveConfig, ParamSet
from adalio.errors import InputError

TRIGGERS = ("", "count", "near", "near_ratio", "eigen", "hold")
_ROT_TRANS_ORDER = np.array([3, 4, 5, 0, 1, 2])
_COLUMNS = np.arange(6)


def _as_points(points: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must be an (N, 3) array of points (got shape {arr.shape})")
    return arr


def count_near(points_lidar: np.ndarray, d_xy_m: float) -> int:
    """N_near of lio-design.md §9.2: points with |x| < d_xy and |y| < d_xy (z ignored)."""
    pts = _as_points(points_lidar, "points_lidar")
    near = (np.abs(pts[:, 0]) < d_xy_m) & (np.abs(pts[:, 1]) < d_xy_m)
    return int(np.count_nonzero(near))


@dataclass
class Decision:
    """Outcome of one :meth:`DegeneracyDetector.check`."""

    degenerate: bool
    """True if the degenerate parameter set is active for this scan."""
    trigger: str
    """'', 'count', 'near', 'near_ratio', 'eigen' or 'hold' (see the module docstring)."""
    n_down: int
    """Points of the scan downsampled with the general leaf (N_down)."""
    n_near: int
    """Of those, points with |x|, |y| < d_xy in the LiDAR frame (N_near)."""
    params: ParamSet
    """The active set: ``cfg.degenerate`` if degenerate else ``cfg.general``."""


class DegeneracyDetector:
    """Per-scan degeneracy check with hold (lio-design.md §9.2, §9.5; paper §III-C).

    Stateful: call :meth:`check` once per scan, in scan order.
    """

    def __init__(self, cfg: AdaptiveConfig) -> None:
        self.cfg = cfg
        self._held_left = 0

    def reset(self) -> None:
        """Forget the hold state (e.g. at a new sequence)."""
        self._held_left = 0

    def _count_trigger(self, n_down: int, n_near: int) -> str:
        cfg = self.cfg
        if cfg.detector == "near_ratio":
            if n_down < cfg.tau_n and (n_down == 0 or n_near / n_down > cfg.near_ratio):
                return "near_ratio"
            return ""
        if n_down < cfg.tau_n:
            return "count"
        if n_near < cfg.tau_near:
            return "near"
        return ""

    def check(self, points_down_general_lidar: np.ndarray,
              weak_geometry: bool = False) -> Decision:
        """Decide the parameter set of this scan from its general-leaf downsampled cloud.

        ``weak_geometry``: the caller's localizability verdict (:func:`is_weak`), used as the
        'eigen' trigger in modes other than 'fixed' when ``use_localizability_trigger`` is set.
        """
        cfg = self.cfg
        pts = _as_points(points_down_general_lidar, "points_down_general_lidar")
        n_down = int(pts.shape[0])
        n_near = count_near(pts, cfg.d_xy_m)
        if cfg.mode == "fixed":
            return Decision(False, "", n_down, n_near, cfg.general)
        trigger = self._count_trigger(n_down, n_near)
        if not trigger and weak_geometry and cfg.use_localizability_trigger:
            trigger = "eigen"
        if trigger:
            self._held_left = max(int(cfg.hold_scans), 1) - 1
            return Decision(True, trigger, n_down, n_near, cfg.degenerate)
        if self._held_left > 0:
            self._held_left -= 1
            return Decision(True, "hold", n_down, n_near, cfg.degenerate)
        return Decision(False, "", n_down, n_near, cfg.general)


@dataclass
class Localizability:
    """Information of one scan's accepted point-to-plane residuals (module docstring §2)."""

    info: np.ndarray
    """(6, 6) H^T H / R in (rot xyz, trans xyz) order."""
    eigenvalues: np.ndarray
    """(6,) ascending eigenvalues of ``info`` (rotation entries 1/rad², translation 1/m²)."""
    eigenvectors: np.ndarray
    """(6, 6) unit eigenvectors as columns, (rot xyz, trans xyz) order, matching eigenvalues."""
    weakest: np.ndarray
    """(6,) eigenvector of the smallest eigenvalue; sign: largest-|.| component positive."""
    score: float
    """1 - sqrt(translation_ratio) in [0, 1]; 1 = a translation direction is unobservable."""
    translation_ratio: float
    """lambda_min / lambda_max of the 3x3 translation block (0 if the block is zero)."""
    n_residuals: int = 0
    """m, the number of rows of H."""
    translation_eigenvalues: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """(3,) ascending eigenvalues of the translation block (1/m²)."""
    scaling: np.ndarray | None = field(default_factory=lambda: np.eye(6))
    """(6, 6) W = M^-1/2 in error-state order [dp, dtheta] (module docstring §3); None when not
    computed (``localizability(..., observability=False)``)."""
    observability: np.ndarray | None = field(default_factory=lambda: np.zeros(6))
    """(6,) ascending eigenvalues of W I_e W divided by the largest (0 = unobservable); None
    when not computed."""


def _metric_scaling(info_e: np.ndarray, points: np.ndarray | None) -> np.ndarray:
    W = np.eye(6)
    if points is not None and len(points):
        sq = np.einsum("ij,ij->i", points, points)
        J = np.eye(3) * sq.mean() - (points.T @ points) / len(points)
        lam, vec = np.linalg.eigh(J)
        if lam[0] > 1e-9 * max(lam[-1], 1e-300):
            W[3:, 3:] = (vec / np.sqrt(lam)) @ vec.T
            return W
    tr_t = float(np.trace(info_e[:3, :3]))
    tr_r = float(np.trace(info_e[3:, 3:]))
    if tr_t > 0 and tr_r > 0:
        W[3:, 3:] *= np.sqrt(tr_t / tr_r)
    return W


def localizability(H_pose: np.ndarray, point_cov: float,
                   points_body: np.ndarray | None = None,
                   observability: bool = True) -> Localizability:
    """Information, eigen-decomposition and degeneracy score of a scan (module docstring §2).

    ``H_pose``: (m, 6) rows ``[dr/d dp (3), dr/d dtheta (3)]`` (lio-design.md §6.3) of the
    accepted residuals; ``point_cov``: residual variance R (m²); ``points_body``: optional
    (m, 3) lever arms ``p_I`` of the rows (IMU frame, metres), used only for the observability
    metric M of §3 (without them the scalar fallback applies). ``observability=False`` leaves
    out the metric and the scaled spectrum (``scaling`` and ``observability`` are then None),
    which only AdaLIO+'s projector and probes read: the per-scan statistics of every mode need
    the rest, and the metric was a third of the function's time.
    """
    H = np.asarray(H_pose, dtype=np.float64)
    if H.ndim != 2 or H.shape[1] != 6:
        raise InputError(f"H_pose must be an (m, 6) array (got shape {H.shape})")
    if not point_cov > 0:
        raise InputError(f"point_cov must be > 0 (got {point_cov})")
    m = int(H.shape[0])
    pts = None
    if points_body is not None:
        pts = _as_points(points_body, "points_body")
        if len(pts) != m:
            raise InputError(f"points_body has {len(pts)} rows but H_pose has {m}")
    if m == 0 or not np.any(H):
        return Localizability(info=np.zeros((6, 6)), eigenvalues=np.zeros(6),
                              eigenvectors=np.eye(6), weakest=np.zeros(6), score=1.0,
                              translation_ratio=0.0, n_residuals=m)
    info_e = (H.T @ H) / point_cov
    info = info_e[np.ix_(_ROT_TRANS_ORDER, _ROT_TRANS_ORDER)]
    lam, vec = np.linalg.eigh(info)
    lam = np.clip(lam, 0.0, None)
    # each column's sign: its largest-|.| entry positive (the first such entry on ties)
    vec *= np.where(vec[np.argmax(np.abs(vec), axis=0), _COLUMNS] < 0, -1.0, 1.0)
    lam_t = np.clip(np.linalg.eigvalsh(info_e[:3, :3]), 0.0, None)
    ratio = float(lam_t[0] / lam_t[2]) if lam_t[2] > 0 else 0.0
    ratio = min(max(ratio, 0.0), 1.0)
    W = obs = None
    if observability:
        W = _metric_scaling(info_e, pts)
        lam_s = np.clip(np.linalg.eigvalsh(W @ info_e @ W), 0.0, None)
        obs = lam_s / lam_s[-1] if lam_s[-1] > 0 else np.zeros(6)
    return Localizability(info=info, eigenvalues=lam, eigenvectors=vec, weakest=vec[:, 0].copy(),
                          score=float(1.0 - np.sqrt(ratio)), translation_ratio=ratio,
                          n_residuals=m, translation_eigenvalues=lam_t, scaling=W,
                          observability=obs)


def is_weak(loc: Localizability, cfg: AdaptiveConfig) -> bool:
    """The 'eigen' trigger: translation eigenvalue ratio below ``cfg.min_eigen_ratio``."""
    return bool(loc.translation_ratio < cfg.min_eigen_ratio)


def observable_projector(loc: Localizability, ratio: float,
                         keep_horizontal: bool = False,
                         up_world: np.ndarray | None = None) -> np.ndarray:
    """(6, 6) projector in error-state order [dp, dtheta] onto the observable directions.

    Module docstring §3: with ``W = loc.scaling`` and ``I~ = W I_e W``, keep the eigenvectors
    ``U_k`` of ``I~`` with eigenvalue >= ``ratio`` * lambda_max(I~) and return
    ``P = W U_k U_k^T W^-1``. P is idempotent; ``H P`` and ``P delta`` remove exactly the weak
    directions. With ``keep_horizontal`` a weak direction that is mostly a horizontal
    translation (:func:`mostly_horizontal`, §5; ``up_world`` the world's up) is kept too.
    ``ratio <= 0`` gives the identity;
    a scan without residuals gives the zero matrix (nothing is observable).
    """
    if not np.isfinite(ratio) or not 0.0 <= ratio <= 1.0:
        raise InputError(f"projector ratio must be in [0, 1] (got {ratio})")
    if ratio <= 0.0:
        return np.eye(6)
    if loc.n_residuals == 0 or not np.any(loc.info):
        return np.zeros((6, 6))
    lam, vec = _scaled_eigen(loc)
    W = _scaling(loc)
    strong = lam >= ratio * lam[-1]
    if keep_horizontal:
        strong |= np.array([mostly_horizontal(W, W @ v, up_world) for v in vec.T])
    keep = vec[:, strong]
    return W @ (keep @ keep.T) @ np.linalg.inv(W)


def mostly_horizontal(W: np.ndarray, d: np.ndarray, up_world: np.ndarray | None = None) -> bool:
    """A pose displacement ``d`` (error order [dp (world), dtheta]) is mostly a horizontal
    translation when the square of ``dp``'s part across ``up_world`` (the world's unit up, against
    gravity; None: the world's z, for a gravity-aligned world) is more than half of its mean
    square point motion, ``|W^-1 d|²`` (``W`` the scaling of module docstring §3, §5)."""
    dp = np.asarray(d[:3], dtype=np.float64)
    up = np.array([0.0, 0.0, 1.0]) if up_world is None else np.asarray(up_world, np.float64)
    across = dp - float(dp @ up) * up
    return bool(across @ across > 0.5 * float(np.sum(np.linalg.solve(W, d) ** 2)))


def _scaling(loc: Localizability) -> np.ndarray:
    if loc.scaling is None:
        raise ValueError("this Localizability was computed with observability=False")
    return loc.scaling


def _scaled_eigen(loc: Localizability) -> tuple[np.ndarray, np.ndarray]:
    """Ascending eigen-decomposition of ``W I_e W`` (module docstring §3), error order."""
    inv = np.argsort(_ROT_TRANS_ORDER)
    info_e = loc.info[np.ix_(inv, inv)]
    W = _scaling(loc)
    return np.linalg.eigh(W @ info_e @ W)


def weak_directions(loc: Localizability, count: int, step_m: float) -> np.ndarray:
    """(count, 6) error-state pose displacements ``step_m * W v_k`` along the ``count`` weakest
    eigenvectors ``v_k`` of ``W I_e W`` (module docstring §3): each moves the scan points by
    ``step_m`` RMS."""
    _, vec = _scaled_eigen(loc)
    return step_m * (_scaling(loc) @ vec[:, :count]).T


def consistent_projector(loc: Localizability, ratio: float, directions: np.ndarray,
                         restoring: np.ndarray, min_restoring: float,
                         keep_horizontal: bool = False,
                         up_world: np.ndarray | None = None) -> np.ndarray:
    """:func:`observable_projector` that also drops the probed ``directions`` (rows, error order
    [dp (world), dtheta], as from :func:`weak_directions`) whose ``restoring`` ratio is below
    ``min_restoring`` (module docstring §4). With ``keep_horizontal``, neither drops a direction
    that is mostly a horizontal translation (:func:`mostly_horizontal`, §5; ``up_world`` the
    world's up). The result is an idempotent (6, 6) projector."""
    P = observable_projector(loc, ratio, keep_horizontal, up_world)
    W = _scaling(loc)
    drop = [d for d, rho in zip(directions, restoring) if not rho >= min_restoring
            and not (keep_horizontal and mostly_horizontal(W, d, up_world))]
    if not drop:
        return P
    Winv = np.linalg.inv(W)
    U = np.linalg.qr(Winv @ np.array(drop).T)[0]
    Q = np.eye(6) - U @ U.T
    return W @ Q @ Winv @ P
