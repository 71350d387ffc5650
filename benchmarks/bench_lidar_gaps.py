"""Benchmark: seconds without a scan (a LiDAR gap), and the scan after one.

A LiDAR's driver restarts, a cable shakes loose, a bag drops a topic for a while: the IMU alone
carries the pose across, and the scan after the gap must find the map again from a prediction
that can be decimetres off. For every scene, seed, IMU noise level (x the HILTI BMI085's white
noise) and gap length, the simulator's whole sequence is fed through the Python API with the
scans ending in ``[start, start + gap]`` dropped, up to ``--after-s`` seconds after the gap,
once per ``filter.gate_sigmas`` given (0: FAST-LIO2's range gate alone; the default 3 also
admits the residuals the predicted pose covariance allows).

Per run, positions aligned on the first pose (the world is the IMU frame at the start): the
largest error from the scan after the gap on, the error at the last scan, and whether the scan
after the gap claims less than a third of its error on some axis. The predicted position sigma
at the gap's end is what the run's warning says (``Odometry.lidar_gaps``). Gap 0 is the run
without a gap, over the same stretch.

    python benchmarks/bench_lidar_gaps.py                    # hall, corridor, spiral; 2 seeds
    python benchmarks/bench_lidar_gaps.py --scenes hall --seeds 1 --gaps 5 --gate-sigmas 0 3
    python benchmarks/bench_lidar_gaps.py --imu-rate 100 --gate-sigmas 3     # an Ouster's IMU
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
import warnings
from dataclasses import dataclass

import numpy as np
from evo.core.trajectory import PoseTrajectory3D

from adalio import Bag, ImuBatch, Odometry, Sequencer, load_config
from adalio.eval.metrics import align_pair
from adalio.sim import cached_sequence
from adalio.sim.generate import IMU_RATE_HZ, SimResult


@dataclass
class GapRun:
    """One run with the scans of a window dropped."""

    t_s: np.ndarray
    """(n,) the estimates' times, s after the bag start."""
    errors_m: np.ndarray
    """(n, 3) position errors after aligning the first pose."""
    sigmas_m: np.ndarray
    """(n, 3) the reported world position sigmas."""
    lidar_gap_s: np.ndarray
    """(n,) ``ScanStats.lidar_gap_s``."""
    odometry: Odometry
    warnings: list[str]
    """The LiDAR-gap warnings."""


def run_with_gap(sim: SimResult, gap_s: tuple[float, float] | None, stop_s: float,
                 gate_sigmas: float | None = None) -> GapRun:
    """Feed ``sim`` without the scans ending in ``gap_s`` (s after the bag start), up to
    ``stop_s``; ``gate_sigmas`` None: the sequence config's."""
    cfg = load_config(config_file=sim.config_path)
    if gate_sigmas is not None:
        cfg.filter.gate_sigmas = gate_sigmas
    odom = Odometry(cfg)
    t_ns, T, sigma, gap = [], [], [], []
    with Bag(sim.bag_path) as bag, warnings.catch_warnings(record=True) as caught:
        start_ns = bag.start_ns
        warnings.simplefilter("always")
        for item in Sequencer(bag, cfg.sensor.lidar_topic, cfg.sensor.imu_topic, cfg.sensor):
            if isinstance(item, ImuBatch):
                odom.add_imu(item.t_ns, item.gyro_rad_s, item.accel_m_s2)
                continue
            rel_s = (item.t_end_ns - start_ns) * 1e-9
            if rel_s > stop_s:
                break
            if gap_s is not None and gap_s[0] < rel_s < gap_s[1]:
                continue
            est = odom.add_scan(item.points_lidar, item.t_ns)
            if est is not None:
                t_ns.append(est.t_ns)
                T.append(est.T_world_imu)
                sigma.append(est.stats.sigma_p_world_m)
                gap.append(est.stats.lidar_gap_s)
    est = PoseTrajectory3D(poses_se3=T, timestamps=np.asarray(t_ns) * 1e-9)
    pair = align_pair(est, sim.gt_path, align="first")  # the GT interpolated at the stamps
    if pair.est.num_poses != len(t_ns):
        raise RuntimeError(f"{len(t_ns) - pair.est.num_poses} estimates without a GT pose")
    # errors in the estimate's world, the frame of its sigmas
    err = (pair.est.positions_xyz - pair.gt.positions_xyz) @ pair.T_gt_est[:3, :3]
    msgs = [str(w.message) for w in caught if "LiDAR gap" in str(w.message)]
    return GapRun((np.asarray(t_ns) - start_ns) * 1e-9, err, np.asarray(sigma), np.asarray(gap),
                  odom, msgs)


