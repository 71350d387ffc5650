"""Benchmark: fixed vs adaptive vs adaptive+ on the simulator's scenes (issue #5).

For every scene and seed, the simulator's sequence (``adalio.sim.cached_sequence``) is run
through ``adalio.pipeline.run_bag`` with the sequence's own ``config.yaml`` and only
``adaptive.mode`` overridden; sequences and runs are tasks of the batch layer
(``adalio.batch``) on an embedded Dask cluster with ``--workers`` processes (default: the
number of cores), or on an existing one with ``--scheduler tcp://HOST:PORT``. Per run: ATE RMSE
after SE(3) (Umeyama) and first-pose alignment
(``adalio.eval.metrics.ate``, translation part, metres), the max first-pose-aligned error,
divergence (max first-pose-aligned error > ``--diverge-m`` (1 m), or the run aborted / stopped
before 90 % of the scans), the share of scans the detector put in the degenerate set, and the
median wall time per scan.

Prints one markdown table (RMSE per seed 'a / b', or mean (worst) beyond 3 seeds), the command that made
it, and the per-scene distributions of N_down / N_near / degeneracy score (from the fixed
runs, whose detector still reports them) with the share of scans each threshold would flag,
so that tau_n / tau_near are judged on all scenes, not tuned on one.

    python benchmarks/bench_modes.py --scenes hall corridor --seeds 2 --duration 30
    python benchmarks/bench_modes.py --scenes stairs_garage --seeds 8 --imu-bias-scale 0
    python benchmarks/bench_modes.py --motion-from \
        tests/data/real/hilti2022_gt/exp_04_construction_upper_level_easy_2_2022-03-03-11-48-59_imu.txt
"""

from __future__ import annotations

import argparse
import contextlib
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from adalio.batch import BagJob, BagRow, BatchResult, dask_client, run_jobs
from adalio.config import MODES, config_from_dict, load_config, set_options
from adalio.errors import ConfigError, InputError
from adalio.eval.files import read_scans_csv
from adalio.eval.metrics import ate, sigma_consistency
from adalio.sim import SCENES, cached_sequence


@dataclass
class RunRow:
    scene: str
    seed: int
    mode: str
    ate_se3_m: float = float("nan")
    ate_first_m: float = float("nan")
    max_err_m: float = float("nan")
    diverged: bool = True
    aborted: str = ""
    pct_degenerate: float = float("nan")
    ms_per_scan: float = float("nan")
    n_scans: int = 0
    sim_failed: bool = False
    within_3sigma: tuple[float, float, float] = (float("nan"),) * 3
    """Share of scans whose error (aligned on the filter's first scan) is within 3 sigma on x, y,
    z."""
    mean_nees: float = float("nan")
    increment_corr: tuple[float, float, float] = (float("nan"),) * 3
    """Lag-1 correlation of the error's 1 s increments on x, y, z (+1: drift, 0: random walk)."""
    scans: dict[str, np.ndarray] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "scans"}


def gt_scan_count(gt_path: Path, lidar_rate_hz: float) -> int:
    t = np.loadtxt(gt_path, usecols=0, comments="#", ndmin=1)
    return int((t[-1] - t[0]) * lidar_rate_hz) if t.size > 1 else 0


def parse_overrides(items: list[str]) -> dict[str, str]:
    """``--set KEY=VALUE`` items as config overrides, checked once against the config's fields
    and ranges: a bad one ends the benchmark with one ``error:`` line before any run."""
    try:
        out = set_options(items)
    except ConfigError as exc:
        raise SystemExit(f"error: {exc}") from None
    try:
        load_config(overrides=out)
    except ConfigError as exc:
        raise SystemExit(f"error: --set: {exc}") from None
    return out


def run_dir(out_root: Path, scene: str, seed: int, mode: str) -> Path:
    return out_root / f"{scene}_s{seed}_{mode.replace('+', 'plus')}"


def sequences(client, scenes: list[str], seeds: int, duration_s: float | None,
              motion_from: Path | None = None, imu_bias_scale: float = 1.0) -> dict:
    """(scene, seed) -> SimResult, or the one-line reason the simulator failed; generated (or
    taken from the cache) as tasks on the cluster."""
    keys = [(scene, seed) for scene in scenes for seed in range(seeds)]
    futures = [client.submit(cached_sequence, scene, seed=seed, duration_s=duration_s,
                             motion_from=motion_from, imu_bias_scale=imu_bias_scale,
                             pure=False) for scene, seed in keys]
    out: dict = {}
    for key, fut in zip(keys, futures, strict=True):
        try:
            out[key] = fut.result()
        except Exception as exc:  # noqa: BLE001 - reported in the table, not a divergence
            out[key] = f"simulator: {exc}".splitlines()[0][:120]
    return out


