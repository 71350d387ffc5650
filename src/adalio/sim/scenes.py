"""Procedural indoor scenes of the simulator: triangle meshes plus a walking route.

Frame: scene world, z up, metres, floor of the start level at z = 0. A :class:`Scene` holds the
mesh (closed solids, first-hit ray casting only), the route of the IMU through it (waypoints at
rig height, corners are filleted by :mod:`adalio.sim.trajectory`) and a walking-speed limit per
waypoint (slower on stairs). Clutter is placed from a seeded generator, away from the route.
"""

from __future__ import annotations

import inspect
import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from adalio.errors import InputError
from adalio.sim import geometry as g

RIG_HEIGHT_M = 1.35
"""Height of the handheld IMU above the floor the operator stands on (metres)."""


@dataclass
class Scene:
    """A mesh and the route walked through it."""

    name: str
    mesh: trimesh.Trimesh
    waypoints_m: np.ndarray
    """(K, 3) IMU positions along the route (scene world)."""
    speed_limit_m_s: np.ndarray
    """(K,) walking speed limit at each waypoint (interpolated along the route)."""
    fillet_m: float = 1.0
    """Corner rounding distance of the route (metres)."""


def _seg_dist_xy(points_xy: np.ndarray, polyline_xy: np.ndarray) -> np.ndarray:
    """Horizontal distance of each point to a polyline."""
    a = polyline_xy[:-1][None]
    b = polyline_xy[1:][None]
    p = points_xy[:, None]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
    d = p - (a + t[..., None] * ab)
    return np.sqrt((d * d).sum(-1)).min(axis=1)


def _place_clutter(rng: np.random.Generator, route_xy: np.ndarray, area_lo: np.ndarray,
                   area_hi: np.ndarray, n: int, makers: list[Callable], clearance_m: float,
                   avoid: list[tuple[np.ndarray, float]] | None = None,
                   z0: float = 0.0) -> list[trimesh.Trimesh]:
    """Seeded rejection sampling of clutter objects at least ``clearance_m`` from the route."""
    parts: list[trimesh.Trimesh] = []
    placed: list[tuple[np.ndarray, float]] = list(avoid or [])
    tries = 0
    while len(parts) < n and tries < 50 * n:
        tries += 1
        maker = makers[int(rng.integers(len(makers)))]
        mesh, radius = maker(rng)
        c = rng.uniform(area_lo + radius, area_hi - radius)
        if _seg_dist_xy(c[None], route_xy)[0] < clearance_m + radius:
            continue
        if any(np.hypot(*(c - q)) < r + radius + 0.1 for q, r in placed):
            continue
        mesh.apply_translation([c[0], c[1], z0])
        parts.append(mesh)
        placed.append((c, radius))
    return parts


def _crate(rng: np.random.Generator) -> tuple[trimesh.Trimesh, float]:
    e = rng.uniform([0.4, 0.4, 0.3], [1.2, 1.0, 1.3])
    yaw = rng.uniform(0, np.pi)
    return g.oriented_box([0, 0, e[2] / 2], e, yaw), 0.5 * np.hypot(e[0], e[1])


def _stacked_crates(rng: np.random.Generator) -> tuple[trimesh.Trimesh, float]:
    e = rng.uniform([0.6, 0.6, 0.5], [1.0, 1.0, 0.8])
    yaw = rng.uniform(0, np.pi)
    lower = g.oriented_box([0, 0, e[2] / 2], e, yaw)
    e2 = e * rng.uniform(0.5, 0.9, 3)
    upper = g.oriented_box([0.05, -0.05, e[2] + e2[2] / 2], e2, yaw + rng.uniform(-0.4, 0.4))
    return g.merge([lower, upper]), 0.5 * np.hypot(e[0], e[1])


def _table(rng: np.random.Generator) -> tuple[trimesh.Trimesh, float]:
    lx, ly = rng.uniform(1.0, 1.8), rng.uniform(0.6, 0.9)
    h = rng.uniform(0.72, 0.78)
    parts = [g.box([-lx / 2, -ly / 2, h - 0.04], [lx / 2, ly / 2, h])]
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (lx / 2 - 0.05), sy * (ly / 2 - 0.05)
            parts.append(g.box([cx - 0.03, cy - 0.03, 0], [cx + 0.03, cy + 0.03, h - 0.04]))
    m = g.merge(parts)
    m.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, np.pi), [0, 0, 1]))
    return m, 0.5 * np.hypot(lx, ly)


