"""Tests of adalio.lio.degeneracy on ray-cast and sampled synthetic scenes (numpy only)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from adalio.config import AdaptiveConfig
from adalio.errors import InputError
from adalio.lio.degeneracy import (
    DegeneracyDetector,
    consistent_projector,
    count_near,
    is_weak,
    localizability,
    mostly_horizontal,
    observable_projector,
    weak_directions,
)

GENERAL_LEAF_M = AdaptiveConfig().general.voxel_size_m
POINT_COV = 0.001


def xt32_rays(n_cols: int = 1000) -> np.ndarray:
    """Unit ray directions of a 32-beam LiDAR (elevations -16..+15 deg, 1 deg apart)."""
    az = np.linspace(0.0, 2.0 * np.pi, n_cols, endpoint=False)
    el = np.deg2rad(np.arange(-16.0, 16.0, 1.0))
    A, E = np.meshgrid(az, el)
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)


def raycast_box(lo, hi, origin, max_range_m: float = 100.0, blind_m: float = 0.5):
    """Returns of the 32-beam LiDAR at ``origin`` inside the box [lo, hi]: points, normals."""
    d = xt32_rays()
    lo_rel = np.asarray(lo, float) - origin
    hi_rel = np.asarray(hi, float) - origin
    with np.errstate(divide="ignore"):
        t_face = np.where(d > 0, hi_rel / d, np.where(d < 0, lo_rel / d, np.inf))
    axis = t_face.argmin(1)
    t = t_face.min(1)
    pts = d * t[:, None]
    rows = np.arange(len(pts))
    normals = np.zeros_like(pts)
    normals[rows, axis] = -np.sign(d[rows, axis])
    r = np.linalg.norm(pts, axis=1)
    keep = (r > blind_m) & (r < max_range_m)
    return pts[keep], normals[keep]


def voxel_centroids(points: np.ndarray, leaf_m: float) -> np.ndarray:
    keys = np.floor(points / leaf_m).astype(np.int64)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    sums = np.zeros((inv.max() + 1, 3))
    np.add.at(sums, inv, points)
    return sums / np.bincount(inv)[:, None]


def voxel_representatives(points: np.ndarray, normals: np.ndarray, leaf_m: float):
    keys = np.floor(points / leaf_m).astype(np.int64)
    _, idx = np.unique(keys, axis=0, return_index=True)
    return points[idx], normals[idx]


def pose_jacobian(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Rows [n^T, (p x n)^T] of lio-design.md §6.3 at identity attitude and extrinsic."""
    return np.hstack([normals, np.cross(points, normals)])


SCENES = {
    # name: (box lo, box hi, sensor origin, max range)
    "stairwell": ((-1.5, -1.5, -10.0), (1.5, 1.5, 10.0), (0.3, -0.2, 0.0), 100.0),
    "corridor": ((-100.0, -1.0, 0.0), (100.0, 1.0, 2.6), (0.0, 0.2, 1.3), 50.0),
    "hall": ((-20.0, -15.0, 0.0), (20.0, 15.0, 8.0), (1.0, 2.0, 1.5), 100.0),
}


def scene_scan(name: str):
    lo, hi, origin, max_range = SCENES[name]
    pts, nrm = raycast_box(lo, hi, np.asarray(origin, float), max_range_m=max_range)
    return pts, nrm


def cfg_with(**kw) -> AdaptiveConfig:
    return dataclasses.replace(AdaptiveConfig(tau_n=800, tau_near=500, d_xy_m=5.0,
                                              near_ratio=0.8, hold_scans=3), **kw)


# ----------------------------------------------------------------------------- count_near
def test_count_near_matches_brute_force_with_strict_edges():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-8, 8, size=(2000, 3))
    pts[:20, 0] = 5.0
    pts[20:40, 1] = -5.0
    brute = sum(1 for p in pts if abs(p[0]) < 5.0 and abs(p[1]) < 5.0)
    assert count_near(pts, 5.0) == brute
    assert count_near(np.zeros((0, 3)), 5.0) == 0
    with pytest.raises(InputError):
        count_near(np.zeros((4, 2)), 5.0)


