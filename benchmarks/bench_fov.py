"""Is the stairwell's height a limit of the XT-32's vertical field of view?

The same simulated walks (``adalio.sim.cached_sequence``) are run with the default config twice:
with the PandarXT-32 as it is (32 beams, +15..-16 deg) and with the same 32 beams spread over
+-22.5 deg (the Ouster OS1-64's view), registered here as the diagnostic model ``xt32-wide``
(nothing else changes: columns, noise, mounting, IMU, preset). Per run: SE(3) ATE, the largest
first-pose-aligned error (a run beyond ``--diverge-m`` diverged) and the share of scans whose
height error lies within 3 reported sigmas.

    python benchmarks/bench_fov.py --seeds 8 --columns 1000      # README, Session 33
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from adalio.config import load_config
from adalio.eval.files import read_scans_csv
from adalio.eval.metrics import ate, sigma_consistency
from adalio.pipeline import run_bag
from adalio.sim import SCENES, cached_sequence
from adalio.sim.lidar import LIDAR_MODELS, XT32

WIDE = "xt32-wide"
WIDE_HALF_FOV_DEG = 22.5
"""Half the OS1-64's vertical view (+-22.5 deg)."""


def register_wide_model() -> None:
    """The XT-32 with its 32 beams spread evenly over +-22.5 deg, as a simulator model."""
    elevations = tuple(np.linspace(WIDE_HALF_FOV_DEG, -WIDE_HALF_FOV_DEG, XT32.channels))
    LIDAR_MODELS[WIDE] = replace(XT32, name=WIDE, elevations_deg=elevations)


def run_one(scene: str, seed: int, lidar: str, columns: int, out: Path) -> dict:
    seq = cached_sequence(scene, seed=seed, lidar=lidar, columns=columns)
    cfg = load_config(None, seq.config_path)
    res = run_bag(seq.bag_path, cfg, out / f"{scene}_s{seed}_{lidar}", progress=False)
    est = res.trajectory_path  # written in time order
    within = sigma_consistency(est, seq.gt_path,
                               read_scans_csv(res.scans_csv_path)).within_3sigma
    return {"ate_m": ate(est, seq.gt_path, "se3")["rmse_m"],
            "max_first_m": ate(est, seq.gt_path, "first")["max_m"], "z_within": within[2]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["stairs_garage"], choices=list(SCENES))
    ap.add_argument("--seeds", type=int, default=8, help="number of seeds (0 .. N-1)")
    ap.add_argument("--columns", type=int, default=1000)
    ap.add_argument("--diverge-m", type=float, default=1.0)
    ap.add_argument("--out", type=Path, default=Path(".cache/bench_fov"))
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.columns < 16:
        raise SystemExit("error: --seeds must be >= 1 and --columns >= 16")
    register_wide_model()
    rows: dict[tuple[str, str], list[dict]] = {}
    for scene in args.scenes:
        for seed in range(args.seeds):
            for lidar in ("xt32", WIDE):
                r = run_one(scene, seed, lidar, args.columns, args.out)
                rows.setdefault((scene, lidar), []).append(r)
                print(f"{scene} seed {seed} {lidar}: ATE {r['ate_m'] * 100:.1f} cm, first-pose max "
                      f"{r['max_first_m'] * 100:.1f} cm, z within 3σ {r['z_within'] * 100:.0f} %",
                      flush=True)
    cmd = "python benchmarks/bench_fov.py " + " ".join(sys.argv[1:] if argv is None else argv)
    print(f"\nCommand: `{cmd}` ({args.columns} columns, default config of each sequence)\n")
    print("| scene | LiDAR | ATE SE(3) mean (worst) | first-pose max > "
          f"{args.diverge_m:g} m | z within 3σ mean (worst) |")
    print("|---|---|---|---|---|")
    for (scene, lidar), rs in rows.items():
        a = np.array([r["ate_m"] for r in rs]) * 100
        z = np.array([r["z_within"] for r in rs]) * 100
        n_div = sum(r["max_first_m"] > args.diverge_m for r in rs)
        view = "+15..-16°" if lidar == "xt32" else f"±{WIDE_HALF_FOV_DEG:g}°"
        print(f"| {scene} | {lidar} ({view}) | {a.mean():.1f} cm ({a.max():.1f} cm) | "
              f"{n_div}/{len(rs)} | {z.mean():.0f} ({z.min():.0f}) % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