def _barrel(rng: np.random.Generator) -> tuple[trimesh.Trimesh, float]:
    r = rng.uniform(0.25, 0.35)
    return g.cylinder([0, 0], r, 0.0, rng.uniform(0.8, 1.0), sections=20), r


def _shelf(rng: np.random.Generator) -> tuple[trimesh.Trimesh, float]:
    lx, ly, h = rng.uniform(1.5, 2.5), 0.5, rng.uniform(1.8, 2.4)
    parts = [g.box([-lx / 2, -ly / 2, 0], [-lx / 2 + 0.04, ly / 2, h]),
             g.box([lx / 2 - 0.04, -ly / 2, 0], [lx / 2, ly / 2, h]),
             g.box([-lx / 2, ly / 2 - 0.02, 0], [lx / 2, ly / 2, h])]
    for z in np.linspace(0.1, h - 0.02, 5):
        parts.append(g.box([-lx / 2, -ly / 2, z - 0.02], [lx / 2, ly / 2, z]))
    m = g.merge(parts)
    m.apply_transform(trimesh.transformations.rotation_matrix(
        float(rng.integers(4)) * np.pi / 2, [0, 0, 1]))
    return m, 0.5 * np.hypot(lx, ly)


# --------------------------------------------------------------------------- hall
def build_hall(seed: int = 0, size_m: tuple[float, float, float] = (20.0, 15.0, 5.0),
               n_clutter: int = 26) -> Scene:
    """Open hall with pillars, ceiling beams, furniture and crates: the non-degenerate baseline."""
    rng = np.random.default_rng([seed, 1])
    lx, ly, lz = size_m
    free = [(np.array([0.0, 0.0, 0.0]), np.array([lx, ly, lz]))]
    for x in (0.3 * lx, 0.7 * lx):
        free.append((np.array([x - 0.6, ly, 0.0]), np.array([x + 0.6, ly + 0.25, 2.4])))
    free.append((np.array([lx, 0.4 * ly - 0.9, 0.0]), np.array([lx + 0.3, 0.4 * ly + 0.9, 3.0])))
    free.append((np.array([-0.2, 0.6 * ly, 1.0]), np.array([0.0, 0.6 * ly + 2.5, 2.5])))
    parts = g.solid_complement(free)
    pillars = []
    for fx in (0.25, 0.5, 0.75):
        for fy in (1 / 3, 2 / 3):
            pillars.append((np.array([fx * lx, fy * ly]), 0.35))
            if fx == 0.5:
                parts.append(g.cylinder([fx * lx, fy * ly], 0.3, 0.0, lz, sections=24))
            else:
                c = np.array([fx * lx, fy * ly])
                parts.append(g.box([*(c - 0.25), 0.0], [*(c + 0.25), lz]))
    for fx in (0.25, 0.5, 0.75):
        parts.append(g.box([fx * lx - 0.15, 0.0, lz - 0.5], [fx * lx + 0.15, ly, lz]))
    m = 2.5
    route = np.array([[m, m], [lx - m, m], [lx - m, ly - m], [0.35 * lx, ly - m],
                      [0.35 * lx, 0.5 * ly], [0.62 * lx, 0.5 * ly]])
    parts += _place_clutter(rng, route, np.array([0.3, 0.3]), np.array([lx - 0.3, ly - 0.3]),
                            n_clutter, [_crate, _stacked_crates, _table, _barrel, _shelf],
                            clearance_m=0.9, avoid=pillars)
    waypoints = np.column_stack([route, np.full(len(route), RIG_HEIGHT_M)])
    return Scene("hall", g.merge(parts), waypoints, np.full(len(route), 1.25), fillet_m=1.8)


