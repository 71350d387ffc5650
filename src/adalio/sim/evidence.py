"""Ground truth of what a simulated sweep can tell about the height.

A noise-free sweep is ray-cast against the scene's mesh on the simulator's own route (same
scene, trajectory and extrinsic as ``adalio.sim.simulate`` builds for that seed). A return is
*height evidence* when it hits a face with ``|n_z| > 0.95`` (floor, tread, landing, ceiling)
farther than ``min_range_m`` (so the operator's body and the handrail under the sensor do not
count). ``benchmarks/bench_observability.py`` and the tests of the reported sigmas
(``filter.sigmas_height_blind``) take it as the truth about which sweeps hold no height.
"""

from __future__ import annotations

import math

import numpy as np

from adalio.sim.generate import START_NS, T_IMU_LIDAR_HILTI, build_trajectory
from adalio.sim.lidar import Occluder, RayCaster, SweepSimulator, lidar_model
from adalio.sim.scenes import build_scene

HORIZONTAL_FACE_NZ = 0.95
"""A face whose unit normal has ``|n_z|`` above this is horizontal (height evidence)."""


def height_evidence(scene: str, seed: int, step_s: float, min_range_m: float,
                    lidar: str = "xt32", columns: int | None = None,
                    ) -> tuple[np.ndarray, np.ndarray, object, float]:
    """(sweep start times in s from the start every ``step_s``, their numbers of
    height-evidence returns, the route, its duration in s) for the named LiDAR model."""
    T_il = np.asarray(T_IMU_LIDAR_HILTI, dtype=np.float64)
    scn = build_scene(scene, seed)
    traj = build_trajectory(scn, T_il, seed)
    dur = math.floor(traj.duration_s * 10.0) / 10.0
    caster = RayCaster(scn.mesh, seed)
    sim = SweepSimulator(caster, traj, lidar_model(lidar, columns), T_il, START_NS, Occluder())
    t_s = np.arange(0.0, dur - 0.1, step_s)
    counts = np.zeros(len(t_s), np.int64)
    for k, t in enumerate(t_s):
        sw = sim.sweep(START_NS + round(t * 1e9), np.random.default_rng(0), noise_scale=0.0)
        ok = sw.valid & (sw.face >= 0) & (sw.range_m > min_range_m)
        counts[k] = int(np.sum(np.abs(caster.face_normals[sw.face[ok], 2]) > HORIZONTAL_FACE_NZ))
    return t_s, counts, traj, dur
