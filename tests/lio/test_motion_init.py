"""The moving start's fit covariance against brute force (Monte Carlo over noisy fits)."""

import numpy as np

from adalio.lio.motion_init import _lsq_covariance


def test_least_squares_covariance_matches_the_scatter_of_repeated_fits():
    """sigma² (AᵀA)⁻¹ with sigma² from the residuals: its mean over 4000 noisy fits of the
    motion model p_j = p_0 + v_0 t_j + ½ g t_j² equals the covariance of the fitted parameters."""
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 1.0, 11)
    eye = np.eye(3)
    A = np.vstack([np.hstack([eye, tj * eye, 0.5 * tj**2 * eye]) for tj in t])
    x_true = rng.normal(size=9)
    sigma = 0.02
    sols, covs = [], []
    for _ in range(4000):
        b = A @ x_true + sigma * rng.standard_normal(A.shape[0])
        x = np.linalg.lstsq(A, b, rcond=None)[0]
        sols.append(x)
        covs.append(_lsq_covariance(A, A @ x - b, 9))
    sols = np.array(sols)
    empirical = np.cov(sols.T)
    predicted = np.mean(covs, axis=0)
    d_emp, d_pred = np.diag(empirical), np.diag(predicted)
    assert np.allclose(d_pred, d_emp, rtol=0.08)
    # the velocity-gravity correlation is carried too (v_end = v_0 + g t uses it)
    rho_emp = empirical[3, 6] / np.sqrt(empirical[3, 3] * empirical[6, 6])
    rho_pred = predicted[3, 6] / np.sqrt(predicted[3, 3] * predicted[6, 6])
    assert rho_pred < -0.8 and abs(rho_pred - rho_emp) < 0.03


def test_handover_gravity_covariance_is_the_fit_s_on_the_sphere_tangent():
    """P[G] after a moving start is the fit's 3-D gravity covariance mapped onto the S² tangent
    of the filter's gravity (after the world alignment): brute force, the scatter of
    ``g_sample ⊟ g`` over gravity vectors drawn from that covariance."""
    from adalio.lio import so3
    from adalio.lio.motion_init import MovingInitResult, handover_covariance
    from adalio.lio.state import G

    rng = np.random.default_rng(3)
    g = np.array([0.4, -0.9, 9.75])
    g *= 9.81 / np.linalg.norm(g)
    A = rng.normal(size=(3, 3))
    C_g = 0.01 * (A @ A.T + 0.1 * np.eye(3))  # (m/s²)²: 0.1-0.3 m/s², 0.6-1.8° of tilt
    R_align = so3.exp(np.array([0.3, -0.2, 1.1]))
    fit = MovingInitResult(
        t_ns=0, R_world_imu=np.eye(3), p_world_imu_m=np.zeros(3), v_world_m_s=np.zeros(3),
        gyro_bias_rad_s=np.zeros(3), gravity_world_m_s2=g, residual_m=0.02,
        gravity_norm_fit_m_s2=9.81, n_scans=11, window_s=1.0,
        points_lidar_end=np.zeros((0, 3)), rotation_residual_rad=1e-3,
        velocity_cov_m2_s2=np.eye(3) * 1e-3, gravity_cov_m2_s4=C_g)
    P = handover_covariance(fit, R_align, estimate_extrinsic=False)
    g_w = R_align @ g
    anchor = so3.anchor_frame(g_w)
    samples = rng.multivariate_normal(g, C_g, size=20000) @ R_align.T
    d = np.array([so3.s2_boxminus(s, g_w, anchor) for s in samples])
    S = np.cov(d.T)
    assert np.allclose(P[G, G], S, rtol=0.05, atol=0.03 * np.sqrt(np.outer(np.diag(S),
                                                                             np.diag(S))).max())
    # 0.6-1.8° of tilt, where the still start's P0 claims 0.18°
    assert np.all(np.sqrt(np.diag(P[G, G])) > np.deg2rad(0.5))
