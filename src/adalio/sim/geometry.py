"""Procedural mesh primitives for the simulator's scenes.

World frame of a scene: z up, metres. Every primitive is a closed triangle mesh (trimesh); scenes
are unions of overlapping solids, which is all a first-hit ray caster needs (inner faces are never
reached from free space).
"""

from __future__ import annotations

import itertools

import numpy as np
import trimesh


def box(lo: np.ndarray | list[float], hi: np.ndarray | list[float]) -> trimesh.Trimesh:
    """Axis-aligned solid box between corners ``lo`` and ``hi``."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    m = trimesh.creation.box(extents=hi - lo)
    m.apply_translation((lo + hi) / 2.0)
    return m


def oriented_box(center: np.ndarray, extents: np.ndarray, yaw_rad: float) -> trimesh.Trimesh:
    """Solid box of ``extents`` rotated by ``yaw_rad`` about z and centred at ``center``."""
    m = trimesh.creation.box(extents=np.asarray(extents, dtype=np.float64))
    T = trimesh.transformations.rotation_matrix(yaw_rad, [0, 0, 1])
    T[:3, 3] = center
    m.apply_transform(T)
    return m


def cylinder(center_xy: np.ndarray | list[float], radius_m: float, z0: float, z1: float,
             sections: int = 24) -> trimesh.Trimesh:
    """Vertical solid cylinder."""
    m = trimesh.creation.cylinder(radius=radius_m, height=z1 - z0, sections=sections)
    m.apply_translation([center_xy[0], center_xy[1], (z0 + z1) / 2.0])
    return m


def rod(p0: np.ndarray, p1: np.ndarray, radius_m: float, sections: int = 8) -> trimesh.Trimesh:
    """Solid cylinder between two points (handrails, pipes)."""
    return trimesh.creation.cylinder(radius=radius_m, segment=np.array([p0, p1]),
                                     sections=sections)


def prism(polygon_xy: np.ndarray, z0: float, z1: float) -> trimesh.Trimesh:
    """Vertical extrusion of a convex counter-clockwise polygon between ``z0`` and ``z1``."""
    poly = np.asarray(polygon_xy, dtype=np.float64)
    n = len(poly)
    verts = np.vstack([np.column_stack([poly, np.full(n, z0)]),
                       np.column_stack([poly, np.full(n, z1)])])
    faces = []
    for i in range(1, n - 1):
        faces.append([0, i + 1, i])
        faces.append([n, n + i, n + i + 1])
    for i in range(n):
        j = (i + 1) % n
        faces.append([i, j, n + j])
        faces.append([i, n + j, n + i])
    return trimesh.Trimesh(verts, np.array(faces), process=False)


def annulus_sector(r0: float, r1: float, a0: float, a1: float, z0: float, z1: float,
                   center_xy: tuple[float, float] = (0.0, 0.0),
                   max_step_rad: float = 0.12) -> list[trimesh.Trimesh]:
    """Solid annulus sector (radii ``r0..r1``, angles ``a0..a1``) as convex prisms."""
    n = max(1, int(np.ceil(abs(a1 - a0) / max_step_rad)))
    angles = np.linspace(a0, a1, n + 1)
    cx, cy = center_xy
    parts = []
    for b0, b1 in itertools.pairwise(angles):
        c0, s0, c1, s1 = np.cos(b0), np.sin(b0), np.cos(b1), np.sin(b1)
        poly = np.array([[cx + r0 * c0, cy + r0 * s0], [cx + r1 * c0, cy + r1 * s0],
                         [cx + r1 * c1, cy + r1 * s1], [cx + r0 * c1, cy + r0 * s1]])
        if b1 < b0:
            poly = poly[::-1]
        parts.append(prism(poly, z0, z1))
    return parts


def solid_complement(free_boxes: list[tuple[np.ndarray, np.ndarray]],
                     wall_m: float = 0.3) -> list[trimesh.Trimesh]:
    """Walls, floors and ceilings around a union of free axis-aligned boxes.

    Space is split on every box face coordinate; each cell outside all free boxes but within
    ``wall_m`` of the union's bounding box becomes a solid box if it touches free space.
    Adjacent solid cells along x are merged to keep the triangle count low.
    """
    lows = np.array([b[0] for b in free_boxes], dtype=np.float64)
    highs = np.array([b[1] for b in free_boxes], dtype=np.float64)
    lo = lows.min(axis=0) - wall_m
    hi = highs.max(axis=0) + wall_m
    axes = []
    for k in range(3):
        c = np.unique(np.concatenate([lows[:, k], highs[:, k], [lo[k], hi[k]]]))
        axes.append(c)
    centers = [0.5 * (a[1:] + a[:-1]) for a in axes]
    cx, cy, cz = np.meshgrid(*centers, indexing="ij")
    free = np.zeros(cx.shape, dtype=bool)
    for blo, bhi in zip(lows, highs, strict=True):
        free |= ((cx > blo[0]) & (cx < bhi[0]) & (cy > blo[1]) & (cy < bhi[1])
                 & (cz > blo[2]) & (cz < bhi[2]))
    near = np.zeros_like(free)
    for axis in range(3):
        for shift in (-1, 1):
            rolled = np.roll(free, shift, axis=axis)
            idx = [slice(None)] * 3
            idx[axis] = 0 if shift == 1 else -1
            rolled[tuple(idx)] = False
            near |= rolled
    solid = near & ~free
    parts = []
    nx, ny, nz = solid.shape
    for j in range(ny):
        for k in range(nz):
            i = 0
            while i < nx:
                if not solid[i, j, k]:
                    i += 1
                    continue
                i0 = i
                while i < nx and solid[i, j, k]:
                    i += 1
                parts.append(box([axes[0][i0], axes[1][j], axes[2][k]],
                                 [axes[0][i], axes[1][j + 1], axes[2][k + 1]]))
    return parts


def merge(parts: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """Concatenate solids into one mesh (no boolean union: overlaps are harmless)."""
    return trimesh.util.concatenate(parts)
