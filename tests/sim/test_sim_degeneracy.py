"""Degeneracy is real: translation information of ground-truth-registered scans per scene.

For every sweep, the point-to-plane translation information is ``sum n nᵀ`` over the valid
returns (range > 0.5 m, the blind zone of the presets), with ``n`` the normal of the mesh face
each ray hit. Its smallest eigenvalue measures how well the scan pins down the position.
"""

from __future__ import annotations

import numpy as np

from adalio.sim import SCENES
from adalio.sim.generate import START_NS, T_IMU_LIDAR_HILTI, build_trajectory
from adalio.sim.lidar import RayCaster, SweepSimulator, lidar_model
from adalio.sim.scenes import build_scene


def translation_eigenvalues(scene: str, columns: int = 360, step_s: float = 1.0) -> np.ndarray:
    """(n_sweeps, 3) ascending eigenvalues of sum n nᵀ along the scene's walk."""
    T = np.asarray(T_IMU_LIDAR_HILTI)
    scn = build_scene(scene, 0)
    traj = build_trajectory(scn, T, 0)
    caster = RayCaster(scn.mesh)
    sim = SweepSimulator(caster, traj, lidar_model("xt32", columns), T, START_NS)
    out = []
    for t in np.arange(0.0, traj.duration_s - 0.1, step_s):
        sw = sim.sweep(START_NS + int(t * 1e9), np.random.default_rng(0), noise_scale=0.0)
        keep = sw.valid & (sw.range_m > 0.5)
        n = caster.face_normals[sw.face[keep]]
        out.append(np.linalg.eigvalsh(n.T @ n))
    return np.array(out)


def test_corridor_and_spiral_are_far_weaker_than_the_hall():
    eig = {s: translation_eigenvalues(s) for s in SCENES}
    print("\nscene           sweeps  min(l_min)  p10(l_min)  median(l_min)  median(l_max)")
    for s, e in eig.items():
        print(f"{s:15s} {len(e):6d} {e[:, 0].min():11.1f} {np.percentile(e[:, 0], 10):11.1f} "
              f"{np.median(e[:, 0]):14.1f} {np.median(e[:, 2]):14.1f}")
    hall_weakest = eig["hall"][:, 0].min()
    assert hall_weakest > 100.0
    for s in ("corridor", "spiral"):
        assert eig[s][:, 0].min() < 0.1 * hall_weakest, s
    # the weakness is a direction, not a lack of points: the strongest direction stays strong
    assert np.median(eig["corridor"][:, 2]) > 0.5 * np.median(eig["hall"][:, 2])
