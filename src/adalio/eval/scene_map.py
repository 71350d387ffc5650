"""How much of a run's map lies off a simulated scene's surfaces (``adalio simulate`` writes
the scene's mesh as ``scene.ply`` beside ``meta.json``): ghosts of things that moved past the
sensor, and a map that drifted. Metres, the scene's frame."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from adalio.eval.files import read_map_points
from adalio.eval.metrics import align_pair

OFF_SCENE_M = 0.1
"""A map point farther than this from every surface of the simulated scene is off it."""
SURFACE_SAMPLE_M = 0.03
"""Spacing of the scene's surface samples the map points are measured against (at most
``MAX_SURFACE_SAMPLES`` of them: the largest scene's are 5.5 cm apart)."""
MAX_SURFACE_SAMPLES = 4_000_000
_surfaces: dict[str, cKDTree] = {}
"""The last scene's surface samples (one scene after another in a benchmark)."""


def map_off_scene(map_path: Path, trajectory_path: Path, gt_path: Path,
                  meta_path: Path) -> float:
    """Share of a run's map points farther than ``OFF_SCENE_M`` from the simulated scene's
    mesh (``scene.ply`` beside ``meta_path``, its surface sampled every ``SURFACE_SAMPLE_M``),
    the map moved by the trajectory's SE(3) alignment onto the GT and into the scene's frame
    (``meta.json``'s ``T_scene_world``): ghosts of things that moved, and a map that drifted."""
    mesh_path = meta_path.parent / "scene.ply"
    key = str(mesh_path)
    if key not in _surfaces:
        mesh = trimesh.load(mesh_path)
        n = int(min(mesh.area / SURFACE_SAMPLE_M ** 2, MAX_SURFACE_SAMPLES))
        _surfaces.clear()
        _surfaces[key] = cKDTree(trimesh.sample.sample_surface(mesh, n, seed=0)[0])
    T_gt_est = align_pair(trajectory_path, gt_path, "se3").T_gt_est
    T_sw = np.asarray(json.loads(meta_path.read_text())["T_scene_world"])
    T = T_sw @ T_gt_est
    pts = read_map_points(map_path) @ T[:3, :3].T + T[:3, 3]
    d, _ = _surfaces[key].query(pts, distance_upper_bound=OFF_SCENE_M)
    return float(np.mean(~np.isfinite(d))) if len(pts) else float("nan")
