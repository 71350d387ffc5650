import numpy as np
import pytest

from adalio.lio import measurement, so3
from adalio.lio.state import State

rng = np.random.default_rng(3)
NO_GATE = (np.zeros((6, 6)), 0.0)
"""point_to_plane's covariance gate off: FAST-LIO2's range gate alone."""


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
                                           np.ones(n, bool), estimate_extrinsic, *NO_GATE)
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
                                           selected, False, *NO_GATE)
    assert acc.tolist() == [True, False, True, False, False]
    assert np.allclose(r, residual[[0, 2]])
    assert H.shape == (2, 12)


def test_the_covariance_gate_admits_the_residuals_the_predicted_pose_allows():
    """Rows the range gate rejects (near points, decimetre residuals) are accepted iff
    ``r² <= k² h P hᵀ``, with h the row's pose columns taken by finite differences of the
    residual (independent of the kernel's own row) and P a random pose covariance."""
    x = State(p=rng.normal(size=3), R=so3.exp(rng.normal(size=3)),
              R_LI=so3.exp(rng.normal(size=3) * 0.5), t_LI=rng.normal(size=3) * 0.3)
    n = 60
    pts = rng.normal(size=(n, 3))
    pts *= (rng.uniform(1.0, 4.0, n) / np.linalg.norm(pts, axis=1))[:, None]  # 1-4 m away
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    A = rng.normal(size=(6, 6)) * 0.1
    P = A @ A.T + np.diag([0.04, 0.04, 0.04, 1e-4, 1e-4, 1e-4])  # ~0.3 m, ~1 deg
    eps = 1e-6
    h = np.empty((n, 6))
    zero = np.zeros(n)
    for c in range(6):
        e = np.zeros(23)
        e[c] = eps
        h[:, c] = (_residuals(x.boxplus(e), pts, normals, zero)
                   - _residuals(x.boxplus(-e), pts, normals, zero)) / (2 * eps)
    k = 3.0
    allowed = k * np.sqrt(np.einsum("ij,jk,ik->i", h, P, h))
    residual = allowed * np.where(np.arange(n) % 2 == 0, 0.98, 1.02)
    range_gate = np.sqrt(np.linalg.norm(pts, axis=1)) / 9.0
    assert np.all(np.abs(residual) > range_gate)  # every row beyond FAST-LIO2's gate
    d = -_residuals(x, pts, normals, zero) + residual
    sel = np.ones(n, bool)
    _, r, acc = measurement.point_to_plane(pts, x.R, x.p, x.R_LI, x.t_LI, normals, d, sel,
                                           False, P, k)
    assert acc.tolist() == (np.arange(n) % 2 == 0).tolist()
    assert np.allclose(r, residual[acc])
    _, _, acc_off = measurement.point_to_plane(pts, x.R, x.p, x.R_LI, x.t_LI, normals, d, sel,
                                               False, P, 0.0)
    assert not acc_off.any()


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


