"""The fused search + fit (adalio.lio.associate) against the three-step path it replaces:
IVox.knn, then fit_planes with the search-radius gate, then neighbour_moments. Same inputs must
give the same outputs bit for bit, on a map with planes, clutter and empty space."""

import numpy as np
import pytest

from adalio.lio import associate as assoc_mod
from adalio.lio.associate import associate
from adalio.lio.ivox import IVox
from adalio.lio.plane import fit_planes, neighbour_moments


def _room_map(rng: np.random.Generator) -> IVox:
    """A 6 x 4 x 3 m box (floor, ceiling, walls) sampled every ~5 cm with 1 cm noise, plus a
    cloud of clutter points inside."""
    u, v = rng.uniform(0, 1, (2, 4000))
    faces = [np.c_[6 * u, 4 * v, 0 * u], np.c_[6 * u, 4 * v, 3 + 0 * u],
             np.c_[6 * u, 0 * u, 3 * v], np.c_[6 * u, 4 + 0 * u, 3 * v],
             np.c_[0 * u, 4 * u, 3 * v], np.c_[6 + 0 * u, 4 * u, 3 * v]]
    pts = np.vstack(faces + [rng.uniform([1, 1, 0.5], [5, 3, 2.5], (800, 3))])
    pts += rng.normal(0, 0.01, pts.shape)
    ivox = IVox(resolution_m=0.5, nearby_type=18, max_points_per_voxel=32, cell_m=0.05)
    ivox.add_points(pts)
    return ivox


def _three_step(ivox, q, k, max_range_m, min_nb, radius_m, margin_m, method, min_extent_m):
    nbrs, counts, dist2 = ivox.knn(q, k, max_range_m)
    farthest2 = dist2[np.arange(len(q)), np.maximum(counts - 1, 0)]
    near = (counts >= min_nb) & (farthest2 <= radius_m ** 2)
    normals, d, valid = fit_planes(nbrs, counts, min_nb, margin_m, method, min_extent_m)
    mu, lam_mid = neighbour_moments(nbrs, counts)
    return normals, d, valid & near, counts, mu, lam_mid, nbrs[:, 0]