# ----------------------------------------------------------------------------- detector
@pytest.mark.parametrize("detector", ["count", "near_ratio"])
def test_stairwell_scan_is_flagged_by_counts(detector):
    pts, _ = scene_scan("stairwell")
    down = voxel_centroids(pts, GENERAL_LEAF_M)
    dec = DegeneracyDetector(cfg_with(detector=detector)).check(down)
    assert dec.degenerate
    assert dec.trigger == ("count" if detector == "count" else "near_ratio")
    assert dec.n_down == len(down) and dec.n_near == count_near(down, 5.0)
    assert dec.params.voxel_size_m == AdaptiveConfig().degenerate.voxel_size_m


def test_corridor_scan_is_flagged_by_its_geometry():
    pts, nrm = scene_scan("corridor")
    p_down, n_down = voxel_representatives(pts, nrm, GENERAL_LEAF_M)
    cfg = cfg_with(detector="near_ratio")
    loc = localizability(pose_jacobian(p_down, n_down), POINT_COV)
    assert is_weak(loc, cfg)
    det = DegeneracyDetector(cfg)
    dec = det.check(p_down, weak_geometry=is_weak(loc, cfg))
    assert dec.degenerate and dec.trigger == "eigen"
    no_geo = DegeneracyDetector(cfg_with(detector="near_ratio", use_localizability_trigger=False))
    assert not no_geo.check(p_down, weak_geometry=True).degenerate


def test_open_hall_scan_is_not_flagged():
    pts, nrm = scene_scan("hall")
    p_down, n_down = voxel_representatives(pts, nrm, GENERAL_LEAF_M)
    cfg = cfg_with(detector="near_ratio")
    loc = localizability(pose_jacobian(p_down, n_down), POINT_COV)
    assert not is_weak(loc, cfg)
    dec = DegeneracyDetector(cfg).check(voxel_centroids(pts, GENERAL_LEAF_M),
                                        weak_geometry=is_weak(loc, cfg))
    assert not dec.degenerate and dec.trigger == ""
    assert dec.params.voxel_size_m == AdaptiveConfig().general.voxel_size_m


def test_count_reading_near_criterion_fires_in_open_hall():
    """The public code's N_near < tau_near fires where few returns lie within ±5 m (§9.2)."""
    pts, _ = scene_scan("hall")
    down = voxel_centroids(pts, GENERAL_LEAF_M)
    dec = DegeneracyDetector(cfg_with(detector="count")).check(down)
    assert dec.n_down >= 800 and dec.n_near < 500
    assert dec.degenerate and dec.trigger == "near"


def _cloud(n_near: int, n_far: int) -> np.ndarray:
    rng = np.random.default_rng(n_near * 7919 + n_far)
    near = rng.uniform(-4.9, 4.9, size=(n_near, 3))
    far = np.column_stack([rng.uniform(6, 30, n_far), rng.uniform(-30, 30, n_far),
                           rng.uniform(-2, 2, n_far)])
    return np.vstack([near, far])


def test_hold_keeps_degenerate_set_then_releases():
    det = DegeneracyDetector(cfg_with(detector="count", hold_scans=3))
    open_scan = _cloud(600, 2000)
    narrow_scan = _cloud(300, 0)
    seq = [open_scan, narrow_scan, open_scan, open_scan, open_scan, open_scan]
    out = [det.check(s) for s in seq]
    assert [d.trigger for d in out] == ["", "count", "hold", "hold", "", ""]
    assert [d.degenerate for d in out] == [False, True, True, True, False, False]
    gen, deg = det.cfg.general, det.cfg.degenerate
    assert [d.params for d in out] == [gen, deg, deg, deg, gen, gen]
    retrig = [det.check(s) for s in (narrow_scan, open_scan, narrow_scan, open_scan, open_scan,
                                     open_scan)]
    assert [d.trigger for d in retrig] == ["count", "hold", "count", "hold", "hold", ""]


def test_hold_of_one_scan_means_no_hold():
    det = DegeneracyDetector(cfg_with(hold_scans=1))
    assert [det.check(s).trigger for s in (_cloud(300, 0), _cloud(600, 2000))] == ["count", ""]


def test_fixed_mode_never_switches():
    det = DegeneracyDetector(cfg_with(mode="fixed"))
    pts, _ = scene_scan("stairwell")
    down = voxel_centroids(pts, GENERAL_LEAF_M)
    for _ in range(4):
        dec = det.check(down, weak_geometry=True)
        assert not dec.degenerate and dec.trigger == ""
        assert dec.params is det.cfg.general
        assert dec.n_down == len(down) and dec.n_near == count_near(down, 5.0)


