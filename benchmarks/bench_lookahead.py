"""Benchmark: a second pass that looks ahead (the leading edge's share of the error, measured).

Issue #14's shaft error comes mostly from the map's leading edge: where the sensor moves into
space it has not mapped, every map neighbourhood lies on the side it came from, and the rows
pull the pose back up the helix (README, *Where adalio stands*; benchmark log, Session 41).
This benchmark measures what a map on both sides would give, without a smoother: pass 1 is the
default run; pass ``n`` runs the estimator again on the same bag, and each scan's update
searches, besides its own map, the points pass ``n - 1`` inserted from the next scan on, over
``--look-ahead-s`` seconds (never the scan's own points), placed by pass ``n - 1``'s motion from
the previous scan (:func:`place_future`), so anchored at this pass's previous pose: anchoring
them at the current scan's prediction would confirm any velocity error (Session 41). The future
points only fill map cells that hold no point yet (the map's own insertion rule), they never
enter the map kept for later scans, and the backfill's reversed pass does not look ahead.

Per run: SE(3)-aligned ATE RMSE and the largest error after aligning the first pose, of every
pass, and the median time per scan (the estimator's, as ``adalio run`` reports it) of the first
and the last pass: the last one's includes the map copy a look-ahead makes per scan. The
summary gives, per scene and IMU noise, each pass's mean (worst). A measurement, not a mode
(benchmark log, Session 57).

    python benchmarks/bench_lookahead.py --scenes spiral --seeds 4 --lidars xt32-512
    python benchmarks/bench_lookahead.py --scenes corridor stairs_garage --passes 2
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import shlex
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from bench_modes import parse_overrides
from bench_sensors import LIDARS

import adalio.lio
from adalio.config import load_config
from adalio.eval.metrics import ate
from adalio.lio import Odometry
from adalio.lio.odometry import MIN_POINTS_FOR_UPDATE
from adalio.pipeline import run_bag
from adalio.sim import cached_sequence
from adalio.types import Estimate

MATCH_NS = 20_000_000
"""A scan of the earlier pass is 'the same scan' within 20 ms (both passes read the same clouds,
so their scan ends are equal but for the preprocessing's dropped points; a sweep lasts 50-100
ms)."""


def place_future(T_prev_now: np.ndarray, T_prev_then: np.ndarray,
                 points_then: np.ndarray) -> np.ndarray:
    """World points of the earlier pass moved into this pass's world: ``T_prev_now ·
    T_prev_then⁻¹ · p``, i.e. the earlier pass's motion from the previous scan (pose
    ``T_prev_then``, 4x4 world-from-IMU) to the scan that inserted ``p``, applied from this
    pass's pose at that previous scan (``T_prev_now``)."""
    A = T_prev_now @ np.linalg.inv(T_prev_then)
    return points_then @ A[:3, :3].T + A[:3, 3]


@dataclass
class PassRecord:
    """What one pass left for the next: per scan end (ns), the IMU pose and the points it put
    into its map (world frame)."""

    poses: dict[int, np.ndarray] = field(default_factory=dict)
    points: dict[int, np.ndarray] = field(default_factory=dict)

    def add(self, est: Estimate) -> None:
        if est.stats.backfill or est.points_world is None:
            return
        t = int(est.t_ns)
        self.poses[t] = est.T_world_imu.copy()
        self.points[t] = np.asarray(est.points_world, dtype=np.float64).copy()

    def pose_at(self, t_ns: int) -> np.ndarray | None:
        return self.poses.get(int(t_ns))

    def ahead(self, t_from_ns: int, t_to_ns: int) -> list[np.ndarray]:
        """Points of the scans after the one ending at ``t_from_ns`` (not that scan: its own
        points would be matched to themselves) up to ``t_to_ns``, in time order."""
        return [self.points[t] for t in sorted(self.points) if t_from_ns + MATCH_NS < t <= t_to_ns]


def look_ahead_odometry(earlier: PassRecord, look_ahead_s: float) -> type[Odometry]:
    """An :class:`Odometry` whose updates also search ``earlier``'s next ``look_ahead_s``."""

    class LookAhead(Odometry):
        looks = True

        def _reversed_copy(self, mirror_ns: int) -> Odometry:
            rev = super()._reversed_copy(mirror_ns)
            rev.looks = False
            return rev

        def _add_scan(self, points_lidar, t_ns, ring):
            ready = (self.looks and self.initialized and self._t_first_map_ns is not None)
            T_then = earlier.pose_at(self._t_state_ns) if ready else None
            if T_then is None:
                return super()._add_scan(points_lidar, t_ns, ring)
            t_end = int(np.max(t_ns))
            ahead = earlier.ahead(t_end, t_end + round(look_ahead_s * 1e9))
            if not ahead:
                return super()._add_scan(points_lidar, t_ns, ring)
            mine = self._ivox
            with_future = copy.deepcopy(mine)
            with_future.add_points(
                place_future(self._state.T_world_imu(), T_then, np.concatenate(ahead)),
                self._map_cell(self.cfg.adaptive.general.voxel_size_m))
            self._ivox = with_future
            try:
                est = super()._add_scan(points_lidar, t_ns, ring)
            finally:
                self._ivox = mine
            # the map kept gets what Odometry inserts: the scan's points, if it updated
            if (est is not None and est.points_world is not None
                    and len(est.points_world) >= MIN_POINTS_FOR_UPDATE):
                mine.add_points(est.points_world, self._map_cell(est.stats.voxel_size_m))
            return est

    return LookAhead


@contextlib.contextmanager
def _estimator(cls: type[Odometry]):
    """``run_bag`` builds ``adalio.lio.Odometry``: this one, for the duration."""
    saved = adalio.lio.Odometry
    adalio.lio.Odometry = cls
    try:
        yield
    finally:
        adalio.lio.Odometry = saved


