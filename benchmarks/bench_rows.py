"""Which point-to-plane rows have a map plane that is not their point's surface?

A census of the odometry's rows against the simulator's truth, with no estimator in the loop:
the scene's sweeps are undistorted with the true poses, one every 0.1 s over a window, and each
is associated (``_Association``, the degenerate parameter set of the default config) against a
map built the odometry's way (``IVox.from_config``, the finer cell) from the earlier sweeps at
their true poses, then inserted. A row is *wrong* when its fitted plane normal is more than
``--max-angle-deg`` off the true face its point was ray-cast on. Printed per scene and seed: the
share of wrong rows, the share of the claimed height information (``n_z²`` summed over rows)
they hold, and the same split by the face the point lies on: horizontal (``|n_z| > 0.9``),
vertical (``|n_z| < 0.3``) or other. The default windows lie in each scene's narrow part.

    python benchmarks/bench_rows.py --scenes hall corridor spiral stairs_garage   # README, S. 35
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from scipy.spatial import cKDTree

from adalio.config import Config
from adalio.lio.ivox import IVox
from adalio.lio.odometry import _Association
from adalio.lio.state import State
from adalio.lio.voxel import voxel_downsample
from adalio.sim import SCENES
from adalio.sim.generate import START_NS, T_IMU_LIDAR_HILTI, build_trajectory
from adalio.sim.lidar import LIDAR_MODELS, RayCaster, SweepSimulator, lidar_model
from adalio.sim.scenes import build_scene

WINDOWS_S = {"hall": (6.0, 12.0), "corridor": (6.0, 12.0), "spiral": (24.0, 30.0),
             "stairs_garage": (8.0, 14.0)}
"""Default census windows (seconds after the start): the corridor, the shaft, a flight."""
SCAN_PERIOD_S = 0.1


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c = np.abs(np.sum(a * b, axis=1)) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def census(scene: str, seed: int, lidar: str, columns: int, t0_s: float, t1_s: float,
           max_angle_deg: float) -> dict:
    """Rows of every sweep in [t0_s, t1_s): true face normal, fitted normal (world frame)."""
    cfg = Config()
    deg = cfg.adaptive.degenerate
    T_il = np.asarray(T_IMU_LIDAR_HILTI, dtype=np.float64)
    scn = build_scene(scene, seed)
    traj = build_trajectory(scn, T_il, seed)
    sim = SweepSimulator(RayCaster(scn.mesh, seed), traj, lidar_model(lidar, columns), T_il,
                         START_NS)

    def lidar_pose(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = traj.sample((np.asarray(t_ns, dtype=np.int64) - START_NS) * 1e-9)
        return s.R_world_imu @ T_il[:3, :3], s.p_world_imu_m + s.R_world_imu @ T_il[:3, 3]

    ivox = IVox.from_config(cfg.map)
    face_n, fit_n = [], []
    for k, t_s in enumerate(np.arange(t0_s, t1_s, SCAN_PERIOD_S)):
        sw = sim.sweep(START_NS + round(t_s * 1e9), np.random.default_rng([seed, k]))
        v = sw.valid & (sw.face >= 0)
        R, p = lidar_pose(sw.t_ns[v])
        world = np.einsum("nij,nj->ni", R, sw.xyz_lidar_m[v].astype(np.float64)) + p
        R_e, p_e = lidar_pose(np.array([sw.t_ns[v].max()]))
        end = (world - p_e[0]) @ R_e[0]
        down = voxel_downsample(end, deg.voxel_size_m)
        true_n = sim.caster.face_normals[sw.face[v]][cKDTree(end).query(down)[1]]
        down_world = down @ R_e[0].T + p_e[0]
        if k:
            R_wi = R_e[0] @ T_il[:3, :3].T
            x = State(R=R_wi, p=p_e[0] - R_wi @ T_il[:3, 3], R_LI=T_il[:3, :3].copy(),
                      t_LI=T_il[:3, 3].copy())
            assoc = _Association(down, ivox, cfg, deg.search_radius_m, deg.plane_margin_m,
                                 deg.voxel_size_m)
            assoc.measure(x, True)
            sel = assoc.selected
            face_n.append(true_n[sel])
            fit_n.append(assoc.normals[sel])
        ivox.add_points(down_world, min(cfg.map.map_leaf_m, deg.voxel_size_m))
    face = np.vstack(face_n)
    fit = np.vstack(fit_n)
    wrong = _angle_deg(fit, face) > max_angle_deg
    hz = fit[:, 2] ** 2
    out = {"rows": int(wrong.size), "wrong": float(wrong.mean()),
           "wrong_height_info": float(hz[wrong].sum() / hz.sum())}
    fz = np.abs(face[:, 2])
    for name, on in (("horizontal", fz > 0.9), ("vertical", fz < 0.3),
                     ("other", (fz >= 0.3) & (fz <= 0.9))):
        out[f"{name}_rows"] = float(on.mean())
        out[f"{name}_wrong"] = float(wrong[on].mean()) if on.any() else float("nan")
        out[f"{name}_wrong_height_info"] = float(hz[on & wrong].sum() / hz.sum())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["spiral", "stairs_garage"],
                    choices=list(SCENES))
    ap.add_argument("--seeds", type=int, default=2, help="number of seeds (0 .. N-1)")
    ap.add_argument("--lidar", default="xt32", choices=sorted(LIDAR_MODELS))
    ap.add_argument("--columns", type=int, default=512)
    ap.add_argument("--window-s", type=float, nargs=2, default=None, metavar=("T0", "T1"),
                    help="census window in seconds after the start (default: per scene)")
    ap.add_argument("--max-angle-deg", type=float, default=30.0)
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.columns < 16:
        raise SystemExit("error: --seeds must be >= 1 and --columns >= 16")
    print(f"Command: `python benchmarks/bench_rows.py {' '.join(argv or sys.argv[1:])}`"
          f"  ({args.lidar} at {args.columns} columns, map from true poses, a row is wrong "
          f"beyond {args.max_angle_deg:g} deg)\n")
    print("| scene | seed | window | rows | wrong | their share of the height information | "
          "horizontal faces: rows / wrong / height info | vertical faces | other faces |")
    print("|---|---|---|---|---|---|---|---|---|")
    for scene in args.scenes:
        t0, t1 = args.window_s or WINDOWS_S[scene]
        for seed in range(args.seeds):
            c = census(scene, seed, args.lidar, args.columns, t0, t1, args.max_angle_deg)
            cols = " | ".join(
                f"{c[f'{n}_rows'] * 100:.0f} / {c[f'{n}_wrong'] * 100:.1f} / "
                f"{c[f'{n}_wrong_height_info'] * 100:.0f} %"
                for n in ("horizontal", "vertical", "other"))
            print(f"| {scene} | {seed} | {t0:g}-{t1:g} s | {c['rows']} | "
                  f"{c['wrong'] * 100:.1f} % | {c['wrong_height_info'] * 100:.0f} % | {cols} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
