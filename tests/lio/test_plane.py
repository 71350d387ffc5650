"""Plane fits against known planes and closed-form residuals (lio-design.md §6.2)."""

import numpy as np
import pytest

from adalio.errors import ConfigError, InputError
from adalio.lio.ivox import IVox
from adalio.lio.plane import PARALLEL_MIN_ROWS, fit_planes, neighbour_moments

PENTAGON = np.array([[np.cos(a), np.sin(a)] for a in 2 * np.pi * np.arange(5) / 5])


def random_planes(rng: np.random.Generator, m: int, noise_m: float, d_range=(1.0, 20.0)):
    """Truth (n, d with d >= 0) and 5 neighbours per plane on a 0.5 m pentagon patch."""
    n = rng.normal(size=(m, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = rng.uniform(*d_range, size=m)
    u = np.cross(n, rng.normal(size=(m, 3)))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(n, u)
    centre = -d[:, None] * n + rng.uniform(-3, 3, size=(m, 1)) * u
    patch = 0.5 * PENTAGON * rng.uniform(0.6, 1.0, size=(m, 5, 1))
    nbrs = centre[:, None, :] + patch[..., :1] * u[:, None, :] + patch[..., 1:] * w[:, None, :]
    nbrs += rng.normal(scale=noise_m, size=(m, 5, 1)) * n[:, None, :]
    return n, d, nbrs


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


@pytest.mark.parametrize("method", ["ls", "pca"])
def test_noisy_planes_recover_normal_and_offset(method: str) -> None:
    rng = np.random.default_rng(0)
    n, d, nbrs = random_planes(rng, 400, noise_m=0.003)
    normals, dist, valid = fit_planes(nbrs, np.full(400, 5), 3, 0.05, method)
    assert valid.all()
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    assert np.all(dist >= 0)
    err = angle_deg(normals, n)
    assert np.median(err) < 0.6 and err.max() < 3.0
    assert np.max(np.abs(dist - d)) < 0.4
    residual = np.abs(np.einsum("mkj,mj->mk", nbrs, normals) + dist[:, None])
    assert residual.max() < 0.05


@pytest.mark.parametrize(("method", "tol_m"), [("ls", 1e-7), ("pca", 1e-12)])
def test_noise_free_planes_are_exact(method: str, tol_m: float) -> None:
    rng = np.random.default_rng(1)
    n, d, nbrs = random_planes(rng, 200, noise_m=0.0)
    normals, dist, valid = fit_planes(nbrs, np.full(200, 5), 3, tol_m, method)
    assert valid.all()
    np.testing.assert_allclose(normals, n, atol=tol_m)
    np.testing.assert_allclose(dist, d, atol=100 * tol_m)


def test_pca_and_ls_agree_on_generic_noisy_planes() -> None:
    rng = np.random.default_rng(2)
    _, _, nbrs = random_planes(rng, 300, noise_m=0.002, d_range=(2.0, 30.0))
    counts = np.full(300, 5)
    n_ls, d_ls, v_ls = fit_planes(nbrs, counts, 5, 0.05, "ls")
    n_pca, d_pca, v_pca = fit_planes(nbrs, counts, 5, 0.05, "pca")
    assert v_ls.all() and v_pca.all()
    assert angle_deg(n_ls, n_pca).max() < 0.5
    assert np.max(np.abs(d_ls - d_pca)) < 0.1


def symmetric_patch(h: float, delta: float) -> np.ndarray:
    """Four points of z = h displaced by +delta (x axis) and -delta (y axis)."""
    return np.array(
        [
            [
                [1.0, 0.0, h + delta],
                [-1.0, 0.0, h + delta],
                [0.0, 1.0, h - delta],
                [0.0, -1.0, h - delta],
            ]
        ]
    )


@pytest.mark.parametrize("method", ["ls", "pca"])
def test_margin_edge_cases_against_closed_form_residuals(method: str) -> None:
    h, delta = 2.0, 0.05
    nbrs = symmetric_patch(h, delta)
    z = nbrs[0, :, 2]
    d_expected = np.sum(z**2) / np.sum(z) if method == "ls" else h
    worst = np.max(np.abs(d_expected - z))
    counts = np.array([4])
    for margin, expect_valid in ((worst * (1 + 1e-9), True), (worst * (1 - 1e-9), False)):
        normals, dist, valid = fit_planes(nbrs, counts, 3, margin, method)
        np.testing.assert_allclose(normals[0], [0.0, 0.0, -1.0], atol=1e-12)
        np.testing.assert_allclose(dist[0], d_expected, rtol=1e-12)
        assert bool(valid[0]) is expect_valid


def test_plane_through_world_origin_with_ls() -> None:
    rng = np.random.default_rng(3)
    truth = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    xy = rng.uniform(-1, 1, size=(2, 5, 2))
    nbrs = np.zeros((2, 5, 3))
    nbrs[..., :2] = xy
    nbrs[0, :, 2] = 0.0
    nbrs[1, :, 2] = 0.3 * xy[1, :, 0] - 0.2 * xy[1, :, 1]
    normals, dist, valid = fit_planes(nbrs, np.array([5, 5]), 3, 1e-9, "ls")
    assert valid.all() and np.all(np.isfinite(normals))
    np.testing.assert_allclose(np.abs(normals[0]), [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(np.abs(normals[1] @ truth), 1.0, atol=1e-12)
    np.testing.assert_allclose(dist, 0.0, atol=1e-12)

    noisy = nbrs[1:].copy()
    noisy[..., 2] += rng.normal(scale=1e-3, size=5)
    n_noisy, _, v_noisy = fit_planes(noisy, np.array([5]), 3, 0.01, "ls")
    assert v_noisy[0] and np.abs(n_noisy[0] @ truth) > np.cos(np.radians(2.0))


def test_too_few_and_degenerate_neighbours() -> None:
    rng = np.random.default_rng(4)
    _, _, nbrs = random_planes(rng, 4, noise_m=0.0)
    nbrs[0, 2:] = np.nan
    counts = np.array([2, 4, 5, 5])
    for method in ("ls", "pca"):
        normals, dist, valid = fit_planes(nbrs, counts, 5, 0.1, method)
        np.testing.assert_array_equal(valid, [False, False, True, True])
        assert np.all(np.isnan(normals[:2])) and np.all(np.isnan(dist[:2]))
        _, _, valid3 = fit_planes(nbrs, counts, 3, 0.1, method)
        np.testing.assert_array_equal(valid3, [False, True, True, True])
    line = np.array([[[1.0, 2.0, 3.0], [2.0, 3.0, 4.0], [3.0, 4.0, 5.0], [4.0, 5.0, 6.0]]])
    for method in ("ls", "pca"):
        _, _, valid_line = fit_planes(line, np.array([4]), 3, 0.1, method)
        assert not valid_line[0]


def test_fit_on_ivox_neighbours_of_a_wall() -> None:
    rng = np.random.default_rng(5)
    wall = np.column_stack([np.full(3000, 4.0), rng.uniform(-3, 3, 3000), rng.uniform(0, 3, 3000)])
    ivox = IVox(0.5, 18, 10**6, 64)
    ivox.add_points(wall)
    queries = np.column_stack(
        [np.full(200, 4.0), rng.uniform(-2, 2, 200), rng.uniform(0.5, 2.5, 200)]
    )
    nbrs, counts, _ = ivox.knn(queries, 5, 1.0)
    assert np.all(counts == 5)
    for method, tol_m in (("ls", 1e-7), ("pca", 1e-12)):
        normals, dist, valid = fit_planes(nbrs, counts, 3, tol_m, method)
        assert valid.all()
        np.testing.assert_allclose(normals, np.tile([-1.0, 0.0, 0.0], (200, 1)), atol=tol_m)
        np.testing.assert_allclose(dist, 4.0, atol=tol_m)


@pytest.mark.parametrize("method", ["ls", "pca"])
def test_parallel_path_equals_serial_rows(method: str) -> None:
    rng = np.random.default_rng(6)
    m = PARALLEL_MIN_ROWS + 300
    n, _, nbrs = random_planes(rng, m, noise_m=0.01)
    counts = rng.integers(2, 6, size=m)
    whole = fit_planes(nbrs, counts, 3, 0.02, method)
    half = m // 2
    parts = [
        fit_planes(nbrs[sl], counts[sl], 3, 0.02, method) for sl in (np.s_[:half], np.s_[half:])
    ]
    for i in range(3):
        np.testing.assert_array_equal(whole[i], np.concatenate([p[i] for p in parts]))
    fitted = counts >= 3
    assert 0.2 < whole[2][fitted].mean() < 1.0
    assert np.median(angle_deg(whole[0][fitted], n[fitted])) < 3.0


def test_bad_arguments() -> None:
    with pytest.raises(ConfigError):
        fit_planes(np.zeros((1, 5, 3)), np.array([5]), 3, 0.1, "svd")
    with pytest.raises(InputError):
        fit_planes(np.zeros((1, 5, 2)), np.array([5]), 3, 0.1, "ls")
    with pytest.raises(InputError):
        fit_planes(np.zeros((2, 5, 3)), np.array([5]), 3, 0.1, "ls")


@pytest.mark.parametrize("method", ["ls", "pca"])
def test_min_extent_rejects_clustered_blob_and_keeps_spread_patch(method: str) -> None:
    """5 neighbours within 2 cm pass the margin test with any normal; the extent test drops them
    and still accepts a 0.4 m patch of the same plane (truth: sqrt(lambda_mid) of each set)."""
    rng = np.random.default_rng(3)
    n_true = np.array([0.0, 0.6, 0.8])
    u = np.array([1.0, 0.0, 0.0])
    w = np.cross(n_true, u)
    centre = np.array([2.0, 1.0, 3.0])
    blob = centre + 0.01 * PENTAGON[:, :1] * u + 0.01 * PENTAGON[:, 1:] * w
    blob += rng.normal(scale=0.004, size=(5, 3))
    patch = centre + 0.4 * PENTAGON[:, :1] * u + 0.4 * PENTAGON[:, 1:] * w
    patch += rng.normal(scale=0.004, size=(5, 1)) * n_true
    nbrs = np.stack([blob, patch])
    spread = [np.sqrt(np.linalg.eigvalsh(np.cov(q.T, bias=True))[1]) for q in nbrs]
    assert spread[0] < 0.02
    assert spread[1] > 0.2
    counts = np.full(2, 5)
    _, _, valid_margin_only = fit_planes(nbrs, counts, 3, 0.05, method)
    assert valid_margin_only.all()
    normals, _, valid = fit_planes(nbrs, counts, 3, 0.05, method, min_extent_m=0.05)
    np.testing.assert_array_equal(valid, [False, True])
    assert min(angle_deg(normals[1:], n_true[None])[0], angle_deg(-normals[1:], n_true[None])[0]) < 3
    with pytest.raises(ConfigError):
        fit_planes(nbrs, counts, 3, 0.05, method, min_extent_m=-1.0)


def test_min_extent_matches_brute_force_eigenvalues() -> None:
    """valid(min_extent) == valid(margin only) & sqrt(middle eigenvalue) >= min_extent, with the
    eigenvalues from numpy on anisotropic random neighbour sets far from the origin."""
    rng = np.random.default_rng(8)
    m = 3000
    scale = rng.uniform(0.002, 0.3, size=(m, 1, 3))
    nbrs = rng.normal(size=(m, 5, 3)) * scale + rng.uniform(-50, 50, size=(m, 1, 3))
    counts = np.full(m, 5)
    thr = 0.05
    _, _, base = fit_planes(nbrs, counts, 3, 0.2, "ls")
    _, _, valid = fit_planes(nbrs, counts, 3, 0.2, "ls", min_extent_m=thr)
    lam = np.array([np.linalg.eigvalsh(np.cov(q.T, bias=True))[1] for q in nbrs])
    clear = np.abs(np.sqrt(lam) - thr) > 1e-9
    assert 0.2 * m < base.sum() and 0.1 * m < valid.sum() < base.sum()
    np.testing.assert_array_equal(valid[clear], (base & (np.sqrt(lam) >= thr))[clear])

    counts[:10] = 2
    counts[10:20] = 4
    mu, lam_mid = neighbour_moments(nbrs, counts)
    assert np.isnan(mu[:10]).all() and (lam_mid[:10] == 0).all()
    ref4 = [np.linalg.eigvalsh(np.cov(q[:4].T, bias=True))[1] for q in nbrs[10:20]]
    np.testing.assert_allclose(lam_mid[10:20], ref4, rtol=1e-8, atol=1e-15)
    np.testing.assert_allclose(mu[20:], nbrs[20:].mean(axis=1), rtol=1e-12)
    np.testing.assert_allclose(lam_mid[20:], lam[20:], rtol=1e-8, atol=1e-15)