@dataclass
class Run:
    scene: str
    seed: int
    imu_noise: float
    lidar: str
    imu_bias_scale: float = 1.0
    ate_m: list[float] = field(default_factory=list)
    max_first_m: list[float] = field(default_factory=list)
    ms_per_scan: list[float] = field(default_factory=list)
    error: str = ""


def run_passes(run: Run, passes: int, look_ahead_s: float, out_root: Path,
               overrides: dict[str, str]) -> Run:
    lidar, columns = LIDARS[run.lidar]
    sim = cached_sequence(run.scene, seed=run.seed, lidar=lidar, columns=columns,
                          imu_noise_scale=run.imu_noise, imu_bias_scale=run.imu_bias_scale)
    cfg = load_config(config_file=sim.config_path, overrides=overrides)
    name = f"{run.scene}_s{run.seed}_imu{run.imu_noise:g}_{run.lidar}"
    name += "" if run.imu_bias_scale == 1.0 else f"_bias{run.imu_bias_scale:g}"
    earlier: PassRecord | None = None
    for n in range(1, passes + 1):
        record = PassRecord()
        cls = Odometry if earlier is None else look_ahead_odometry(earlier, look_ahead_s)
        out = out_root / name / f"pass{n}"
        try:
            with _estimator(cls):
                res = run_bag(sim.bag_path, cfg, out, progress=False, on_estimate=record.add)
        except Exception as exc:  # noqa: BLE001 - a failed run is reported, the matrix goes on
            run.error = f"pass {n}: {type(exc).__name__}: {exc}".splitlines()[0][:160]
            return run
        tum = str(out / "trajectory.tum")
        run.ate_m.append(ate(tum, sim.gt_path)["rmse_m"])
        run.max_first_m.append(ate(tum, sim.gt_path, align="first")["max_m"])
        run.ms_per_scan.append(res.ms_per_scan_median)
        earlier = record
    return run


def _cm(values: list[float]) -> str:
    return " / ".join(f"{100 * v:.2f}" for v in values)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["spiral"])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=0,
                    help="seeds first-seed .. first-seed + seeds - 1")
    ap.add_argument("--imu-noise", nargs="+", type=float, default=[1.0, 10.0])
    ap.add_argument("--lidars", nargs="+", default=["xt32-512"], choices=list(LIDARS))
    ap.add_argument("--passes", type=int, default=2,
                    help="passes in all (2: the default run, then one that looks ahead)")
    ap.add_argument("--look-ahead-s", type=float, default=0.5,
                    help="seconds of the earlier pass's scans each update also searches")
    ap.add_argument("--imu-bias-scale", type=float, default=1.0,
                    help="the simulated IMU's initial biases and bias walks x this (0: none)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every pass")
    ap.add_argument("--out", type=Path, default=Path("runs/bench_lookahead"))
    args = ap.parse_args(argv)
    if args.passes < 1:
        print(f"error: --passes must be >= 1 (got {args.passes})", file=sys.stderr)
        return 1
    if not (np.isfinite(args.look_ahead_s) and args.look_ahead_s > 0):
        print(f"error: --look-ahead-s must be > 0 seconds (got {args.look_ahead_s})",
              file=sys.stderr)
        return 1
    if not (np.isfinite(args.imu_bias_scale) and args.imu_bias_scale >= 0):
        print(f"error: --imu-bias-scale must be >= 0 (got {args.imu_bias_scale})",
              file=sys.stderr)
        return 1
    overrides = parse_overrides(args.set)
    t0 = time.perf_counter()
    print("| scene | seed | IMU noise | LiDAR | ATE SE(3), cm, pass 1 / 2 / ... | largest error "
          "after aligning the first pose, cm | ms per scan, first / last pass | error |\n"
          "|---|---|---|---|---|---|---|---|", flush=True)
    runs = []
    for scene in args.scenes:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            for noise in args.imu_noise:
                for lidar in args.lidars:
                    r = run_passes(Run(scene, seed, noise, lidar, args.imu_bias_scale),
                                   args.passes,
                                   args.look_ahead_s, args.out, overrides)
                    runs.append(r)
                    ms = (f"{r.ms_per_scan[0]:.1f} / {r.ms_per_scan[-1]:.1f}"
                          if r.ms_per_scan else "")
                    print(f"| {scene} | {seed} | x{noise:g} | {lidar} | {_cm(r.ate_m)} | "
                          f"{_cm(r.max_first_m)} | {ms} | {r.error} |", flush=True)
    print("\n| scene | IMU noise | runs | ATE SE(3) mean (worst), cm, per pass | time per scan, "
          "last pass / first (median over runs) |\n|---|---|---|---|---|")
    for scene in args.scenes:
        for noise in args.imu_noise:
            done = [r for r in runs if r.scene == scene and r.imu_noise == noise
                    and len(r.ate_m) == args.passes]
            if not done:
                continue
            per_pass = [[r.ate_m[i] for r in done] for i in range(args.passes)]
            cells = " / ".join(f"{100 * np.mean(a):.2f} ({100 * np.max(a):.2f})"
                               for a in per_pass)
            ratio = statistics.median(r.ms_per_scan[-1] / r.ms_per_scan[0] for r in done)
            print(f"| {scene} | x{noise:g} | {len(done)} | {cells} | {ratio:.2f} |")
    print(f"\n{len(runs)} runs in {time.perf_counter() - t0:.0f} s; command: python "
          f"benchmarks/bench_lookahead.py {shlex.join(argv if argv is not None else sys.argv[1:])}")
    return 0 if all(not r.error for r in runs) else 1


if __name__ == "__main__":
    raise SystemExit(main())