# ----------------------------------------------------------------------- corridor
def build_corridor(seed: int = 0, length_a_m: float = 48.0, length_b_m: float = 14.0,
                   width_m: float = 1.6, height_m: float = 2.5, n_doors: int = 5,
                   recess_m: float = 0.1) -> Scene:
    """L-shaped corridor: smooth walls, a few door recesses, ceiling lights, one 90 deg turn."""
    rng = np.random.default_rng([seed, 2])
    w = width_m
    a = (np.array([0.0, -w / 2, 0.0]), np.array([length_a_m, w / 2, height_m]))
    b = (np.array([length_a_m - w, -w / 2, 0.0]),
         np.array([length_a_m, length_b_m, height_m]))
    free = [a, b]
    along = []
    xs = rng.uniform(3.0, length_a_m - 4.0, 64)
    for x in xs:
        if all(abs(x - q) > 10.0 for q in along):
            along.append(x)
        if len(along) == n_doors - 2:
            break
    for i, x in enumerate(along):
        side = 1 if i % 2 == 0 else -1
        y0, y1 = (w / 2, w / 2 + recess_m) if side > 0 else (-w / 2 - recess_m, -w / 2)
        free.append((np.array([x - 0.5, y0, 0.0]), np.array([x + 0.5, y1, 2.1])))
    for y in (0.45 * length_b_m, 0.8 * length_b_m):
        free.append((np.array([length_a_m - w - recess_m, y - 0.5, 0.0]),
                     np.array([length_a_m - w, y + 0.5, 2.1])))
    parts = g.solid_complement(free)
    for x in np.arange(2.5, length_a_m - 1.0, 5.0):
        parts.append(g.box([x - 0.3, -0.15, height_m - 0.05], [x + 0.3, 0.15, height_m]))
    for y in np.arange(3.0, length_b_m - 1.0, 5.0):
        cx = length_a_m - w / 2
        parts.append(g.box([cx - 0.15, y - 0.3, height_m - 0.05], [cx + 0.15, y + 0.3, height_m]))
    parts.append(g.rod(np.array([0.2, w / 2 - 0.15, height_m - 0.15]),
                       np.array([length_a_m - w - 0.1, w / 2 - 0.15, height_m - 0.15]), 0.05))
    parts.append(g.box([length_a_m * 0.5, -w / 2, 0.0], [length_a_m * 0.5 + 0.6, -w / 2 + 0.12,
                                                          0.7]))
    cx = length_a_m - w / 2
    route = np.array([[1.5, 0.0], [cx, 0.0], [cx, length_b_m - 1.5]])
    waypoints = np.column_stack([route, np.full(len(route), RIG_HEIGHT_M)])
    return Scene("corridor", g.merge(parts), waypoints, np.full(len(route), 1.05), fillet_m=0.8)


