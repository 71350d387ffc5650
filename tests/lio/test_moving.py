"""Where a sweep saw through (``lio/moving.py``), against exact ray geometry: a spinning LiDAR in
a box room, its rays cast analytically."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from adalio.config import MapConfig
from adalio.lio.ivox import IVox
from adalio.lio.moving import (
    MovingPoints,
    _atan2,
    in_free_space,
    near_any,
    nearest_image,
    range_image,
    seen_through,
)
from adalio.sim.people import People

ROOM_LO = np.array([-6.0, -4.0, -1.4])
ROOM_HI = np.array([9.0, 5.0, 1.6])
ELEVATIONS_DEG = 15.0 - np.arange(32.0)  # the XT-32's rings
PIXEL = np.radians(1.0)
MARGIN_M, FRACTION = 0.1, 0.01
BODY_M = 0.3  # map.moving_body_m, the default


def wall_distance(origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance from ``origin`` (inside the room) along unit ``dirs`` to the room's walls."""
    with np.errstate(divide="ignore"):
        t = np.where(dirs > 0, (ROOM_HI - origin) / dirs, (ROOM_LO - origin) / dirs)
    return np.min(np.where(dirs != 0, t, np.inf), axis=1)


def sweep(origin: np.ndarray, columns: int = 512, feet: np.ndarray | None = None) -> np.ndarray:
    """Returns (LiDAR frame = world axes at ``origin``) of one noise-free sweep in the room, with
    a person (the simulator's upright cylinder) standing at ``feet`` if given."""
    az = np.linspace(-np.pi, np.pi, columns, endpoint=False) + 0.3 * np.pi / columns
    el = np.radians(ELEVATIONS_DEG)
    d = np.stack(np.broadcast_arrays(np.cos(el)[None] * np.cos(az)[:, None],
                                     np.cos(el)[None] * np.sin(az)[:, None],
                                     np.sin(el)[None]), axis=-1).reshape(-1, 3)
    r = wall_distance(origin, d)
    if feet is not None:
        person = People(np.zeros((2, 3)), np.zeros(1), np.zeros(1), np.zeros(1))
        origins = np.repeat(origin[None], len(d), axis=0)
        r = np.minimum(r, person.cast(origins, d, np.broadcast_to(feet, (len(d), 1, 3)))[0])
    return d * r[:, None]


def random_directions(rng: np.random.Generator, n: int, el_deg: tuple[float, float]):
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.radians(rng.uniform(*el_deg, n))
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def test_fast_atan2_is_within_its_stated_error():
    rng = np.random.default_rng(0)
    yx = np.vstack([rng.normal(size=(5000, 2)), [[0, 1], [1, 0], [0, -1], [-1, 0], [1, 1],
                                                 [-1, -1], [0, 0]]])
    got = np.array([_atan2(y, x) for y, x in yx])
    want = np.arctan2(yx[:, 0], yx[:, 1])
    err = np.abs(np.angle(np.exp(1j * (got - want))))
    assert err.max() < 2.1e-4


