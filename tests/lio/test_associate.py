"""The fused search + fit (adalio.lio.associate) against the three-step path it replaces:
IVox.knn, then fit_planes with the search-radius gate, then neighbour_moments. Same inputs must
give the same outputs bit for bit, on a map with planes, clutter and empty space."""

import numpy as np
import pytest

from adalio.lio import associate as assoc_mod
from adalio.lio.associate import associate
from adalio.lio.ivox import IVox
from adalio.lio.plane import elevation_spread, fit_planes, neighbour_moments


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


def test_elevation_spread_equals_brute_force() -> None:
    rng = np.random.default_rng(5)
    for _ in range(50):
        nbrs = rng.normal(0, 3, (8, 3))
        cnt = int(rng.integers(2, 9))
        origin = rng.normal(0, 1, 3)
        axis = rng.normal(0, 1, 3)
        axis /= np.linalg.norm(axis)
        u = nbrs[:cnt] - origin
        el = np.arcsin(u @ axis / np.linalg.norm(u, axis=1))
        assert elevation_spread(nbrs, cnt, origin, axis) == pytest.approx(np.ptp(el), abs=1e-12)
    # neighbours at the origin are skipped; fewer than two others judge nothing
    assert elevation_spread(np.zeros((3, 3)), 3, np.zeros(3), np.array([0.0, 0, 1])) == np.inf


def _ring_on_floor(origin: np.ndarray, elevation_deg: float, rng: np.random.Generator,
                   azimuth_deg: np.ndarray, roughness_m: float = 0.01) -> np.ndarray:
    """Where the rays of one ring (a cone of one elevation about the vertical) from ``origin``
    hit a rough floor (height N(0, roughness_m) per ray): the points lie on the cone."""
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    u = np.c_[np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.full(a.shape, np.sin(e))]
    z = rng.normal(0.0, roughness_m, a.shape)
    return origin + ((z - origin[2]) / u[:, 2])[:, None] * u


def test_one_ring_test_rejects_the_cone_tangent_planes_of_one_ring() -> None:
    """A LiDAR 1.5 m over a rough floor (1 cm), two of its rings in the map: where a
    query's neighbours all come from one ring they lie on its cone, and the plane fitted to them
    contains the rays (the cone's tangent), tilted from the floor by the ring's elevation,
    whatever the floor does. Seen from the sensor 0.3 m further on (where the filter would judge
    them), the one-ring test rejects exactly those planes (which ring laid down each neighbour
    is known here) and keeps the planes fitted across both rings, which lie near the floor."""
    rng = np.random.default_rng(11)
    o_map = np.array([0.0, 0.0, 1.5])
    o_now = o_map + [0.3, 0.0, 0.0]
    up = np.array([0.0, 0.0, 1.0])
    az = np.arange(-30.0, 30.0, 1.0)
    rings = [_ring_on_floor(o_map, e, rng, az) for e in (-9.0, -8.7)]  # 33 cm apart
    ring_of = {tuple(p): r for r, pts in enumerate(rings) for p in pts}
    ivox = IVox(resolution_m=0.5, nearby_type=18, max_points_per_voxel=32, cell_m=0.05)
    ivox.add_points(np.vstack(rings))
    q = _ring_on_floor(o_now, -8.85, rng, np.arange(-20.0, 20.0, 0.25))  # a later sweep's ring
    args = (ivox, q, 5, 5.0, 3, 3.0, 0.1, "pca", 0.0)
    plain = associate(*args, keep_neighbours=True)
    got = associate(*args, ring_origin=o_now, ring_axis=up, ring_max_deg=0.1)
    both = np.array([len({ring_of[tuple(p)] for p in nb[:c]}) == 2
                     for nb, c in zip(plain.neighbours, plain.counts)])
    one = plain.valid & ~both
    assert one.sum() >= 20 and (plain.valid & both).sum() >= 20  # the scene has both kinds
    np.testing.assert_array_equal(got.valid, plain.valid & both)
    tilt = np.degrees(np.arccos(np.abs(plain.normals @ up)))
    rays = plain.mu - o_map
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    assert np.median(np.abs(np.sum(plain.normals[one] * rays[one], axis=1))) < 0.02  # hold rays
    assert np.median(tilt[one]) == pytest.approx(9.0, abs=1.0)  # the cone's tangent
    assert np.median(tilt[got.valid]) < 3.0  # across two rings: near the floor