# ------------------------------------------------------------------------- spiral
def build_spiral(seed: int = 0, shaft_radius_m: float = 1.3, column_radius_m: float = 0.15,
                 storey_m: float = 3.0, n_storeys: int = 2, riser_m: float = 0.18,
                 room_m: tuple[float, float] = (8.0, 6.0), n_clutter: int = 8) -> Scene:
    """Room -> narrow spiral staircase (central column, helical steps, landings, handrail)
    down ``n_storeys`` -> room. Each storey: a 90 deg landing and 270 deg of steps."""
    rng = np.random.default_rng([seed, 3])
    R, rc, H = shaft_radius_m, column_radius_m, storey_m
    depth = n_storeys * H
    wall_out = R * np.sqrt(2.0) + 0.08
    x_room = -wall_out - 0.05
    lx, ly = room_m
    door_half = np.radians(22.0)
    free = [(np.array([-R, -R, -depth]), np.array([R, R, H])),
            (np.array([x_room - lx, -ly / 2, 0.0]), np.array([x_room, ly / 2, H])),
            (np.array([x_room - lx, -ly / 2, -depth]), np.array([x_room, ly / 2, -depth + H])),
            (np.array([x_room - 0.05, -0.45, 0.0]), np.array([-R + 0.3, 0.45, 2.1])),
            (np.array([x_room - 0.05, -0.45, -depth]), np.array([-R + 0.3, 0.45, -depth + 2.1]))]
    parts = g.solid_complement(free)
    n_wall = 48
    edges = np.linspace(0.0, 2 * np.pi, n_wall + 1) + np.pi
    door_z = [(0.0, 2.1), (-depth, -depth + 2.1)]
    z_bands = sorted({-depth, -depth + 2.1, 0.0, 2.1, H})
    for a0, a1 in itertools.pairwise(edges):
        mid = 0.5 * (a0 + a1)
        in_door_angle = abs(np.angle(np.exp(1j * (mid - np.pi)))) < door_half
        for z0, z1 in itertools.pairwise(z_bands):
            if in_door_angle and any(abs(z0 - d0) < 1e-9 for d0, _ in door_z):
                continue
            parts += g.annulus_sector(R, wall_out, a0, a1, z0, z1)
    parts.append(g.cylinder([0.0, 0.0], rc, -depth, H, sections=20))
    n_steps = round(H / riser_m) - 1
    riser = H / (n_steps + 1)
    land = np.pi / 2
    step_a = (2 * np.pi - land) / n_steps
    a_start = np.pi - land / 2
    for k in range(n_storeys):
        z_top = -k * H
        a = a_start + k * 2 * np.pi
        parts += g.annulus_sector(rc, R, a, a + land, z_top - 0.25, z_top)
        a += land
        for i in range(n_steps):
            zt = z_top - (i + 1) * riser
            parts += g.annulus_sector(rc, R, a + i * step_a, a + (i + 1) * step_a, zt - 0.22, zt,
                                      max_step_rad=0.3)
    r_rail = R - 0.1
    angs = np.arange(a_start + land, a_start + n_storeys * 2 * np.pi, np.radians(12.0))

    def tread_z(ang: np.ndarray) -> np.ndarray:
        rel = ang - a_start
        k = np.floor(rel / (2 * np.pi))
        within = rel - k * 2 * np.pi
        frac = np.clip((within - land) / (2 * np.pi - land), 0.0, 1.0)
        return -k * H - frac * H

    pts = np.column_stack([r_rail * np.cos(angs), r_rail * np.sin(angs), tread_z(angs) + 0.9])
    for p0, p1 in itertools.pairwise(pts):
        parts.append(g.rod(p0, p1, 0.025, sections=6))
    for p in pts[::4]:
        parts.append(g.rod(p, p - np.array([0, 0, 0.9]), 0.015, sections=6))
    mid_a = a_start + 2 * np.pi + land / 2
    c = np.array([(R - 0.05) * np.cos(mid_a), (R - 0.05) * np.sin(mid_a)])
    parts.append(g.box([c[0] - 0.1, c[1] - 0.2, -H + 1.0], [c[0] + 0.05, c[1] + 0.2, -H + 1.6]))
    r_walk = 0.5 * (R + rc) + 0.02
    top = [[x_room - lx + 1.2, -ly / 2 + 1.2], [x_room - lx + 1.2, ly / 2 - 1.2],
           [x_room - 2.0, ly / 2 - 1.2], [x_room - 1.0, 0.0], [-r_walk - 0.6, 0.0]]
    wp = [[x, y, RIG_HEIGHT_M] for x, y in top]
    speed = [1.2] * (len(top) - 1) + [0.6]
    helix = np.arange(np.pi, a_start + n_storeys * 2 * np.pi + land / 2 + 1e-9, np.radians(10.0))
    for ang in helix:
        wp.append([r_walk * np.cos(ang), r_walk * np.sin(ang), tread_z(ang) + RIG_HEIGHT_M])
        speed.append(0.45)
    zb = -depth + RIG_HEIGHT_M
    bottom = [[-r_walk - 0.6, 0.0], [x_room - 1.0, 0.0], [x_room - 2.5, -ly / 2 + 1.2],
              [x_room - lx + 1.2, -ly / 2 + 1.2], [x_room - lx + 1.2, ly / 2 - 1.5]]
    for x, y in bottom:
        wp.append([x, y, zb])
        speed.append(1.1)
    speed[-len(bottom)] = 0.6
    wp_arr = np.array(wp)
    route_top = wp_arr[:len(top), :2]
    route_bot = wp_arr[-len(bottom):, :2]
    lo, hi = np.array([x_room - lx + 0.3, -ly / 2 + 0.3]), np.array([x_room - 0.3, ly / 2 - 0.3])
    door = [(np.array([x_room, 0.0]), 1.0)]
    makers = [_crate, _stacked_crates, _table, _barrel, _shelf]
    for route, z0 in ((route_top, 0.0), (route_bot, -depth)):
        parts += _place_clutter(rng, route, lo, hi, n_clutter, makers, clearance_m=0.9,
                                avoid=door, z0=z0)
    return Scene("spiral", g.merge(parts), wp_arr, np.array(speed), fillet_m=0.6)