def test_free_space_is_where_the_rays_passed_and_only_there():
    """Points well inside the room, within the rings' span, lie in free space; no point on a
    wall or behind one ever does, nor one above the top ring or below the bottom ring (no ray
    passed there), whatever the sensor's position in the world."""
    rng = np.random.default_rng(1)
    origin = np.array([1.0, 0.5, 0.2])
    R = np.eye(3)
    img = range_image(sweep(origin), PIXEL)
    d = random_directions(rng, 20000, (-14.0, 13.0))
    wall = wall_distance(origin, d)
    inside = origin + d * (rng.uniform(0.2, 0.8, len(d)) * wall)[:, None]
    free = in_free_space(inside, R, origin, img, PIXEL, MARGIN_M, FRACTION)
    assert free.mean() > 0.97
    on_wall = origin + d * wall[:, None]
    behind = origin + d * (wall + rng.uniform(0.05, 3.0, len(d)))[:, None]
    for pts in (on_wall, behind):
        assert not in_free_space(pts, R, origin, img, PIXEL, MARGIN_M, FRACTION).any()
    for band in ((17.5, 40.0), (-40.0, -18.5)):  # beyond the top and the bottom ring
        d = random_directions(rng, 5000, band)
        pts = origin + d * (0.5 * wall_distance(origin, d))[:, None]
        assert not in_free_space(pts, R, origin, img, PIXEL, MARGIN_M, FRACTION).any()
    # the same sweep seen from a turned and moved sensor
    yaw = 0.7
    R_WL = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0],
                     [0.0, 0.0, 1.0]])
    p_WL = np.array([3.0, -2.0, 0.5])
    moved = in_free_space((inside - origin) @ R_WL.T + p_WL, R_WL, p_WL, img, PIXEL, MARGIN_M,
                          FRACTION)
    np.testing.assert_array_equal(moved, free)


def test_a_thin_gap_between_rays_is_not_free_space():
    """A post the rays straddle (a 2 cm rod at 6 m, between two columns 0.7° apart): a point on
    it is not in free space, since every ray beside it is checked, not the one through it."""
    origin = np.zeros(3)
    pts = sweep(origin + [1.0, 0.5, 0.2])
    rng = np.random.default_rng(2)
    img = range_image(pts, PIXEL)
    # a point just in front of a return, nearer than the margin: not free
    sample = pts[rng.choice(len(pts), 2000, replace=False)]
    r = np.linalg.norm(sample, axis=1)
    nearer = sample * (1.0 - 0.5 * (MARGIN_M + FRACTION * r) / r)[:, None]
    assert not in_free_space(nearer, np.eye(3), origin, img, PIXEL, MARGIN_M, FRACTION).any()


def panel_sweep(origin: np.ndarray, edge_y: float, columns: int = 512) -> np.ndarray:
    """As :func:`sweep`, with a panel in the plane x = 3 m from y = -4 m to its edge at
    ``edge_y``, floor to ceiling (a wall's end, seen with the room's far wall beyond it)."""
    pts = sweep(origin, columns)
    d = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    ahead = d[:, 0] > 0
    t = np.full(len(d), np.inf)
    t[ahead] = (3.0 - origin[0]) / d[ahead, 0]
    hit = ahead & (origin[1] + np.where(ahead, t, 0.0) * d[:, 1] < edge_y)
    hit &= t < np.linalg.norm(pts, axis=1)
    pts[hit] = d[hit] * t[hit, None]
    return pts