def run_row(bag_row: BagRow, job: BagJob, scene: str, seed: int, mode: str, sim,
            diverge_m: float) -> RunRow:
    """The benchmark's metrics of one finished batch task."""
    row = RunRow(scene, seed, mode)
    if bag_row.status != "ok":
        row.aborted = bag_row.error[:120] or bag_row.status
        return row
    row.n_scans = bag_row.poses
    row.ms_per_scan = bag_row.ms_per_scan
    row.scans = read_scans_csv(job.run_dir / "scans.csv")
    if len(row.scans["t_s"]):
        row.pct_degenerate = 100.0 * float(np.mean(row.scans["degenerate"]))
    expected = gt_scan_count(sim.gt_path, job.config.sensor.lidar_rate_hz)
    if expected and row.n_scans < 0.9 * expected - 5:
        row.aborted = f"stopped at {row.n_scans}/{expected} scans"
    try:
        first = ate(job.run_dir / "trajectory.tum", sim.gt_path, align="first")
    except Exception as exc:  # noqa: BLE001
        row.aborted = row.aborted or f"eval failed: {exc}".splitlines()[0][:120]
        return row
    row.ate_se3_m = bag_row.ate_se3_m
    row.ate_first_m = first["rmse_m"]
    row.max_err_m = first["max_m"]
    row.diverged = bool(row.aborted) or not (row.max_err_m <= diverge_m)
    with contextlib.suppress(InputError):
        cons = sigma_consistency(job.run_dir / "trajectory.tum", sim.gt_path, row.scans)
        row.within_3sigma = tuple(float(v) for v in cons.within_3sigma)
        row.mean_nees = cons.mean_nees
        row.increment_corr = tuple(float(v) for v in cons.increment_correlation)
    return row


def sigma_table(rows: list[RunRow]) -> str:
    """Per scene and mode: share of scans within 3 sigma per axis (mean and worst run), the
    mean NEES (3 for an honest covariance) and the mean correlation of consecutive 1 s error
    increments per axis (how much the error drifts one way: the reason the sigmas combine the
    map's and the filter's errors as correlated, lio/map_uncertainty.py)."""
    lines = [("| scene | mode | within 3σ x | within 3σ y | within 3σ z | mean NEES "
              "| error increments' correlation x / y / z |"),
             "|" + "---|" * 7]
    for scene, mode in dict.fromkeys((r.scene, r.mode) for r in rows):
        rs = [r for r in rows if r.scene == scene and r.mode == mode
              and np.isfinite(r.mean_nees)]
        if not rs:
            continue
        w = np.array([r.within_3sigma for r in rs])
        cells = [f"{100 * w[:, k].mean():.0f} % ({100 * w[:, k].min():.0f})" for k in range(3)]
        nees = np.array([r.mean_nees for r in rs])
        corr = np.nanmean(np.array([r.increment_corr for r in rs]), axis=0)
        lines.append(f"| {scene} | {mode} | {' | '.join(cells)} | {nees.mean():.3g} "
                     f"({nees.max():.3g}) | {' / '.join(f'{c:+.2f}' for c in corr)} |")
    return "\n".join(lines)


def triggers(row: RunRow) -> str:
    if "trigger" not in row.scans:
        return ""
    names, counts = np.unique(row.scans["trigger"], return_counts=True)
    return ",".join(f"{n or 'none'}:{c}" for n, c in zip(names, counts, strict=True))


def fmt_cm(values: list[float]) -> str:
    """Per seed ('a / b') up to 3 seeds, else mean (worst); cm below 1 m, '>100 m' beyond."""
    vals = np.array(values, dtype=float)
    if vals.size == 0 or np.all(np.isnan(vals)):
        return "–"

    def one(v: float) -> str:
        if v < 1.0:
            return f"{v * 100:.1f} cm"
        return f"{v:.2f} m" if v < 100.0 else ">100 m"

    if len(vals) <= 3:
        return " / ".join("–" if np.isnan(v) else one(float(v)) for v in vals)
    return f"{one(float(np.nanmean(vals)))} ({one(float(np.nanmax(vals)))})"