# ------------------------------------------------------------------ stairs_garage
def _car(rng: np.random.Generator, along_y: bool) -> trimesh.Trimesh:
    lx, ly = rng.uniform(4.1, 4.8), rng.uniform(1.7, 1.9)
    h = rng.uniform(1.35, 1.6)
    body = g.box([-lx / 2, -ly / 2, 0.15], [lx / 2, ly / 2, 0.55 * h + 0.15])
    cab = g.box([-0.3 * lx, -0.45 * ly, 0.55 * h + 0.15], [0.25 * lx, 0.45 * ly, h])
    wheels = [g.box([sx * 0.32 * lx - 0.3, sy * ly / 2 - 0.1, 0.0],
                    [sx * 0.32 * lx + 0.3, sy * ly / 2 + 0.1, 0.3]) for sx in (-1, 1)
              for sy in (-1, 1)]
    m = g.merge([body, cab, *wheels])
    if along_y:
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 0, 1]))
    return m


def build_stairs_garage(seed: int = 0, flight_width_m: float = 1.2, storey_m: float = 3.0,
                        n_storeys: int = 2, riser_m: float = 0.1875, tread_m: float = 0.3,
                        garage_m: tuple[float, float, float] = (38.0, 26.0, 2.4),
                        occupancy: float = 0.75) -> Scene:
    """Narrow dog-leg stairwell (two flights per storey, half landings, a wall between the
    flights) down ``n_storeys`` into a large low parking garage with columns and parked cars."""
    rng = np.random.default_rng([seed, 4])
    w, H = flight_width_m, storey_m
    depth = n_storeys * H
    n_rise = round(H / 2 / riser_m)
    riser = H / 2 / n_rise
    run = (n_rise - 1) * tread_m
    land = 1.4
    x_f0, x_f1 = land, land + run
    x_end = x_f1 + land
    y_b0, y_b1 = w + 0.2, 2 * w + 0.2
    gx, gy, gz = garage_m
    free = [(np.array([0.0, 0.0, -depth]), np.array([x_end, y_b1, H])),
            (np.array([-5.0, -1.0, 0.0]), np.array([0.0, y_b1 + 1.0, H])),
            (np.array([-0.35, 0.1, 0.0]), np.array([0.05, w - 0.1, 2.1])),
            (np.array([-gx, -gy / 2, -depth]), np.array([-0.3, gy / 2, -depth + gz])),
            (np.array([-0.35, y_b0 + 0.1, -depth]), np.array([0.05, y_b1 - 0.1, -depth + 2.1]))]
    parts = g.solid_complement(free)
    parts.append(g.box([x_f0, w, -depth], [x_f1, y_b0, H]))
    for k in range(n_storeys):
        z0 = -k * H
        if k == 0:
            parts.append(g.box([0.0, 0.0, z0 - 0.25], [x_f0, y_b1, z0]))
        for i in range(n_rise - 1):
            zt = z0 - (i + 1) * riser
            xa = x_f0 + i * tread_m
            parts.append(g.box([xa, 0.0, zt - riser - 0.2], [xa + tread_m, w, zt]))
        zh = z0 - H / 2
        parts.append(g.box([x_f1, 0.0, zh - 0.25], [x_end, y_b1, zh]))
        for i in range(n_rise - 1):
            zt = zh - (i + 1) * riser
            xb = x_f1 - i * tread_m
            parts.append(g.box([xb - tread_m, y_b0, zt - riser - 0.2], [xb, y_b1, zt]))
        if k < n_storeys - 1:
            parts.append(g.box([0.0, 0.0, z0 - H - 0.25], [x_f0, y_b1, z0 - H]))
    for k in range(n_storeys):
        for y_rail, x0, x1, z_a, z_b in ((w - 0.05, x_f0, x_f1, -k * H, -k * H - H / 2),
                                         (y_b0 + 0.05, x_f1, x_f0, -k * H - H / 2, -k * H - H)):
            p0 = np.array([x0, y_rail, z_a + 0.9])
            p1 = np.array([x1, y_rail, z_b + 0.9])
            parts.append(g.rod(p0, p1, 0.025, sections=6))
    z_g = -depth
    for cx in (-4.0, -12.0, -20.0, -30.0):
        for cy in (-5.8, 5.2, 11.0):
            parts.append(g.box([cx - 0.25, cy - 0.25, z_g], [cx + 0.25, cy + 0.25, z_g + gz]))
    for cx in np.arange(-4.0, -gx, -8.0):
        parts.append(g.box([cx - 0.2, -gy / 2, z_g + gz - 0.45], [cx + 0.2, gy / 2, z_g + gz]))
    parts.append(g.rod(np.array([-1.0, 3.8, z_g + gz - 0.2]),
                       np.array([-gx + 0.5, 3.8, z_g + gz - 0.2]), 0.08, sections=8))
    y_a = 0.5 * (y_b0 + y_b1)
    x_turn = -16.0
    route_xy = np.array([[-0.5, y_a], [x_turn, y_a], [x_turn, -8.5], [-9.0, -8.5]])
    for row_y0, row_y1 in ((5.6, 10.4), (-5.4, -0.8), (-gy / 2 + 0.4, -gy / 2 + 5.2)):
        for cx in np.arange(-1.6, -gx + 1.3, -2.5):
            if rng.random() > occupancy:
                continue
            c = np.array([cx, 0.5 * (row_y0 + row_y1)])
            if _seg_dist_xy(c[None], route_xy)[0] < 3.4:
                continue
            if min(abs(cx - q) for q in (-4.0, -12.0, -20.0, -30.0)) < 1.3:
                continue
            car = _car(rng, along_y=True)
            car.apply_translation([c[0] + rng.uniform(-0.15, 0.15), c[1] + rng.uniform(-0.3, 0.3),
                                   z_g])
            parts.append(car)
    y_a_top = 0.5 * w
    wp, speed = [[-3.5, y_a_top, RIG_HEIGHT_M], [0.5, y_a_top, RIG_HEIGHT_M]], [1.1, 0.6]
    x_mid = 0.5 * (x_f1 + x_end)
    for k in range(n_storeys):
        z0 = -k * H
        wp += [[x_f0 - 0.1, y_a_top, z0 + RIG_HEIGHT_M],
               [x_f1 + 0.1, y_a_top, z0 - H / 2 + RIG_HEIGHT_M],
               [x_mid, y_a_top + 0.1, z0 - H / 2 + RIG_HEIGHT_M],
               [x_mid, y_a - 0.1, z0 - H / 2 + RIG_HEIGHT_M],
               [x_f1 + 0.1, y_a, z0 - H / 2 + RIG_HEIGHT_M],
               [x_f0 - 0.1, y_a, z0 - H + RIG_HEIGHT_M]]
        speed += [0.55] * 6
        if k < n_storeys - 1:
            wp += [[0.65, y_a - 0.1, z0 - H + RIG_HEIGHT_M],
                   [0.65, y_a_top + 0.1, z0 - H + RIG_HEIGHT_M]]
            speed += [0.5, 0.5]
    zb = -depth + RIG_HEIGHT_M
    for x, y in route_xy:
        wp.append([x, y, zb])
        speed.append(1.2)
    speed[-len(route_xy)] = 0.6
    return Scene("stairs_garage", g.merge(parts), np.array(wp), np.array(speed), fillet_m=0.45)


SCENE_BUILDERS: dict[str, Callable[..., Scene]] = {
    "hall": build_hall,
    "corridor": build_corridor,
    "spiral": build_spiral,
    "stairs_garage": build_stairs_garage,
}


def build_scene(name: str, seed: int = 0, **params: object) -> Scene:
    """Build a scene by name with the clutter of ``seed``; ``params`` override the builder's
    size parameters (e.g. ``length_a_m`` of the corridor)."""
    if name not in SCENE_BUILDERS:
        raise InputError(f"unknown scene '{name}': choose one of {', '.join(SCENE_BUILDERS)}")
    builder = SCENE_BUILDERS[name]
    allowed = set(inspect.signature(builder).parameters) - {"seed"}
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise InputError(f"unknown parameter(s) {', '.join(unknown)} of scene '{name}': "
                         f"valid are {', '.join(sorted(allowed))}")
    return builder(seed=seed, **params)