def test_seen_through_is_free_space_with_no_return_next_to_it():
    """``seen_through`` against brute force: free space (``in_free_space``) and no return kept
    in ``nearest_image`` (each pixel's nearest, by scipy's exact neighbour search) within the
    margin, its fraction and one pixel of the point's range; points spread through the room,
    near its walls and the panel's edge, from a turned and moved sensor. With ``behind`` false
    only the returns beside or in front of the point count (range at most the point's plus the
    margin): some points have returns within that reach only behind them, and only then are
    they seen through."""
    rng = np.random.default_rng(7)
    origin = np.array([1.0, 0.5, 0.2])
    pts_l = panel_sweep(origin, 0.3)
    near = nearest_image(pts_l, PIXEL)
    img = range_image(pts_l, PIXEL)
    returns = near[near[..., 3] > 0][:, :3]
    assert len(returns) > 0.9 * np.unique(np.round(pts_l, 9), axis=0).shape[0] / 2
    d = random_directions(rng, 20000, (-14.0, 13.0))
    r_wall = np.linalg.norm(pts_l, axis=1).max()
    inside = d * rng.uniform(0.3, 1.0, (len(d), 1)) * r_wall
    # and some just off the returns: beside the panel's edge, in front of the walls
    close = pts_l[rng.choice(len(pts_l), 4000)] + rng.normal(0.0, 0.15, (4000, 3))
    cand = np.vstack([inside, close])
    yaw = -0.4
    R_WL = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0],
                     [0.0, 0.0, 1.0]])
    p_WL = np.array([-2.0, 4.0, 1.0])
    world = cand @ R_WL.T + p_WL
    got = seen_through(world, R_WL, p_WL, img, near, PIXEL, MARGIN_M, FRACTION, True)
    free = in_free_space(world, R_WL, p_WL, img, PIXEL, MARGIN_M, FRACTION)
    r = np.linalg.norm(cand, axis=1)
    reach = MARGIN_M + (FRACTION + PIXEL) * r
    tree = cKDTree(returns)
    next_to = tree.query(cand)[0] < reach
    np.testing.assert_array_equal(got, free & ~next_to)
    assert got.sum() > 5000 and (free & next_to).sum() > 200
    r_returns = np.linalg.norm(returns, axis=1)
    beside = np.zeros(len(cand), bool)
    for i in np.flatnonzero(free & next_to):
        close = tree.query_ball_point(cand[i], np.nextafter(reach[i], 0.0))
        beside[i] = (r_returns[close] <= r[i] + MARGIN_M).any()
    got = seen_through(world, R_WL, p_WL, img, near, PIXEL, MARGIN_M, FRACTION, False)
    np.testing.assert_array_equal(got, free & ~beside)
    assert (free & beside).sum() > 200 and (free & next_to & ~beside).sum() > 200


def test_a_surface_edge_placed_off_is_not_seen_through():
    """The end of a wall (a panel's edge), its map points placed 5-12 cm beyond it (the poses
    in between drifted): the rays beside them pass the edge to the far wall, so they lie in free
    space, but the panel's returns next to them keep them (``surface_check``); map points half a
    metre beyond, where nothing of the sweep is, are seen through either way."""
    cfg = MapConfig()
    origin = np.array([1.0, 0.5, 0.2])
    sweep_l = panel_sweep(origin, 0.0)
    z = np.linspace(-0.4, 0.4, 9)
    for off_m, kept in ((0.05, True), (0.08, True), (0.12, True), (0.5, False)):
        edge = np.column_stack([np.full_like(z, 3.0), np.full_like(z, off_m), z])
        carved = {}
        for check in (True, False):
            movers = MovingPoints.from_config(cfg)
            movers.surface_check = check
            ivox = IVox.from_config(cfg)
            movers.stored(edge[ivox.add_points(edge, 0.05)], 0)
            carved[check] = movers.carve(ivox, movers.image(sweep_l), np.eye(3),
                                         origin, 100_000_000)
        assert carved[False] >= len(z) - 2, (off_m, carved)  # measured 8-9 of 9
        assert carved[True] == (0 if kept else carved[False]), (off_m, carved)


def test_points_near_what_was_seen_through_wait_and_never_enter_if_seen_through():
    """A map point a sweep sees through leaves the map. Afterwards, points within ``near_m`` of
    it (a walker's, 0.1-0.4 m on) wait for their probation while points elsewhere (the walls)
    enter at once; a sweep that sees through the waiting points drops them, so they never
    enter; waiting points it does not see through enter when their probation is over."""
    cfg = MapConfig()
    movers = MovingPoints.from_config(cfg)
    ivox = IVox.from_config(cfg)
    origin = np.array([1.0, 0.5, 0.2])
    img = movers.image(sweep(origin))
    ghost = origin + np.array([[3.0, 0.0, 0.0]])
    movers.stored(ghost[ivox.add_points(ghost, cfg.map_leaf_m)], 0)
    assert movers.carve(ivox, img, np.eye(3), origin, 100_000_000) == 1
    assert ivox.points().shape[0] == 0
    walker = ghost + np.array([[0.1 * k, 0.1, 0.02 * k] for k in range(1, 5)])
    wall = origin + sweep(origin)[::50]
    t = 200_000_000
    now = movers.admit(np.vstack([walker, wall]), cfg.map_leaf_m, t)
    assert len(now) == len(wall) and np.isin(now, wall).all()
    (waiting, _), = movers.waiting()
    np.testing.assert_array_equal(waiting, walker)
    assert not movers.matured(t + movers.probation_ns - 1)
    assert movers.carve(ivox, img, np.eye(3), origin, t + 100_000_000) == len(walker)
    assert not movers.matured(t + movers.probation_ns)
    # a waiting point the sweeps do not see through (on the wall) enters after its probation
    t2 = t + 150_000_000
    movers.carve(ivox, img, np.eye(3), origin, t2)  # seen through again: ghost's neighbours wait
    on_wall = origin + sweep(origin)[:1]
    movers._seen.append((t2, on_wall + [0.05, 0.0, 0.0]))
    assert len(movers.admit(on_wall, cfg.map_leaf_m, t2)) == 0
    assert movers.carve(ivox, img, np.eye(3), origin, t2 + 100_000_000) == 0
    matured = movers.matured(t2 + movers.probation_ns)
    assert len(matured) == 1
    np.testing.assert_array_equal(matured[0][0], on_wall)
    assert movers.waiting() == []


