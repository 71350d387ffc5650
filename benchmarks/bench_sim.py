"""Generation time of simulated sequences (default: 60 s, PandarXT-32 with 2000 columns, ROS1).

    python benchmarks/bench_sim.py [--duration 60] [--scenes hall corridor ...] [--lidar xt32]

Prints one row per scene: wall seconds, sweeps, points and bag size. Output goes to a temporary
folder that is deleted afterwards.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

from adalio.sim import SCENES, simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--lidar", default="xt32")
    ap.add_argument("--format", default="ros1")
    ap.add_argument("--columns", type=int, default=None)
    args = ap.parse_args()
    print(f"{'scene':15s} {'wall_s':>7s} {'sweeps':>7s} {'points':>10s} {'bag_MB':>8s}")
    for scene in args.scenes:
        tmp = Path(tempfile.mkdtemp(prefix="adalio-bench-sim-"))
        try:
            t0 = time.perf_counter()
            res = simulate(scene, tmp, duration_s=args.duration, lidar=args.lidar,
                           fmt=args.format, columns=args.columns)
            wall = time.perf_counter() - t0
            meta = json.loads(res.meta_path.read_text())
            path = res.bag_path
            size = (sum(p.stat().st_size for p in path.rglob("*")) if path.is_dir()
                    else path.stat().st_size)
            print(f"{scene:15s} {wall:7.1f} {meta['n_scans']:7d} {meta['n_points']:10d} "
                  f"{size / 1e6:8.0f}", flush=True)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