def _pose_rows(x: State, pts_lidar: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Pose columns of point_to_plane's rows for the given normals (all rows accepted)."""
    d = -np.einsum("ij,ij->i", measurement.points_to_world(pts_lidar, x.R, x.p, x.R_LI, x.t_LI),
                   normals)
    H, _, acc = measurement.point_to_plane(pts_lidar, x.R, x.p, x.R_LI, x.t_LI, normals, d,
                                           np.ones(len(pts_lidar), bool), False, *NO_GATE)
    assert acc.all()
    return H[:, :6]


def test_normal_noise_information_matches_monte_carlo_of_refitted_planes():
    """The spread that noisy neighbours give a row's Jacobian ``h`` (built from the refitted
    normal), ``Cov(h) = E[h hᵀ] − E[h] E[h]ᵀ``, is σ² times what the kernel returns: Monte
    Carlo over 20000 refits of one elongated patch, rows weighted."""
    rng_mc = np.random.default_rng(7)
    x = State(p=np.array([1.0, -2.0, 0.5]), R=so3.exp(np.array([0.3, -0.2, 1.1])),
              R_LI=so3.exp(np.array([0.1, 0.2, -0.3])), t_LI=np.array([0.05, -0.02, 0.1]))
    n_true = np.array([0.2, -0.3, 0.9])
    n_true /= np.linalg.norm(n_true)
    e1 = np.cross(n_true, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n_true, e1)
    k, trials, sigma = 8, 20000, 0.005  # first order: sigma well below the patch spread
    uv = rng_mc.uniform(-1, 1, size=(k, 2)) * [0.3, 0.08]  # elongated: tilt differs by axis
    centre = np.array([3.0, 1.0, -1.0])
    patch = centre + uv[:, :1] * e1 + uv[:, 1:] * e2
    nbrs = patch[None] + rng_mc.normal(size=(trials, k, 3)) * sigma
    mu = nbrs.mean(axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(nbrs - mu)
    n_fit = vt[:, 2, :]
    n_fit *= np.sign(n_fit @ n_true)[:, None]
    # one query point in the LiDAR frame, at the patch (world) for the state x
    q_world = centre + 0.05 * e1
    q_lidar = x.R_LI.T @ (x.R.T @ (q_world - x.p) - x.t_LI)
    pts = np.repeat(q_lidar[None], trials, axis=0)
    w = np.full(trials, 0.7)
    h = _pose_rows(x, pts, n_fit) * w[:, None]
    mc = np.cov(h.T, bias=True)
    got = measurement.normal_noise_information(
        pts, np.ones(trials, bool), x.R, x.R_LI, x.t_LI, n_fit, nbrs,
        np.full(trials, k, np.int64), w) * sigma**2 / trials
    assert np.linalg.norm(got - mc) < 0.05 * np.linalg.norm(mc), (got, mc)
    # along the patch's long axis the tilt is (0.3 / 0.08)² = 14x less uncertain than across
    e1_cov = e1 @ got[:3, :3] @ e1
    e2_cov = e2 @ got[:3, :3] @ e2
    assert 8.0 < e2_cov / e1_cov < 25.0


def test_normal_noise_information_equals_its_definition_row_by_row():
    """Against ``Σ w² B N Bᵀ`` built row by row with numpy (``B = [I; [p_I]× Rᵀ]``,
    ``N = pinv(P S P) / k``): random state and extrinsic, rows with 3-8 neighbours on tilted
    noisy patches, rows left out by ``accepted``, and one collinear row (its whole ``h hᵀ``)."""
    rng_b = np.random.default_rng(11)
    x = State(p=rng_b.normal(size=3), R=so3.exp(rng_b.normal(size=3)),
              R_LI=so3.exp(rng_b.normal(size=3) * 0.3), t_LI=rng_b.normal(size=3) * 0.2)
    m, kmax = 60, 8
    pts = rng_b.normal(size=(m, 3)) * 4.0
    counts = rng_b.integers(3, kmax + 1, m)
    nbrs = np.full((m, kmax, 3), np.nan)
    normals = np.zeros((m, 3))
    for i in range(m):
        n = rng_b.normal(size=3)
        n /= np.linalg.norm(n)
        e1 = np.cross(n, rng_b.normal(size=3))
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        uv = rng_b.uniform(-1, 1, (counts[i], 2)) * rng_b.uniform(0.02, 0.4, 2)
        nbrs[i, :counts[i]] = (uv[:, :1] * e1 + uv[:, 1:] * e2
                               + rng_b.normal(size=(counts[i], 1)) * 0.003 * n)
        normals[i] = n
    nbrs[0, :counts[0]] = np.linspace(0.0, 0.4, counts[0])[:, None] * [1.0, 0.0, 0.0]
    normals[0] = [0.0, 0.0, 1.0]  # collinear: P S P has rank 1
    accepted = rng_b.uniform(size=m) < 0.8
    accepted[0] = True
    w = rng_b.uniform(0.2, 1.0, accepted.sum())
    expected = np.zeros((6, 6))
    for j, i in enumerate(np.flatnonzero(accepted)):
        p_imu = x.R_LI @ pts[i] + x.t_LI
        B = np.vstack([np.eye(3), so3.hat(p_imu) @ x.R.T])
        q = nbrs[i, :counts[i]]
        S = np.cov(q.T, bias=True)
        P = np.eye(3) - np.outer(normals[i], normals[i])
        N = np.linalg.pinv(P @ S @ P, rcond=1e-9, hermitian=True) / counts[i]
        if i == 0:
            N = np.outer(normals[i], normals[i])
        expected += w[j] ** 2 * B @ N @ B.T
    got = measurement.normal_noise_information(pts, accepted, x.R, x.R_LI, x.t_LI, normals,
                                               nbrs, counts, w)
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())
    np.testing.assert_array_equal(got, got.T)


def test_normal_noise_information_of_a_row_without_a_plane_is_the_whole_row():
    """Collinear neighbours define no plane: every bit of the row's information is fake."""
    x = State(p=np.zeros(3), R=so3.exp(np.array([0.0, 0.0, 0.4])))
    nbrs = np.zeros((1, 5, 3))
    nbrs[0, :, 0] = np.linspace(2.0, 2.4, 5)  # a line along x
    normal = np.array([[0.0, 0.0, 1.0]])
    pts = np.array([[2.2, 0.0, 0.0]])
    w = np.array([0.5])
    h = _pose_rows(x, pts, normal) * w[:, None]
    got = measurement.normal_noise_information(pts, np.ones(1, bool), x.R, x.R_LI, x.t_LI,
                                               normal, nbrs, np.array([5]), w)
    np.testing.assert_allclose(got, h.T @ h, atol=1e-12)


def test_normal_noise_bias_matches_monte_carlo_of_refitted_planes():
    """A query beyond its neighbours' patch: the refitted normal's tilt enters both the row's
    Jacobian and its residual, ``E[w² h r] = b`` (σ² B N ℓ summed over rows; ℓ the query's lever
    arm from the neighbours' centroid). Monte Carlo over 40000 refits (PCA through the centroid),
    with the noise σ² given and with each row's own estimate of it (``empirical``)."""
    rng_mc = np.random.default_rng(21)
    x = State(p=np.array([0.5, 1.0, -0.3]), R=so3.exp(np.array([-0.2, 0.1, 0.7])),
              R_LI=so3.exp(np.array([0.1, -0.1, 0.2])), t_LI=np.array([0.02, 0.03, -0.05]))
    n_true = np.array([0.9, 0.1, -0.2])
    n_true /= np.linalg.norm(n_true)
    e1 = np.cross(n_true, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n_true, e1)
    k, trials, sigma = 6, 40000, 0.004
    uv = rng_mc.uniform(-1, 1, size=(k, 2)) * [0.3, 0.05]  # a thin strip along e1
    centre = np.array([4.0, -1.0, 0.5])
    patch = centre + uv[:, :1] * e1 + uv[:, 1:] * e2
    nbrs = patch[None] + rng_mc.normal(size=(trials, k, 3)) * sigma
    mu = nbrs.mean(axis=1)
    _, _, vt = np.linalg.svd(nbrs - mu[:, None, :])
    n_fit = vt[:, 2, :]
    n_fit *= np.sign(n_fit @ n_true)[:, None]
    q_world = centre + 0.1 * e1 + 0.35 * e2 + rng_mc.normal(size=(trials, 3)) * sigma
    q_lidar = ((q_world - x.p) @ x.R - x.t_LI) @ x.R_LI
    w = np.full(trials, 0.8)
    h = _pose_rows(x, q_lidar, n_fit)
    r = np.einsum("ij,ij->i", q_world - mu, n_fit)
    mc = np.sum((w**2 * r)[:, None] * h, axis=0)
    mc_se = np.sqrt(trials) * np.std((w**2 * r)[:, None] * h, axis=0)
    args = (q_lidar, np.ones(trials, bool), x.R, x.p, x.R_LI, x.t_LI, n_fit, mu, nbrs,
            np.full(trials, k, np.int64), w)
    F, b = measurement.normal_noise_terms(*args, sigma**2, False)
    _, b_emp = measurement.normal_noise_terms(*args, 1.0, True)
    big = np.abs(mc) > 10 * mc_se  # the components the lever arm drives
    assert big.sum() >= 3
    np.testing.assert_allclose(b[big], mc[big], rtol=0.08)
    np.testing.assert_allclose(b_emp[big], mc[big], rtol=0.1)
    assert np.all(np.abs(b - mc) < 5 * mc_se + 0.08 * np.abs(mc))
    # F is normal_noise_information scaled by the given noise
    F1 = measurement.normal_noise_information(q_lidar, np.ones(trials, bool), x.R, x.R_LI,
                                              x.t_LI, n_fit, nbrs, np.full(trials, k, np.int64),
                                              w)
    np.testing.assert_allclose(F, sigma**2 * F1, rtol=1e-12)