@pytest.mark.parametrize("method", ["ls", "pca"])
@pytest.mark.parametrize("parallel", [False, True])
def test_fused_association_equals_search_then_fit(method: str, parallel: bool,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(3)
    ivox = _room_map(rng)
    # queries on the faces, inside, and far outside (no neighbours)
    q = np.vstack([ivox.points()[rng.choice(ivox.num_points, 1500)] + rng.normal(0, 0.05, (1500, 3)),
                   rng.uniform([-1, -1, -1], [7, 5, 4], (1500, 3)),
                   rng.uniform(20, 30, (50, 3))])
    monkeypatch.setattr(assoc_mod, "PARALLEL_MIN_QUERIES", 1 if parallel else 10**9)
    for k, min_nb, radius_m, margin_m, min_ext in [(5, 3, 3.0, 0.05, 0.05), (8, 5, 0.3, 0.02, 0.0)]:
        ref = _three_step(ivox, q, k, 5.0, min_nb, radius_m, margin_m, method, min_ext)
        got = associate(ivox, q, k, 5.0, min_nb, radius_m, margin_m, method, min_ext)
        for name, a, b in zip(("normals", "d", "valid", "counts", "mu", "lam_mid", "nearest"),
                              ref, (got.normals, got.d, got.valid, got.counts, got.mu,
                                    got.lam_mid, got.nearest)):
            np.testing.assert_array_equal(a, b, err_msg=name)
        # the scene exercises every branch: valid planes, rejected rows, rows with no neighbour
        assert 0 < got.valid.sum() < len(q)
        assert (got.counts == 0).sum() >= 50


@pytest.mark.parametrize("parallel", [False, True])
def test_warm_started_search_equals_a_cold_one(parallel: bool,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A search started from the same rows' previous neighbours returns what a cold search
    returns, bit for bit: rows moved by millimetres (same voxel), by decimetres (many cross into
    another voxel), and on a grid map whose equidistant neighbours make ties."""
    rng = np.random.default_rng(9)
    monkeypatch.setattr(assoc_mod, "PARALLEL_MIN_QUERIES", 1 if parallel else 10**9)
    grid = np.stack(np.meshgrid(*[np.arange(0.0, 2.0, 0.1)] * 2, [0.0], indexing="ij"),
                    -1).reshape(-1, 3)
    grid_map = IVox(resolution_m=0.5, nearby_type=18, max_points_per_voxel=32)
    grid_map.add_points(grid)
    cases = [(_room_map(rng), None), (grid_map, grid)]
    n_crossed = 0
    for ivox, on_grid in cases:
        if on_grid is None:
            q0 = np.vstack([ivox.points()[rng.choice(ivox.num_points, 1500)]
                            + rng.normal(0, 0.05, (1500, 3)),
                            rng.uniform([-1, -1, -1], [7, 5, 4], (500, 3))])
        else:  # grid nodes and cell centres: many neighbours at exactly equal distances
            q0 = np.vstack([on_grid[::3], on_grid[::5] + [0.05, 0.05, 0.0]])
        first = associate(ivox, q0, 5, 5.0, 3, 3.0, 0.05, keep_neighbours=True)
        for step in (0.003, 0.02, 0.2):
            if on_grid is None:
                q1 = q0 + rng.normal(0, step, q0.shape)
            else:  # move along the grid, keeping the ties
                q1 = q0 + np.array([step, 0.0, 0.0])
            cold = associate(ivox, q1, 5, 5.0, 3, 3.0, 0.05, keep_neighbours=True)
            warm = associate(ivox, q1, 5, 5.0, 3, 3.0, 0.05, keep_neighbours=True,
                             warm_from=first)
            for name in ("normals", "d", "valid", "counts", "mu", "lam_mid", "nearest",
                         "neighbours"):
                np.testing.assert_array_equal(getattr(warm, name), getattr(cold, name),
                                              err_msg=f"{name} step {step}")
            n_crossed += int(np.any(np.round(q1 / 0.5) != np.round(q0 / 0.5), axis=1).sum())
    assert n_crossed > 100


def test_empty_map_and_empty_queries() -> None:
    ivox = IVox(resolution_m=0.5, nearby_type=18, max_points_per_voxel=32)
    got = associate(ivox, np.zeros((4, 3)), 5, 5.0, 3, 3.0, 0.05)
    assert not got.valid.any() and (got.counts == 0).all() and np.isnan(got.nearest).all()
    ivox.add_points(np.random.default_rng(0).uniform(0, 1, (100, 3)))
    got = associate(ivox, np.zeros((0, 3)), 5, 5.0, 3, 3.0, 0.05)
    assert got.valid.shape == (0,)


def _support_mask(nbrs, counts, normals, mu, q):
    """Brute force of plane.within_support: in-plane offset of q from its neighbours' centroid
    against the farthest neighbour's projection on it."""
    o = q - mu
    o = o - np.sum(o * normals, axis=1, keepdims=True) * normals
    proj = np.einsum("mkj,mj->mk", nbrs - mu[:, None, :], o)
    proj[np.arange(nbrs.shape[1])[None, :] >= counts[:, None]] = -np.inf
    reach = np.maximum(proj.max(axis=1), 0.0)
    o2 = np.sum(o * o, axis=1)
    return o2 <= reach, o2 - reach


@pytest.mark.parametrize("parallel", [False, True])
def test_support_test_equals_brute_force(parallel: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(5)
    ivox = _room_map(rng)
    q = np.vstack([ivox.points()[rng.choice(ivox.num_points, 1500)] + rng.normal(0, 0.05, (1500, 3)),
                   rng.uniform([-1, -1, -1], [7, 5, 4], (1500, 3))])
    monkeypatch.setattr(assoc_mod, "PARALLEL_MIN_QUERIES", 1 if parallel else 10**9)
    plain = associate(ivox, q, 5, 5.0, 3, 3.0, 0.05, "ls", 0.05)
    got = associate(ivox, q, 5, 5.0, 3, 3.0, 0.05, "ls", 0.05, support_test=True)
    for name in ("normals", "d", "counts", "mu", "lam_mid", "nearest"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(got, name), err_msg=name)
    nbrs, counts, _ = ivox.knn(q, 5, 5.0)
    inside, margin = _support_mask(nbrs, counts, plain.normals, plain.mu, q)
    expect = plain.valid & inside
    differ = got.valid != expect
    assert np.all(np.abs(margin[differ]) < 1e-12)  # only rounding ties may differ
    # the test removes some planes and keeps most: both branches are exercised
    assert 0 < (plain.valid & ~got.valid).sum() < 0.5 * plain.valid.sum()
    assert not (got.valid & ~plain.valid).any()


def _cylinder_map(radius_m: float, angle_max_rad: float) -> IVox:
    """A vertical cylinder wall (axis z through the origin) sampled every 2 cm along the arc from
    angle 0 to angle_max and every 4 cm in height: a curved wall whose map ends at
    a leading edge."""
    ang = np.arange(0.0, angle_max_rad, 0.02 / radius_m)
    z = np.arange(0.0, 2.0, 0.04)
    a, zz = np.meshgrid(ang, z)
    pts = np.c_[radius_m * np.cos(a.ravel()), radius_m * np.sin(a.ravel()), zz.ravel()]
    ivox = IVox(resolution_m=0.5, nearby_type=18, max_points_per_voxel=1000, cell_m=0.02)
    ivox.add_points(pts)
    return ivox


def test_support_test_rejects_extrapolated_planes_on_a_curved_wall() -> None:
    """Queries on the true wall: inside the mapped arc the fitted planes fit them; beyond its
    edge the plane of the last mapped strip is extrapolated and misses the true wall by a
    distance that grows with the gap. The support test keeps the first, drops the second."""
    radius = 1.3
    edge = np.deg2rad(60.0)
    ivox = _cylinder_map(radius, edge)
    inner = np.deg2rad(np.linspace(15.0, 45.0, 40))
    outer = edge + np.deg2rad(np.linspace(1.5, 3.0, 40))  # 3-7 cm beyond the mapped arc
    z = np.full(40, 1.02)  # between two sampled rows: a query level with its outermost neighbours
    # lies on the boundary of their span, where rounding decides
    resid = {}
    for name, ang in (("inner", inner), ("outer", outer)):
        q = np.c_[radius * np.cos(ang), radius * np.sin(ang), z]
        plain = associate(ivox, q, 5, 5.0, 3, 3.0, 0.05, "pca", 0.0)
        got = associate(ivox, q, 5, 5.0, 3, 3.0, 0.05, "pca", 0.0, support_test=True)
        assert plain.valid.all()  # without the test every query has a plane
        assert got.valid.all() if name == "inner" else not got.valid.any()
        resid[name] = np.abs(np.sum(q * plain.normals, axis=1) + plain.d)  # true wall point
    # interpolated planes pass (nearly) through the true wall; extrapolated ones miss it, by more
    # the farther beyond the edge
    assert resid["outer"].min() > 2 * resid["inner"].max()
    assert resid["outer"][-1] > 2 * resid["outer"][0]
