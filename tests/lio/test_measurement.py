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