def test_near_ratio_reading():
    det = DegeneracyDetector(cfg_with(detector="near_ratio", hold_scans=1))
    assert det.check(_cloud(500, 50)).trigger == "near_ratio"      # few, 91 % near
    assert det.check(_cloud(300, 300)).trigger == ""               # few, 50 % near
    assert det.check(_cloud(1000, 10)).trigger == ""               # many points
    assert det.check(np.zeros((0, 3))).trigger == "near_ratio"     # empty scan
    assert det.check(_cloud(0, 100)).trigger == ""                 # few but all far


def test_eigen_trigger_only_when_counts_do_not_fire():
    det = DegeneracyDetector(cfg_with(detector="count", hold_scans=2))
    assert det.check(_cloud(300, 0), weak_geometry=True).trigger == "count"
    assert det.check(_cloud(600, 2000), weak_geometry=True).trigger == "eigen"
    assert det.check(_cloud(600, 2000)).trigger == "hold"
    assert det.check(_cloud(600, 2000)).trigger == ""


# ----------------------------------------------------------------------------- localizability
def sample_planes(planes, n_per_plane: int, half_extent_m: float, rng) -> tuple:
    """Points uniformly on square patches of planes given as (point_on_plane, normal, u, v)."""
    pts, nrm = [], []
    for origin, normal, u, v in planes:
        a = rng.uniform(-half_extent_m, half_extent_m, size=(n_per_plane, 2))
        pts.append(np.asarray(origin) + a[:, :1] * u + a[:, 1:] * v)
        nrm.append(np.tile(normal, (n_per_plane, 1)))
    return np.vstack(pts), np.vstack(nrm)


def corridor_points(yaw_rad: float, rng, n: int = 400):
    """Infinite-like corridor (walls y=±1.1, floor z=-1.2, ceiling z=1.4) along yaw."""
    ex, ey, ez = np.eye(3)
    planes = [((0, 1.1, 0), -ey, ex, ez), ((0, -1.1, 0), ey, ex, ez),
              ((0, 0, -1.2), ez, ex, ey), ((0, 0, 1.4), -ez, ex, ey)]
    pts, nrm = sample_planes(planes, n, 1.0, rng)
    pts[:, 0] *= 15.0
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return pts @ R.T, nrm @ R.T, R @ ex


def box_room_points(rng, n: int = 400):
    ex, ey, ez = np.eye(3)
    planes = [((3.1, 0, 0), -ex, ey, ez), ((-2.7, 0, 0), ex, ey, ez),
              ((0, 2.4, 0), -ey, ex, ez), ((0, -2.2, 0), ey, ex, ez),
              ((0, 0, 1.6), -ez, ex, ey), ((0, 0, -1.3), ez, ex, ey)]
    return sample_planes(planes, n, 1.2, rng)


def test_information_matches_brute_force_sum():
    rng = np.random.default_rng(1)
    pts, nrm = box_room_points(rng, n=50)
    H = pose_jacobian(pts, nrm)
    loc = localizability(H, POINT_COV)
    brute = np.zeros((6, 6))
    for row in H:
        g = np.concatenate([row[3:], row[:3]])
        brute += np.outer(g, g) / POINT_COV
    np.testing.assert_allclose(loc.info, brute, rtol=1e-12, atol=1e-9)
    recon = loc.eigenvectors @ np.diag(loc.eigenvalues) @ loc.eigenvectors.T
    np.testing.assert_allclose(recon, brute, rtol=1e-9, atol=1e-6 * brute.max())
    assert loc.n_residuals == len(H)


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0])
def test_corridor_weakest_direction_is_axis_translation(yaw_deg):
    pts, nrm, axis = corridor_points(np.deg2rad(yaw_deg), np.random.default_rng(2))
    loc = localizability(pose_jacobian(pts, nrm), POINT_COV)
    assert loc.eigenvalues[0] < 1e-9 * loc.eigenvalues[1]
    expected = np.concatenate([np.zeros(3), axis])
    assert abs(abs(loc.weakest @ expected) - 1.0) < 1e-9
    assert loc.translation_ratio < 1e-12
    assert loc.score == pytest.approx(1.0, abs=1e-6)
    assert np.all(np.diff(loc.eigenvalues) >= 0)