def results_table(rows: list[RunRow]) -> str:
    head = ("| scene | mode | ATE SE(3) | ATE first-pose | max err | diverged | "
            "% degenerate | ms/scan |")
    lines = [head, "|" + "---|" * 8]
    keys = list(dict.fromkeys((r.scene, r.mode) for r in rows))
    for scene, mode in keys:
        rs = [r for r in rows if r.scene == scene and r.mode == mode]
        if all(r.sim_failed for r in rs):
            lines.append(f"| {scene} | {mode} | simulator failed |  |  |  |  |  |")
            continue
        rs = [r for r in rs if not r.sim_failed]
        ok = [r for r in rs if not r.aborted]
        div = sum(r.diverged for r in rs)
        pct = np.nanmean([r.pct_degenerate for r in rs]) if ok else float("nan")
        ms = np.nanmedian([r.ms_per_scan for r in rs]) if ok else float("nan")
        lines.append(
            f"| {scene} | {mode} | {fmt_cm([r.ate_se3_m for r in rs])} | "
            f"{fmt_cm([r.ate_first_m for r in rs])} | {fmt_cm([r.max_err_m for r in rs])} | "
            f"{div}/{len(rs)} | {pct:.0f} | {ms:.0f} |")
    return "\n".join(lines)


def pct3(x: np.ndarray) -> str:
    return "/".join(f"{v:.0f}" for v in np.percentile(x, [5, 50, 95]))


def threshold_table(rows: list[RunRow], cfg_adaptive) -> str:
    a = cfg_adaptive
    title = (f"Per-scene N_down / N_near (general leaf {a.general.voxel_size_m} m, d_xy "
             f"{a.d_xy_m} m), from the fixed runs; flags at tau_n={a.tau_n}, "
             f"tau_near={a.tau_near}, near_ratio={a.near_ratio}, "
             f"min_eigen_ratio={a.min_eigen_ratio}:")
    head = ("| scene | scans | N_down p5/p50/p95 | N_near p5/p50/p95 | near/down p50 | "
            "score p50/p95 | N_down<tau_n % | N_near<tau_near % | near_ratio rule % |")
    lines = [title, "", head, "|" + "---|" * 9]
    for scene in dict.fromkeys(r.scene for r in rows):
        rs = [r for r in rows if r.scene == scene and r.mode == "fixed" and r.scans]
        if not rs:
            rs = [r for r in rows if r.scene == scene and r.scans]
        if not rs:
            continue
        nd = np.concatenate([r.scans["n_down_general"] for r in rs])
        nn = np.concatenate([r.scans["n_near"] for r in rs])
        sc = np.concatenate([r.scans["degeneracy_score"] for r in rs])
        frac = np.divide(nn, nd, out=np.ones_like(nn), where=nd > 0)
        rule = (nd < a.tau_n) & (frac > a.near_ratio)
        lines.append(
            f"| {scene} | {nd.size} | {pct3(nd)} | {pct3(nn)} | {np.median(frac):.2f} | "
            f"{np.median(sc):.2f}/{np.percentile(sc, 95):.2f} | "
            f"{100 * np.mean(nd < a.tau_n):.0f} | {100 * np.mean(nn < a.tau_near):.0f} | "
            f"{100 * np.mean(rule):.0f} |")
    return "\n".join(lines)


