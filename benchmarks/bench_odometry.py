"""Per-scan speed of adalio.lio.Odometry on a synthetic XT-32-like sequence.

The sequence is the analytic box-room generator of ``tests/lio/test_odometry.py`` (ray-box
casting, per-column point times, IMU from analytic derivatives). Prints the per-stage profile
(mean ms per processed scan), the median / p90 wall ms per scan (after the first two scans, which
include numba compilation) and the ATE (Umeyama SE(3) on positions).

    python benchmarks/bench_odometry.py --columns 1000 --duration 4 --mode fixed
"""

from __future__ import annotations

import argparse
import importlib.util
import time
from pathlib import Path

import numpy as np

from adalio.lio import Odometry
from adalio.lio.odometry import STAGES


def _generator():
    path = Path(__file__).resolve().parents[1] / "tests" / "lio" / "test_odometry.py"
    spec = importlib.util.spec_from_file_location("_box_room_generator", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--columns", type=int, default=1000, help="azimuth columns per sweep")
    ap.add_argument("--duration", type=float, default=4.0, help="sequence length (s)")
    ap.add_argument("--mode", default="fixed", choices=("fixed", "adaptive", "adaptive+"))
    ap.add_argument("--voxel", type=float, default=None, help="general scan leaf (m)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    gen = _generator()
    cfg = gen._config()
    cfg.adaptive.mode = args.mode
    if args.voxel:
        cfg.adaptive.general.voxel_size_m = args.voxel
    rng = np.random.default_rng(args.seed)
    t_imu, gyro, acc = gen.imu_samples(0.0, args.duration + 0.05, 400.0, rng, noise=0.01)
    scans = [gen.lidar_scan(s, args.columns, rng) for s in np.arange(0.0, args.duration, 0.1)]

    odom = Odometry(cfg)
    est, k = [], 0
    t0 = time.perf_counter()
    for pts, t_ns in scans:
        hi = int(np.searchsorted(t_imu, t_ns.max(), side="right"))
        if hi > k:
            odom.add_imu(t_imu[k:hi], gyro[k:hi], acc[k:hi])
            k = hi
        e = odom.add_scan(pts, t_ns)
        if e is not None:
            est.append(e)
    wall = time.perf_counter() - t0

    timed = est[2:]
    per_stage = {s: np.mean([e.stats.stage_ms.get(s, 0.0) for e in timed]) for s in STAGES}
    ms = np.array([e.stats.wall_ms for e in timed])
    t = np.array([e.t_ns for e in est]) * 1e-9
    gt_p, *_ = gen.trajectory(t)
    ate = gen.umeyama_ate(np.array([e.T_world_imu[:3, 3] for e in est]), gt_p)
    print(f"{len(scans)} scans x {args.columns} columns x 32 beams, mode={args.mode}, "
          f"leaf={cfg.adaptive.general.voxel_size_m} m, total {wall:.1f} s (incl. compile)")
    print(f"n_raw {np.median([e.stats.n_raw for e in timed]):.0f}  "
          f"n_down {np.median([e.stats.n_down for e in timed]):.0f}  "
          f"iterations {np.mean([e.stats.iterations for e in timed]):.2f}  "
          f"map points {odom.map_points().shape[0]}")
    print("stage          mean ms/scan")
    for s in STAGES:
        print(f"  {s:<12} {per_stage[s]:8.2f}")
    print(f"median {np.median(ms):.2f} ms/scan, p90 {np.percentile(ms, 90):.2f} ms/scan, "
          f"ATE {ate * 100:.2f} cm")


if __name__ == "__main__":
    main()