def test_box_room_all_six_directions_constrained():
    rng = np.random.default_rng(3)
    pts, nrm = box_room_points(rng)
    loc = localizability(pose_jacobian(pts, nrm), POINT_COV)
    n = len(pts)
    assert loc.translation_ratio > 0.5
    assert loc.score < 0.3
    assert loc.eigenvalues[0] > 0.1 * n / 6 / POINT_COV
    assert np.abs(observable_projector(loc, 0.01) - np.eye(6)).max() < 1e-9
    loc_m = localizability(pose_jacobian(pts, nrm), POINT_COV, points_body=pts)
    assert loc_m.observability[0] > 0.1
    assert np.abs(observable_projector(loc_m, 0.01) - np.eye(6)).max() < 1e-9


def test_weakest_direction_sign_is_deterministic():
    pts, nrm, _ = corridor_points(0.3, np.random.default_rng(4))
    H = pose_jacobian(pts, nrm)
    a = localizability(H, POINT_COV).weakest
    b = localizability(-H[::-1], POINT_COV).weakest
    np.testing.assert_allclose(a, b, atol=1e-9)
    assert a[np.argmax(np.abs(a))] > 0


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0])
def test_projector_removes_exactly_the_corridor_axis(yaw_deg):
    pts, nrm, axis = corridor_points(np.deg2rad(yaw_deg), np.random.default_rng(5))
    H = pose_jacobian(pts, nrm)
    P = observable_projector(localizability(H, POINT_COV, points_body=pts), 0.01)
    u = np.concatenate([axis, np.zeros(3)])
    np.testing.assert_allclose(P, np.eye(6) - np.outer(u, u), atol=1e-8)
    np.testing.assert_allclose(P @ P, P, atol=1e-8)
    np.testing.assert_allclose(H @ P, H, atol=1e-6)


def test_raycast_corridor_point_metric_keeps_roll_and_removes_axis():
    """Roll has a ~1 m lever arm against ~10 m for yaw: only the point metric keeps it."""
    pts, nrm = scene_scan("corridor")
    p_down, n_down = voxel_representatives(pts, nrm, GENERAL_LEAF_M)
    H = pose_jacobian(p_down, n_down)
    with_pts = localizability(H, POINT_COV, points_body=p_down)
    assert with_pts.observability[0] < 1e-9 and with_pts.observability[1] > 0.05
    P = observable_projector(with_pts, 0.01)
    np.testing.assert_allclose(P, np.diag([0.0, 1, 1, 1, 1, 1]), atol=1e-6)
    fallback = localizability(H, POINT_COV)
    assert fallback.observability[1] < 0.01
    P_fb = observable_projector(fallback, 0.01)
    assert np.linalg.matrix_rank(P_fb, tol=1e-6) == 4
    _, sv, vt = np.linalg.svd(P_fb)
    null = vt[sv < 1e-6]
    assert np.abs(null[:, 3]).max() > 0.95


def test_projector_on_coupled_weak_direction_is_oblique_and_idempotent():
    rng = np.random.default_rng(6)
    pts, nrm = box_room_points(rng, n=60)
    H = pose_jacobian(pts, nrm)
    w = rng.normal(size=6)
    w /= np.linalg.norm(w)
    H_weak = H - np.outer(H @ w, w)
    loc = localizability(H_weak, POINT_COV)
    P = observable_projector(loc, 1e-6)
    np.testing.assert_allclose(P @ w, 0.0, atol=1e-8)
    np.testing.assert_allclose(P @ P, P, atol=1e-8)
    np.testing.assert_allclose(H_weak @ P, H_weak, atol=1e-6)
    assert np.linalg.matrix_rank(P, tol=1e-6) == 5


def test_empty_scan_localizability():
    loc = localizability(np.zeros((0, 6)), POINT_COV)
    assert loc.score == 1.0 and loc.translation_ratio == 0.0 and loc.n_residuals == 0
    assert not np.any(loc.info) and not np.any(loc.eigenvalues)
    assert not np.any(observable_projector(loc, 0.01))
    assert is_weak(loc, AdaptiveConfig())
    np.testing.assert_array_equal(observable_projector(loc, 0.0), np.eye(6))


