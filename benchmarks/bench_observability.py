"""Ground truth: where the simulated scenes hide the height, and what the IMU alone loses there.

For each scene and seed this rebuilds the simulator's scene, walking route and IMU stream exactly
as ``adalio.sim.simulate`` does (same seeds, so the same accelerometer bias walk as the cached
bag) and ray-casts noise-free sweeps every ``--step`` seconds. A return counts as *height
evidence* when it hits a mesh face with ``|n_z| > 0.95`` (floor, tread, landing, ceiling) at more
than ``--min-range`` metres (so the operator's body and the handrail under the sensor do not
count). A sweep with fewer than ``--min-points`` such returns is *height-blind*: its LiDAR
residuals carry no height information whatever the estimator does with them.

Over each height-blind stretch of at least 1 s the height can only come from integrating the
accelerometer. Starting from a perfect state and a perfect bias at the start of the stretch, the
height error at its end is the double integral of the change of the true world-z accelerometer
bias (the simulator's random walk, ``ImuNoise.accel_bias_walk_m_s3_sqrt_hz``). That is a floor:
no estimator using this LiDAR and IMU does better on average, and errors of successive stretches
are not undone (the map of the next stretch is built at the drifted height).

Prints one row per scene and seed: share of height-blind sweeps, longest stretch, and the floor
(root-sum-square of the per-stretch errors, and the largest one), then the command.

    python benchmarks/bench_observability.py --scenes spiral stairs_garage --seeds 4
"""

from __future__ import annotations

import argparse
import shlex
import sys

import numpy as np

from adalio.pipeline import _flag_ranges
from adalio.sim import SCENES
from adalio.sim.evidence import height_evidence
from adalio.sim.generate import IMU_RATE_HZ, START_NS
from adalio.sim.imu import ImuNoise, synthesize_imu

MIN_STRETCH_S = 1.0


def blind_stretches(t_s: np.ndarray, blind: np.ndarray, step_s: float) -> list[tuple[float, float]]:
    """(start, end) in seconds of the runs of ``blind`` sweeps lasting >= MIN_STRETCH_S (the
    pipeline's run finder; a run ends one step after its last blind sweep)."""
    runs = _flag_ranges([round(t * 1e9) for t in t_s], blind.tolist())
    return [(a, b + step_s) for a, b in runs if b + step_s - a >= MIN_STRETCH_S]


def imu_height_floor(traj, dur_s: float, seed: int,
                     stretches: list[tuple[float, float]]) -> list[float]:
    """Height error (m) at the end of each stretch from the true accelerometer bias walk alone."""
    dt_ns = round(1e9 / IMU_RATE_HZ)
    t_imu = START_NS + np.arange(round(dur_s * 1e9) // dt_ns + 1, dtype=np.int64) * dt_ns
    imu = synthesize_imu(traj, t_imu, START_NS, np.random.default_rng([seed, 200]), ImuNoise(),
                         1.0, IMU_RATE_HZ)
    t_rel = (t_imu - START_NS) * 1e-9
    R_world_imu = traj.sample(t_rel).R_world_imu
    bias_z = np.einsum("nj,nj->n", R_world_imu[:, 2, :], imu.accel_bias_m_s2)
    dt = 1.0 / IMU_RATE_HZ
    errors = []
    for start, end in stretches:
        m = (t_rel >= start) & (t_rel <= end)
        dv = np.cumsum(bias_z[m] - bias_z[m][0]) * dt
        errors.append(float(np.sum(dv) * dt))
    return errors


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--seeds", type=int, default=2, help="number of seeds (0 .. N-1)")
    ap.add_argument("--step", type=float, default=0.2, help="seconds between analysed sweeps")
    ap.add_argument("--min-points", type=int, default=20)
    ap.add_argument("--min-range", type=float, default=1.0)
    args = ap.parse_args()
    print("| scene | seed | height-blind sweeps | longest stretch | IMU floor RSS | "
          "worst stretch |")
    print("|---|---|---|---|---|---|")
    for scene in args.scenes:
        for seed in range(args.seeds):
            t_s, counts, traj, dur = height_evidence(scene, seed, args.step, args.min_range)
            blind = counts < args.min_points
            stretches = blind_stretches(t_s, blind, args.step)
            errs = imu_height_floor(traj, dur, seed, stretches)
            longest = max((b - a for a, b in stretches), default=0.0)
            rss = float(np.sqrt(np.sum(np.square(errs)))) if errs else 0.0
            worst = max((abs(e) for e in errs), default=0.0)
            print(f"| {scene} | {seed} | {100 * blind.mean():.0f} % | {longest:.1f} s | "
                  f"{100 * rss:.1f} cm | {100 * worst:.1f} cm |", flush=True)
    print(f"\n`python {shlex.join(sys.argv)}`")


if __name__ == "__main__":
    main()
