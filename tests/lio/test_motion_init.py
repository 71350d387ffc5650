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