def test_bad_inputs_raise_input_error():
    with pytest.raises(InputError):
        localizability(np.zeros((5, 3)), POINT_COV)
    with pytest.raises(InputError):
        localizability(np.ones((5, 6)), 0.0)
    loc = localizability(np.eye(6), POINT_COV)
    with pytest.raises(InputError):
        observable_projector(loc, 1.5)
    with pytest.raises(InputError):
        DegeneracyDetector(AdaptiveConfig()).check(np.zeros(3))


@settings(max_examples=60, deadline=None)
@given(st.integers(min_value=1, max_value=40), st.integers(min_value=0, max_value=2**31 - 1),
       st.floats(min_value=0.0, max_value=0.5))
def test_localizability_invariants_on_random_jacobians(m, seed, ratio):
    rng = np.random.default_rng(seed)
    H = rng.normal(size=(m, 6)) * rng.uniform(0.01, 10.0, size=6)
    loc = localizability(H, POINT_COV)
    assert 0.0 <= loc.score <= 1.0 and 0.0 <= loc.translation_ratio <= 1.0
    assert np.all(np.diff(loc.eigenvalues) >= 0) and np.all(loc.eigenvalues >= 0)
    np.testing.assert_allclose(np.linalg.norm(loc.weakest), 1.0, atol=1e-9)
    for k in range(6):  # every eigenvector's largest entry is positive, as the weakest's
        v = loc.eigenvectors[:, k]
        assert v[np.argmax(np.abs(v))] >= 0
    P = observable_projector(loc, ratio)
    np.testing.assert_allclose(P @ P, P, atol=1e-6 * max(1.0, np.abs(P).max()))
    if m < 3:
        assert loc.translation_ratio < 1e-9
    # without the observability metric: the same spectrum to the bit, and nothing that could
    # pass for a metric
    lean = localizability(H, POINT_COV, observability=False)
    for name in ("info", "eigenvalues", "eigenvectors", "weakest", "translation_eigenvalues"):
        np.testing.assert_array_equal(getattr(lean, name), getattr(loc, name))
    assert (lean.score, lean.translation_ratio) == (loc.score, loc.translation_ratio)
    assert lean.scaling is None and lean.observability is None
    if np.any(H):
        with pytest.raises(ValueError, match="observability=False"):
            observable_projector(lean, max(ratio, 0.01))


def test_weak_directions_move_points_by_the_step_and_follow_the_weakest_eigenvectors():
    rng = np.random.default_rng(11)
    pts, nrm, axis = corridor_points(0.4, rng)
    loc = localizability(pose_jacobian(pts, nrm), POINT_COV, points_body=pts)
    step = 0.05
    dirs = weak_directions(loc, 3, step)
    assert dirs.shape == (3, 6)
    for d in dirs:
        dp, dth = d[:3], d[3:]
        motion = dp[None, :] + np.cross(dth[None, :], pts)
        rms_without_cross_term = np.sqrt(dp @ dp + np.mean(np.sum(np.cross(dth, pts) ** 2, 1)))
        assert rms_without_cross_term == pytest.approx(step, rel=1e-9)
        assert np.isfinite(motion).all()
    u = np.concatenate([axis, np.zeros(3)])
    assert abs(dirs[0] @ u) == pytest.approx(step, rel=1e-6)


def test_consistent_projector_drops_only_directions_that_do_not_restore():
    rng = np.random.default_rng(12)
    pts, nrm = box_room_points(rng)
    loc = localizability(pose_jacobian(pts, nrm), POINT_COV, points_body=pts)
    dirs = weak_directions(loc, 3, 0.05)
    P = consistent_projector(loc, 0.0, dirs, np.array([0.1, 0.9, np.nan]), 0.6)
    np.testing.assert_allclose(P @ P, P, atol=1e-9)
    np.testing.assert_allclose(P @ dirs[0], 0.0, atol=1e-9)
    np.testing.assert_allclose(P @ dirs[1], dirs[1], atol=1e-9)
    np.testing.assert_allclose(P @ dirs[2], 0.0, atol=1e-9)
    assert np.linalg.matrix_rank(P, tol=1e-6) == 4
    np.testing.assert_allclose(consistent_projector(loc, 0.0, dirs, np.ones(3), 0.6), np.eye(6),
                               atol=1e-9)


