"""Procedural indoor scenes of the simulator: triangle meshes plus a walking route.

Frame: scene world, z up, metres, floor of the start level at z = 0. A :class:`Scene` holds the
mesh (closed solids, first-hit ray casting only), the route of the IMU through it (waypoints at
rig height, corners are filleted by :mod:`adalio.sim.trajectory`) and a walking-speed limit per
waypoint (slower on stairs). Clutter is placed from a seeded generator, away from the route.
"""

from __future__ import annotations

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
def build_corridor(seed: int = 0, length_a_m: float = 36.0, length_b_m: float = 16.0,
                   width_m: float = 1.6, height_m: float = 2.5, n_doors: int = 6) -> Scene:
    """L-shaped corridor: smooth walls, a few door recesses, ceiling lights, one 90 deg turn."""
    rng = np.random.default_rng([seed, 2])
    w = width_m
    a = (np.array([0.0, -w / 2, 0.0]), np.array([length_a_m, w / 2, height_m]))
    b = (np.array([length_a_m - w, -w / 2, 0.0]),
         np.array([length_a_m, length_b_m, height_m]))
    free = [a, b]
    along = []
    xs = np.sort(rng.uniform(3.0, length_a_m - 4.0, 64))
    for x in xs:
        if all(abs(x - q) > 6.0 for q in along):
            along.append(x)
        if len(along) == n_doors - 2:
            break
    for i, x in enumerate(along):
        side = 1 if i % 2 == 0 else -1
        y0, y1 = (w / 2, w / 2 + 0.15) if side > 0 else (-w / 2 - 0.15, -w / 2)
        free.append((np.array([x - 0.5, y0, 0.0]), np.array([x + 0.5, y1, 2.1])))
    for y in (0.45 * length_b_m, 0.8 * length_b_m):
        free.append((np.array([length_a_m - w - 0.15, y - 0.5, 0.0]),
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


SCENE_BUILDERS: dict[str, Callable[..., Scene]] = {
    "hall": build_hall,
    "corridor": build_corridor,
}


def build_scene(name: str, seed: int = 0) -> Scene:
    """Build a scene by name with its default sizes and the clutter of ``seed``."""
    if name not in SCENE_BUILDERS:
        raise InputError(f"unknown scene '{name}': choose one of {', '.join(SCENE_BUILDERS)}")
    return SCENE_BUILDERS[name](seed=seed)
