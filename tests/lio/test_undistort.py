import numpy as np

from adalio.config import ImuConfig
from adalio.lio import imu, so3
from adalio.lio.state import DIM, State

rng = np.random.default_rng(2)
OMEGA_B = np.array([0.3, -0.2, 1.0])
V_B = np.array([1.5, 0.3, 0.1])
R0 = so3.exp(np.array([0.1, 0.05, -0.4]))
P0 = np.array([1.0, -2.0, 0.5])
GRAVITY = np.array([0.0, 0.0, -9.81])


def _pose(t: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant body twist: R = R0 Exp(ω t), p = p0 + R0 t J_l(ω t) v_b."""
    R = R0 @ so3.exp(OMEGA_B * t)
    p = P0 + R0 @ (t * so3.jr(-OMEGA_B * t)) @ V_B
    return R, p


def test_constant_twist_undistortion_below_1mm():
    R_LI = so3.exp(np.array([0.02, -0.01, 1.2]))
    t_LI = np.array([0.05, -0.02, 0.1])
    t_end = 0.1
    imu_t = np.arange(-0.0025, t_end + 1e-9, 0.0025)
    gyro = np.tile(OMEGA_B, (imu_t.size, 1))
    acc = np.array([np.cross(OMEGA_B, V_B) - _pose(t)[0].T @ GRAVITY for t in imu_t])

    x = State(p=P0.copy(), R=R0.copy(), R_LI=R_LI, t_LI=t_LI, v=R0 @ V_B, g=GRAVITY.copy())
    q = imu.process_noise(ImuConfig())
    y, _, rec = imu.propagate(x, np.eye(DIM), imu_t, gyro, acc, 0.0, t_end, q)

    n = 3000
    X_world = P0 + rng.uniform(-20, 20, size=(n, 3))
    t_pts = np.sort(rng.uniform(0.0, t_end, size=n))
    pts = np.empty((n, 3))
    for j, t in enumerate(t_pts):
        R, p = _pose(t)
        pts[j] = R_LI.T @ (R.T @ (X_world[j] - p) - t_LI)
    R_e, p_e = _pose(t_end)
    expected = ((X_world - p_e) @ R_e - t_LI) @ R_LI

    assert np.abs(y.R - R_e).max() < 1e-9
    assert np.linalg.norm(y.p - p_e) < 1e-3
    out = imu.undistort(pts, t_pts, rec, y.R, y.p, R_LI, t_LI)
    err = np.linalg.norm(out - expected, axis=1)
    assert err.max() < 1e-3, err.max()
    raw_err = np.linalg.norm(pts - expected, axis=1)
    assert raw_err.max() > 0.1
