import numpy as np

from adalio.config import FilterConfig
from adalio.lio import measurement, so3
from adalio.lio.ieskf import iterated_update
from adalio.lio.state import DIM, State, initial_covariance

rng = np.random.default_rng(4)
HALF = np.array([5.0, 4.0, 1.5])


def _box_room(n_per_wall: int, walls=range(6)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on the walls of an axis-aligned box ``|x_i| = HALF_i``, with their planes."""
    pts, normals, ds = [], [], []
    for w in walls:
        axis, sign = w // 2, (1.0 if w % 2 else -1.0)
        p = rng.uniform(-HALF, HALF, size=(n_per_wall, 3))
        p[:, axis] = sign * HALF[axis]
        n = np.zeros(3)
        n[axis] = 1.0
        pts.append(p)
        normals.append(np.tile(n, (n_per_wall, 1)))
        ds.append(np.full(n_per_wall, -sign * HALF[axis]))
    return np.vstack(pts), np.vstack(normals), np.concatenate(ds)


def _scan(x_true: State, X_world: np.ndarray) -> np.ndarray:
    return ((X_world - x_true.p) @ x_true.R - x_true.t_LI) @ x_true.R_LI


def _measure_fn(pts_lidar, normals, ds, cfg, log):
    def measure(x: State, research: bool):
        log.append(research)
        sel = np.ones(pts_lidar.shape[0], bool)
        H, r, _ = measurement.point_to_plane(pts_lidar, x.R, x.p, x.R_LI, x.t_LI, normals, ds,
                                             sel, cfg.estimate_extrinsic)
        return H, r
    return measure


def test_box_room_update_recovers_injected_offset():
    cfg = FilterConfig()
    X, normals, ds = _box_room(300)
    x_true = State(p=np.array([0.7, -0.4, 0.2]), R=so3.exp(np.array([0.05, -0.02, 0.8])),
                   R_LI=so3.exp(np.array([0.0, 0.0, np.pi / 2])), t_LI=np.array([0.1, 0.0, 0.05]))
    pts = _scan(x_true, X)
    offset = np.zeros(DIM)
    offset[0:3] = [0.04, -0.03, 0.02]
    offset[3:6] = np.deg2rad([0.6, -0.5, 1.0])
    x_prior = x_true.boxplus(offset)
    log: list[bool] = []
    out = iterated_update(x_prior, initial_covariance(False), _measure_fn(pts, normals, ds, cfg,
                                                                          log), cfg)
    assert np.linalg.norm(out.state.p - x_true.p) < 1e-3
    assert np.linalg.norm(so3.log(x_true.R.T @ out.state.R)) < np.deg2rad(0.01)
    assert out.converged and 2 <= out.iterations <= cfg.max_iterations + 1
    assert log[0] is True and len(log) == out.iterations
    assert np.allclose(out.state.R_LI, x_true.R_LI) and np.allclose(out.state.t_LI, x_true.t_LI)
    assert out.H.shape == (X.shape[0], 12)
    assert np.all(np.diag(out.P)[:6] < 1e-3) and np.allclose(out.P, out.P.T)


def test_small_H_gain_equals_standard_kalman_on_linear_model():
    cfg = FilterConfig(max_iterations=1, estimate_extrinsic=True)
    x0 = State()
    vec = np.r_[0:3, 9:21]
    A = rng.normal(size=(vec.size, vec.size)) * 0.1
    P0 = np.eye(DIM) * 0.05
    P0[np.ix_(vec, vec)] += A @ A.T
    m = 30
    H12 = np.zeros((m, 12))
    H12[:, :3] = rng.normal(size=(m, 3))
    z = rng.normal(size=m) * 0.1

    def measure(x: State, research: bool):
        dp = x.p - x0.p
        return H12.copy(), H12[:, :3] @ dp - z

    out = iterated_update(x0, P0, measure, cfg)
    H = np.zeros((m, DIM))
    H[:, :12] = H12
    Rm = cfg.laser_point_cov * np.eye(m)
    K = P0 @ H.T @ np.linalg.inv(H @ P0 @ H.T + Rm)
    dx_ref = K @ z
    P_ref = (np.eye(DIM) - K @ H) @ P0
    assert np.allclose(out.state.boxminus(x0), dx_ref, atol=1e-9)
    assert np.allclose(out.P, P_ref, atol=1e-9)


def test_pose_projector_keeps_unobservable_direction_at_prediction():
    cfg = FilterConfig()
    X, normals, ds = _box_room(300, walls=(2, 3, 4, 5))
    x_true = State(p=np.array([0.3, 0.1, 0.0]))
    pts = _scan(x_true, X)
    offset = np.zeros(DIM)
    offset[0:3] = [0.05, 0.03, -0.02]
    x_prior = x_true.boxplus(offset)
    proj = np.eye(6)
    proj[0, 0] = 0.0
    out = iterated_update(x_prior, initial_covariance(False),
                          _measure_fn(pts, normals, ds, cfg, []), cfg, pose_projector=proj)
    assert out.state.p[0] == x_prior.p[0]
    assert np.linalg.norm(out.state.p[1:] - x_true.p[1:]) < 1e-3
    assert np.all(out.H[:, 0] == 0.0)


def test_projected_update_covariance_matches_monte_carlo():
    """adaptive+ holds pose directions at the prior while the correlated states still update (a
    Schmidt "consider" gain); the reported covariance must be that of the actual estimation
    error. Truth: the error of 50000 sampled priors and measurements through the filter's own
    (linear) map from measurement to correction."""
    cfg = FilterConfig(max_iterations=1)
    rng = np.random.default_rng(11)
    x0 = State()
    vec = np.r_[0:6, 12:21]
    A = rng.normal(size=(vec.size, vec.size)) * 0.1
    P0 = np.eye(DIM) * 1e-4
    P0[np.ix_(vec, vec)] += A @ A.T
    m = 12
    H12 = np.zeros((m, 12))
    H12[:, :3] = rng.normal(size=(m, 3))
    proj = np.eye(6)
    proj[0, 0] = 0.0

    def run(z: np.ndarray):
        def measure(x: State, research: bool):
            return H12.copy(), H12[:, :3] @ (x.p - x0.p) - z
        return iterated_update(x0, P0, measure, cfg, pose_projector=proj)

    out = run(np.zeros(m))
    K_eff = np.column_stack([run(np.eye(m)[i]).state.boxminus(x0) for i in range(m)])
    H = np.zeros((m, DIM))
    H[:, :3] = H12[:, :3] @ proj[:3, :3]
    n = 50000
    e = rng.multivariate_normal(np.zeros(DIM), P0, size=n)
    v = rng.normal(scale=np.sqrt(cfg.laser_point_cov), size=(n, m))
    e_post = e - (e @ H.T + v) @ K_eff.T
    emp = np.cov(e_post.T)
    assert np.all(K_eff[0] == 0.0)  # the held position component never moves
    assert np.any(np.abs(K_eff[12:21]) > 1e-3)  # velocity and biases still take the update
    sd = np.sqrt(np.diag(P0))
    assert np.max(np.abs(out.P - emp) / np.outer(sd, sd)) < 0.025  # sampling noise ~0.012
    assert np.isclose(out.P[0, 0], P0[0, 0])
    short = (np.eye(DIM) - K_eff @ H) @ P0  # the optimal-gain shortcut is not this error's
    assert np.max(np.abs(short - emp) / np.outer(sd, sd)) > 0.1


def test_world_sigmas_match_monte_carlo():
    """World-frame sigmas of a random covariance against sampled perturbations: position errors
    are world-frame already, attitude errors δθ (body frame, R Exp(δθ)) are measured as the world
    rotation Log(R Exp(δθ) Rᵀ)."""
    from scipy.spatial.transform import Rotation

    from adalio.lio.state import P_, TH, world_sigmas

    rng = np.random.default_rng(3)
    A = rng.normal(size=(DIM, DIM)) * 0.02
    P = A @ A.T + np.eye(DIM) * 1e-5
    R = Rotation.from_euler("zyx", [1.1, 0.4, -0.6]).as_matrix()
    sig_p, sig_th_deg = world_sigmas(R, P)
    d = rng.multivariate_normal(np.zeros(DIM), P, size=40000)
    pos = d[:, P_]
    rot_w = np.array([so3.log(R @ so3.exp(x.copy()) @ R.T) for x in d[:, TH]])
    np.testing.assert_allclose(sig_p, pos.std(axis=0), rtol=0.03)
    np.testing.assert_allclose(sig_th_deg, np.degrees(rot_w.std(axis=0)), rtol=0.03)
    # the body-frame diagonal is not the world one for this rotation
    assert not np.allclose(sig_th_deg, np.degrees(np.sqrt(np.diag(P[TH, TH]))), rtol=0.05)
