import numpy as np
import pytest

from adalio.lio import measurement, so3
from adalio.lio.state import State

rng = np.random.default_rng(3)


def _residuals(x: State, pts, normals, d) -> np.ndarray:
    p_world = (pts @ x.R_LI.T + x.t_LI) @ x.R.T + x.p
    return np.einsum("ij,ij->i", p_world, normals) + d


@pytest.mark.parametrize("estimate_extrinsic", [True, False])
def test_H_rows_match_finite_differences(estimate_extrinsic):
    x = State(p=rng.normal(size=3) * 3, R=so3.exp(rng.normal(size=3)),
              R_LI=so3.exp(rng.normal(size=3) * 0.5), t_LI=rng.normal(size=3) * 0.3)
    n = 40
    pts = rng.uniform(-15, 15, size=(n, 3))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    p_world = measurement.points_to_world(pts, x.R, x.p, x.R_LI, x.t_LI)
    assert np.allclose(p_world, (pts @ x.R_LI.T + x.t_LI) @ x.R.T + x.p)
    d = -np.einsum("ij,ij->i", p_world, normals) + rng.uniform(-0.05, 0.05, n)
    H, r, acc = measurement.point_to_plane(pts, x.R, x.p, x.R_LI, x.t_LI, normals, d,
                                           np.ones(n, bool), estimate_extrinsic)
    assert acc.all() and H.shape == (n, 12)
    assert np.allclose(r, _residuals(x, pts, normals, d), atol=1e-12)
    eps = 1e-6
    num = np.empty((n, 12))
    for c in range(12):
        e = np.zeros(23)
        e[c] = eps
        num[:, c] = (_residuals(x.boxplus(e), pts, normals, d)
                     - _residuals(x.boxplus(-e), pts, normals, d)) / (2 * eps)
    if estimate_extrinsic:
        assert np.allclose(H, num, atol=1e-6)
    else:
        assert np.allclose(H[:, :6], num[:, :6], atol=1e-6)
        assert np.all(H[:, 6:] == 0.0)


def test_range_adaptive_gate_and_selection():
    x = State()
    ranges = np.array([4.0, 4.0, 25.0, 25.0, 9.0])
    pts = np.zeros((5, 3))
    pts[:, 0] = ranges
    normals = np.tile([1.0, 0.0, 0.0], (5, 1))
    limit = np.sqrt(ranges) / 9.0
    residual = np.array([0.99, 1.01, 0.99, 1.01, 0.1]) * limit
    d = -ranges + residual
    selected = np.array([True, True, True, True, False])
    H, r, acc = measurement.point_to_plane(pts, x.R, x.p, x.R_LI, x.t_LI, normals, d,
                                           selected, False)
    assert acc.tolist() == [True, False, True, False, False]
    assert np.allclose(r, residual[[0, 2]])
    assert H.shape == (2, 12)


@pytest.mark.parametrize("plane_variance,share", [(True, True), (True, False), (False, True)])
def test_residual_weights_match_brute_force(plane_variance, share):
    """1/sigma per accepted row: plane-fit variance 1 + 1/k + rho²/(k lambda_mid) at the
    world point, times the number of accepted rows sharing the row's group, written out
    row by row in plain numpy."""
    x = State(p=rng.normal(size=3), R=so3.exp(rng.normal(size=3)),
              R_LI=so3.exp(rng.normal(size=3) * 0.3), t_LI=rng.normal(size=3) * 0.2)
    n = 60
    pts = rng.uniform(-10, 10, (n, 3))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    mu = rng.normal(size=(n, 3)) * 5
    lam_mid = rng.uniform(0.0, 0.02, n)
    lam_mid[:3] = 0.0  # floor at 1e-12
    counts = rng.integers(0, 8, n)
    group_id = rng.integers(0, 12, n)
    accepted = rng.uniform(size=n) < 0.7
    w = measurement.residual_weights(pts, accepted, x.R, x.p, x.R_LI, x.t_LI, normals, mu,
                                     lam_mid, counts, group_id, 12, plane_variance, share)
    p_world = (pts @ x.R_LI.T + x.t_LI) @ x.R.T + x.p
    expect = []
    for i in np.flatnonzero(accepted):
        var = 1.0
        if plane_variance:
            off = p_world[i] - mu[i]
            rho2 = max(off @ off - (off @ normals[i]) ** 2, 0.0)
            k = max(counts[i], 1)
            var = 1 + 1 / k + rho2 / (k * max(lam_mid[i], 1e-12))
        if share:
            var *= np.sum(accepted & (group_id == group_id[i]))
        expect.append(var ** -0.5)
    assert w.shape == (accepted.sum(),)
    np.testing.assert_allclose(w, expect, rtol=1e-12)