def run_all(args: argparse.Namespace, overrides: dict[str, str], out_root: Path,
            t0: float) -> tuple[BatchResult, list[RunRow]]:
    """Sequences, then every (scene, seed, mode) run, on one Dask cluster; rows in table order.
    Prints one line per run as it finishes."""
    runs: dict[str, tuple[str, int, str, object]] = {}
    failed_sims: list[RunRow] = []
    jobs: list[BagJob] = []
    with dask_client(args.workers, args.scheduler) as client:
        sims = sequences(client, args.scenes, args.seeds, args.duration, args.motion_from,
                         args.imu_bias_scale)
        for scene in args.scenes:
            for seed in range(args.seeds):
                sim = sims[(scene, seed)]
                for mode in args.modes:
                    if isinstance(sim, str):
                        failed_sims.append(RunRow(scene, seed, mode, aborted=sim,
                                                  diverged=False, sim_failed=True))
                        continue
                    cfg = load_config(config_file=sim.config_path,
                                      overrides={**overrides, "adaptive.mode": mode})
                    name = run_dir(out_root, scene, seed, mode).name
                    jobs.append(BagJob(name, sim.bag_path, cfg, out_root, sim.gt_path))
                    runs[name] = (scene, seed, mode, sim)
        by_name = {j.name: j for j in jobs}
        done: dict[str, RunRow] = {}

        def report(bag_row: BagRow) -> None:
            scene, seed, mode, sim = runs[bag_row.bag]
            row = run_row(bag_row, by_name[bag_row.bag], scene, seed, mode, sim,
                          args.diverge_m)
            done[bag_row.bag] = row
            took = "reused" if bag_row.skipped else f"{bag_row.wall_s:.0f} s"
            print(f"[{time.perf_counter() - t0:7.0f} s] {scene} seed {seed} {mode}: "
                  f"ATE se3 {row.ate_se3_m:.3f} m first {row.ate_first_m:.3f} m max "
                  f"{row.max_err_m:.3f} m degenerate {row.pct_degenerate:.0f} % "
                  f"{row.ms_per_scan:.0f} ms/scan {triggers(row)} {row.aborted} "
                  f"({took}, {bag_row.worker})", file=sys.stderr, flush=True)

        result = run_jobs(jobs, out_root, client=client, force=not args.resume, on_row=report)
    rows = failed_sims + [done[j.name] for j in jobs if j.name in done]
    order = {(sc, sd, m): k for k, (sc, sd, m) in enumerate(
        (sc, sd, m) for sc in args.scenes for sd in range(args.seeds) for m in args.modes)}
    rows.sort(key=lambda r: order[(r.scene, r.seed, r.mode)])
    return result, rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--seeds", type=int, default=2, help="number of seeds (0 .. N-1)")
    ap.add_argument("--duration", type=float, default=None,
                    help="sequence length in seconds (default: the simulator's)")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    ap.add_argument("--diverge-m", type=float, default=1.0,
                    help="a run diverged if its max first-pose-aligned error exceeds this")
    ap.add_argument("--out", type=Path, default=Path(".cache/bench_modes"))
    ap.add_argument("--imu-bias-scale", type=float, default=1.0,
                    help="multiplier of the simulated IMU's initial biases and bias walks "
                    "(0: an IMU without bias, to separate what the bias costs)")
    ap.add_argument("--motion-from", type=Path, default=None, metavar="TUM",
                    help="walk with the handheld motion of this real trajectory (e.g. "
                    "tests/data/real/hilti2022_gt/exp_04_..._imu.txt) instead of the "
                    "simulator's synthetic one; 'none': no hand motion (a robot's walk)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every run, e.g. --set adaptive.tau_n=1500")
    ap.add_argument("--resume", action="store_true",
                    help="reuse finished runs found in --out (the batch layer's markers: "
                         "same bag, ground truth and config)")
    ap.add_argument("--workers", type=int, default=None,
                    help="worker processes of the embedded Dask cluster (default: cores); "
                         "ms/scan is timed under that parallel load, use 1 for timings")
    ap.add_argument("--scheduler", default=None,
                    help="existing Dask scheduler (tcp://HOST:PORT) on a shared filesystem")
    args = ap.parse_args(argv)
    overrides = parse_overrides(args.set)
    if not args.imu_bias_scale >= 0:
        raise SystemExit(f"error: --imu-bias-scale must be >= 0 (got {args.imu_bias_scale})")
    out_root = args.out.expanduser().resolve()

    t0 = time.perf_counter()
    try:
        result, rows = run_all(args, overrides, out_root, t0)
    except KeyboardInterrupt:
        result = None
    if result is None or result.interrupted:
        print("interrupted: finished runs are kept (rerun with --resume)", file=sys.stderr)
        return 130

    saved = [run_dir(out_root, r.scene, r.seed, r.mode) / "config.yaml" for r in rows]
    saved = [p for p in saved if p.is_file()]
    cfg0 = (config_from_dict(yaml.safe_load(saved[0].read_text())) if saved
            else load_config(overrides=overrides))
    cmd = "python benchmarks/bench_modes.py " + " ".join(
        shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    print(f"Command: `{cmd.strip()}`  ({args.seeds} seeds, duration "
          f"{args.duration or 'default'} s, divergence = max first-pose error > "
          f"{args.diverge_m} m or run aborted)\n")
    print(results_table(rows))
    print()
    print(threshold_table(rows, cfg0.adaptive))
    print()
    print("Uncertainty: mean (worst) over seeds")
    print(sigma_table(rows))
    aborted = [r for r in rows if r.aborted]
    if aborted:
        print()
        for r in aborted:
            print(f"- aborted: {r.scene} seed {r.seed} {r.mode}: {r.aborted}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