def _mean_worst(values: list[float]) -> str:
    return f"{np.mean(values):.1f} ({np.max(values):.1f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["hall", "corridor", "spiral"])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--imu-noise", nargs="+", type=float, default=[1.0, 10.0])
    ap.add_argument("--gaps", nargs="+", type=float, default=[0.0, 1.0, 3.0, 5.0],
                    help="seconds without a scan (0: none)")
    ap.add_argument("--start-s", type=float, default=12.0, help="the gap starts here")
    ap.add_argument("--after-s", type=float, default=8.0, help="seconds run after the gap")
    ap.add_argument("--gate-sigmas", nargs="+", type=float, default=[0.0, 3.0])
    ap.add_argument("--columns", type=int, default=512)
    ap.add_argument("--imu-rate", type=float, default=IMU_RATE_HZ,
                    help="the simulated IMU's rate, Hz (default: the BMI085's 400)")
    args = ap.parse_args()
    rows: dict[tuple[str, float, float], list[dict]] = {}
    t0 = time.time()
    for scene, seed, noise, gap in itertools.product(args.scenes, range(args.seeds),
                                                     args.imu_noise, args.gaps):
        sim = cached_sequence(scene, seed=seed, imu_noise_scale=noise, columns=args.columns,
                              imu_rate_hz=args.imu_rate)
        window = (args.start_s, args.start_s + gap) if gap > 0 else None
        for gate in args.gate_sigmas:
            run = run_with_gap(sim, window, args.start_s + gap + args.after_s, gate)
            i = int(np.searchsorted(run.t_s, args.start_s, side="right"))  # after the gap
            e = np.linalg.norm(run.errors_m[i:], axis=1) * 100
            z = np.abs(run.errors_m[i] / run.sigmas_m[i])
            pred = run.odometry.lidar_gaps[0][2] if run.odometry.lidar_gaps else None
            row = {"scene": scene, "seed": seed, "imu": noise, "gap_s": gap,
                   "gate_sigmas": gate, "max_after_cm": round(float(e.max()), 2),
                   "end_cm": round(float(e[-1]), 2), "first_z": round(float(z.max()), 2),
                   "sigma_pred_m": None if pred is None else round(pred, 3)}
            print(json.dumps(row), flush=True)
            rows.setdefault((scene, gap, gate), []).append(row)
    print("\n| scene | gap | gate_sigmas | runs | largest error after the gap, cm | error at "
          "the end, cm | scan after the gap beyond 3 sigma | predicted sigma, cm |")
    print("|---|---|---|---|---|---|---|---|")
    for (scene, gap, gate), rs in rows.items():
        pred = [r["sigma_pred_m"] * 100 for r in rs if r["sigma_pred_m"] is not None]
        print(f"| {scene} | {gap:g} s | {gate:g} | {len(rs)} | "
              f"{_mean_worst([r['max_after_cm'] for r in rs])} | "
              f"{_mean_worst([r['end_cm'] for r in rs])} | "
              f"{sum(r['first_z'] > 3 for r in rs)} | "
              f"{_mean_worst(pred) if pred else '-'} |")
    print(f"\n{sum(len(r) for r in rows.values())} runs in {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