def test_a_point_where_an_earlier_sweep_saw_through_is_moving():
    """A point that appears half-way to the wall, half a second after a sweep that saw the wall
    there, is moving; points on the wall are not, and nothing is judged before that sweep."""
    cfg = MapConfig()
    movers = MovingPoints.from_config(cfg)
    origin = np.array([1.0, 0.5, 0.2])
    rng = np.random.default_rng(3)
    d = random_directions(rng, 500, (-12.0, 10.0))
    wall = origin + d * wall_distance(origin, d)[:, None]
    appeared = origin + d * (0.5 * wall_distance(origin, d))[:, None]
    assert not movers.moving(appeared, 0).any()
    movers.add_sweep(movers.image(sweep(origin)), np.eye(3), origin, 0)
    t = movers.lookback_ns
    assert movers.moving(appeared, t).mean() > 0.97
    assert not movers.moving(wall, t).any()


def test_near_any_is_the_brute_force_distance_test():
    """``near_any`` against every pairwise distance: clouds of several spreads, radii, sources
    on cell edges and none at all."""
    rng = np.random.default_rng(5)
    for n_src, spread, radius in ((0, 5.0, 0.3), (1, 1.0, 0.3), (40, 3.0, 0.3), (300, 8.0, 0.5),
                                  (25, 2.0, 0.05)):
        points = rng.uniform(-spread, spread, (4000, 3))
        sources = rng.uniform(-spread, spread, (n_src, 3))
        if n_src:
            sources[: n_src // 2] = np.round(sources[: n_src // 2] / radius) * radius
            points[:500] = sources[rng.integers(0, n_src, 500)] + rng.normal(0, radius, (500, 3))
        dist = np.sqrt(((points[:, None, :] - sources[None, :, :]) ** 2).sum(-1))
        truth = (dist < radius).any(axis=1) if n_src else np.zeros(len(points), bool)
        got = near_any(points, sources, radius)
        np.testing.assert_array_equal(got, truth)
        if n_src:
            assert 0 < got.sum() < len(points)


def test_someone_walking_away_is_kept_out_by_their_trail():
    """A person walks away from the sensor at 1.2 m/s. Its points now stand behind where the
    sweep half a second before saw it, so none is in free space; the map points it left 0.2-0.3 s
    ago are seen through, and its points now, on the same body, are kept out with them
    (``map.moving_body_m`` 0.3 m): exactly the sweep's points within that of a point in free space
    or seen through and not within the margin of a map point (the room's walls and floor are
    in the map), by scipy's exact nearest neighbours; with ``moving_body_m`` 0, none of the person's.
    The trail is carved by free space alone (``surface_check`` off): 0.2-0.3 s behind a walker
    walking straight away at 6 m, it is within the surface check's reach (0.27 m there) of the
    walker's back, so with the check it waits until the walker is farther
    (:func:`test_seen_through_is_free_space_with_no_return_next_to_it`), unless returns behind a
    point do not count (``surface_check_behind`` off): the back stands behind the trail along
    its rays, and the check carves what free space alone does."""
    cfg = MapConfig()
    origin = np.array([0.0, 0.5, 0.2])

    def feet(t_s):
        return np.array([origin[0] + 6.0 + 1.2 * t_s, origin[1], ROOM_LO[2]])

    def on_person(pts, t_s):
        f = feet(t_s)
        return ((np.hypot(pts[:, 0] - f[0], pts[:, 1] - f[1]) < 0.2 + 1e-6)
                & (pts[:, 2] < f[2] + 1.75 + 1e-6))

    def trail_in_map(check: bool, behind: bool, body_m: float = BODY_M,
                     room: bool = False) -> tuple[MovingPoints, IVox]:
        """The sweep at 0 s kept, and the map points the walker left at 0.2 and 0.3 s stored
        (the last sweep's are on probation), with the room's walls and floor in the map first
        if ``room``."""
        movers = MovingPoints.from_config(cfg)
        movers.body_m = body_m
        movers.surface_check, movers.surface_check_behind = check, behind
        ivox = IVox.from_config(cfg)
        if room:
            ivox.add_points(origin + np.vstack([sweep(origin + [dx, 0.0, 0.0]) + [dx, 0.0, 0.0]
                                                for dx in (-0.5, 0.0, 0.5)]), 0.1)
        movers.add_sweep(movers.image(sweep(origin, feet=feet(0.0))), np.eye(3), origin, 0)
        for t_s in (0.2, 0.3):
            left = origin + sweep(origin, feet=feet(t_s))
            trail = left[on_person(left, t_s)]
            movers.stored(trail[ivox.add_points(trail, 0.1)], round(t_s * 1e9))
        return movers, ivox

    def carved(check: bool, behind: bool) -> int:
        """How many of the trail's map points the sweep now carves."""
        movers, ivox = trail_in_map(check, behind)
        return movers.carve(ivox, movers.image(sweep(origin, feet=feet(0.5))), np.eye(3),
                            origin, 500_000_000)

    n_free = carved(False, True)  # measured 106
    assert n_free > 20
    # the back within reach behind keeps part of the trail (measured 56); without the returns
    # behind, only the lowest points, next to the floor's returns, stay (measured 100 carved)
    assert carved(True, True) < 0.75 * n_free
    assert carved(True, False) > 0.9 * n_free

    runs = {}
    for body_m in (BODY_M, 0.0):
        movers, ivox = trail_in_map(False, True, body_m, room=True)
        now = origin + sweep(origin, feet=feet(0.5))
        t = 500_000_000
        assert movers.carve(ivox, movers.image(now - origin), np.eye(3), origin, t) > 20
        free = in_free_space(now, np.eye(3), origin, movers._sweeps[0].img, movers.pixel_rad,
                             movers.margin_m, movers.margin_fraction)
        person = on_person(now, 0.5)
        assert person.sum() > 50 and not (free & person).any()
        seen = np.concatenate([p for _, p in movers._seen])
        runs[body_m] = (movers.moving(now, t, ivox), now, free, seen, person, ivox.points())
    flags, now, free, seen, person, in_map = runs[BODY_M]

    near_body = cKDTree(np.vstack([now[free], seen])).query(now)[0] < BODY_M
    on_map = cKDTree(in_map).query(now)[0] < cfg.moving_margin_m
    np.testing.assert_array_equal(flags, free | (near_body & ~on_map))
    assert flags[person].mean() > 0.7  # measured 0.78: one edge column is 0.3 m from the trail
    assert not flags[~person].any()  # the floor under the feet is in the map
    assert (near_body & ~person).sum() > 10  # ... and next to the trail
    flags0, *_ = runs[0.0]
    assert not flags0[person].any()
