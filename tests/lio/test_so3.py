import numpy as np
import pytest

from adalio.lio import so3
from adalio.lio.state import DIM, State, initial_covariance

rng = np.random.default_rng(0)


@pytest.mark.parametrize("scale", [1e-9, 1e-3, 0.5, 2.0, 3.1])
def test_exp_log_roundtrip_and_orthonormal(scale):
    for _ in range(20):
        axis = rng.normal(size=3)
        phi = axis / np.linalg.norm(axis) * scale
        R = so3.exp(phi)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(so3.log(R), phi, atol=1e-8)


def test_log_near_pi():
    phi = np.array([0.0, 0.0, np.pi - 1e-6])
    assert np.allclose(so3.log(so3.exp(phi)), phi, atol=1e-5)


def test_exp_batch_matches_scalar_exp():
    phis = rng.normal(size=(50, 3)) * np.logspace(-8, 0.4, 50)[:, None]
    batch = so3.exp_batch(phis)
    for phi, Rb in zip(phis, batch):
        assert np.allclose(Rb, so3.exp(phi), atol=1e-12)


def test_right_jacobian_vs_finite_difference():
    for _ in range(10):
        phi = rng.normal(size=3)
        eps = 1e-6
        num = np.empty((3, 3))
        for i in range(3):
            e = np.zeros(3)
            e[i] = eps
            num[:, i] = (so3.log(so3.exp(phi).T @ so3.exp(phi + e))
                         - so3.log(so3.exp(phi).T @ so3.exp(phi - e))) / (2 * eps)
        assert np.allclose(so3.jr(phi), num, atol=1e-7)
        assert np.allclose(so3.jr_inv(phi) @ so3.jr(phi), np.eye(3), atol=1e-10)


@pytest.mark.parametrize("gdir", [[0, 0, -1], [1, 0, 0], [-1, 0, 0], [0.3, -0.8, 0.2]])
def test_s2_basis_and_boxplus_boxminus(gdir):
    g = np.asarray(gdir, float) / np.linalg.norm(gdir) * 9.81
    anchor = so3.anchor_frame(g)
    g_pert = so3.exp(rng.normal(size=3) * 0.2) @ g
    for gg in (g, g_pert):
        B = so3.s2_basis(gg, anchor)
        assert np.allclose(B.T @ B, np.eye(2), atol=1e-12)
        assert np.allclose(B.T @ gg, 0.0, atol=1e-9)
        for _ in range(5):
            d = rng.normal(size=2) * 0.3
            g2 = so3.s2_boxplus(gg, d, anchor)
            assert np.isclose(np.linalg.norm(g2), 9.81)
            assert np.allclose(so3.s2_boxminus(g2, gg, anchor), d, atol=1e-10)


def test_state_boxplus_boxminus_inverse():
    x = State(p=rng.normal(size=3), R=so3.exp(rng.normal(size=3)),
              R_LI=so3.exp(rng.normal(size=3) * 0.1), t_LI=rng.normal(size=3) * 0.1,
              v=rng.normal(size=3), b_g=rng.normal(size=3) * 0.01, b_a=rng.normal(size=3) * 0.1)
    d = rng.normal(size=DIM) * 0.1
    assert np.allclose(x.boxplus(d).boxminus(x), d, atol=1e-10)
    assert np.allclose(x.boxminus(x), 0.0)
    P = initial_covariance(estimate_extrinsic=False)
    assert P.shape == (DIM, DIM) and P[6, 6] < 1e-8 and P[15, 15] == 1e-4 and P[0, 0] == 1.0


@pytest.mark.parametrize("shape", [(3, 3, 3), (6, 6, 6), (3, 2, 4), (1, 5, 2)])
def test_small_products_match_numpy(shape):
    """The loop products the kernels use instead of numba's BLAS ``@``, against numpy's, on
    C-ordered and strided (transposed, sliced) operands."""
    n, k, m = shape
    A = rng.normal(size=(n, k))
    B = rng.normal(size=(k, m))
    Bt = np.ascontiguousarray(B.T)
    x = rng.normal(size=k)
    y = rng.normal(size=n)
    assert np.allclose(so3.mul(A, B), A @ B, rtol=1e-13, atol=1e-13)
    assert np.allclose(so3.mul(A, Bt.T), A @ B, rtol=1e-13, atol=1e-13)
    sparse = A * (rng.random(A.shape) < 0.5)
    assert np.allclose(so3.mul(sparse, B), sparse @ B, rtol=1e-13, atol=1e-13)
    assert np.allclose(so3.mul_vec(A, x), A @ x, rtol=1e-13, atol=1e-13)
    assert np.allclose(so3.mul_vec(A.T, y), A.T @ y, rtol=1e-13, atol=1e-13)
    wide = rng.normal(size=(n, k + 2))
    assert np.allclose(so3.mul(wide[:, 1:k + 1], B), wide[:, 1:k + 1] @ B, rtol=1e-13,
                       atol=1e-13)


def test_cross_matches_numpy():
    for _ in range(20):
        a, b = rng.normal(size=3), rng.normal(size=3)
        assert np.allclose(so3.cross(a, b), np.cross(a, b), rtol=1e-14, atol=1e-14)