def test_projectors_keep_mostly_horizontal_translations():
    """§5: with ``keep_horizontal`` a probed direction that does not restore is still held
    when it is mostly a vertical translation or a rotation, and not when it is mostly a
    horizontal translation; the eigenvalue test keeps a weak horizontal translation too."""
    rng = np.random.default_rng(12)
    pts, nrm = box_room_points(rng)
    loc = localizability(pose_jacobian(pts, nrm), POINT_COV, points_body=pts)
    W = loc.scaling
    dirs = np.array([
        [0.04, 0.03, 0.0, 0.0, 0.0, 0.0],    # horizontal translation
        [0.01, 0.0, 0.049, 0.0, 0.0, 0.0],   # mostly vertical
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.02],     # a rotation about the vertical
    ])
    # brute force: the mean square motion of the scan points, without the cross term
    for d, horizontal in zip(dirs, (True, False, False)):
        ms = d[:3] @ d[:3] + np.mean(np.sum(np.cross(d[3:], pts) ** 2, axis=1))
        assert (d[0] ** 2 + d[1] ** 2 > 0.5 * ms) == horizontal
        assert mostly_horizontal(W, d) == horizontal
        # the same with the world's up given: along z, and turned with the scene onto its side
        assert mostly_horizontal(W, d, np.array([0.0, 0.0, 1.0])) == horizontal
        Q = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # z -> -y
        T = np.kron(np.eye(2), Q)
        side_pts = pts @ Q.T
        W_side = localizability(pose_jacobian(side_pts, nrm @ Q.T), POINT_COV,
                                points_body=side_pts).scaling
        assert mostly_horizontal(W_side, T @ d, Q @ np.array([0.0, 0.0, 1.0])) == horizontal
    never = np.zeros(3)
    held_all = consistent_projector(loc, 0.0, dirs, never, 0.6)
    kept = consistent_projector(loc, 0.0, dirs, never, 0.6, keep_horizontal=True)
    for P in (held_all, kept):
        np.testing.assert_allclose(P @ P, P, atol=1e-9)
    for d in dirs:
        np.testing.assert_allclose(held_all @ d, 0.0, atol=1e-9)
    # the horizontal one is not held: the projector is the one of the other two alone
    np.testing.assert_allclose(kept, consistent_projector(loc, 0.0, dirs[1:], never[1:], 0.6),
                               atol=1e-12)
    assert np.linalg.norm(kept @ dirs[0]) > 0.5 * np.linalg.norm(dirs[0])
    assert np.linalg.matrix_rank(kept, tol=1e-6) == 4


def test_observable_projector_keeps_a_weak_horizontal_axis():
    """A corridor (two side walls, floor, ceiling, no end wall): its axis is the weakest
    direction and a horizontal translation. The eigenvalue test removes it, unless
    ``keep_horizontal``; the rest of the projector is unchanged."""
    rng = np.random.default_rng(5)
    n = 3000
    y = rng.uniform(-8.0, 8.0, n)
    side = rng.integers(0, 4, n)
    pts = np.stack([np.where(side == 0, -1.0, np.where(side == 1, 1.0, rng.uniform(-1, 1, n))),
                    y, np.where(side == 2, -1.2, np.where(side == 3, 1.3, rng.uniform(-1.2, 1.3,
                                                                                     n)))], 1)
    nrm = np.zeros((n, 3))
    nrm[side < 2, 0] = 1.0
    nrm[side >= 2, 2] = 1.0
    H = pose_jacobian(pts, nrm)
    H[:, 1] += 0.003 * rng.standard_normal(n)  # a trace of along-axis information
    loc = localizability(H, POINT_COV, points_body=pts)
    along = np.array([0.0, 0.05, 0.0, 0.0, 0.0, 0.0])
    P = observable_projector(loc, 0.01)
    Pk = observable_projector(loc, 0.01, keep_horizontal=True)
    np.testing.assert_allclose(P @ along, 0.0, atol=1e-4)
    np.testing.assert_allclose(Pk @ along, along, atol=1e-4)
    np.testing.assert_allclose(Pk @ Pk, Pk, atol=1e-9)
    assert np.linalg.matrix_rank(Pk, tol=1e-6) == np.linalg.matrix_rank(P, tol=1e-6) + 1
