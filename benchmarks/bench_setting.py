"""Time per scan of an optional setting (``--set``) against the same run without it.

For each sequence, the simulator's bag (``adalio.sim.cached_sequence``) is run with the setting
off and on, alternately, ``--repeats`` times each in this one process, and the median wall ms
per scan of each run (``RunResult.ms_per_scan_median``) is printed with the ratio of their
medians. Absolute times on a shared machine are noisy; the ratio is the figure.

    python benchmarks/bench_setting.py --set filter.local_surface_check=true
    python benchmarks/bench_setting.py --set filter.robust_kernel=geman_mcclure
    python benchmarks/bench_setting.py --set filter.robust_kernel=geman_mcclure \
        --runs spiral:0:2000 hall:0:512 --repeats 3
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from bench_modes import parse_overrides

from adalio.config import load_config
from adalio.pipeline import run_bag
from adalio.sim import cached_sequence

DEFAULT_RUNS = ("spiral:0:2000", "hall:0:2000", "stairs_garage:3:512")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", default=list(DEFAULT_RUNS),
                    metavar="SCENE:SEED:COLUMNS", help="XT-32 sequences to time")
    ap.add_argument("--repeats", type=int, default=2, help="runs per setting and sequence")
    ap.add_argument("--set", action="append", required=True, metavar="KEY=VALUE",
                    help="the setting timed against the default (repeatable)")
    args = ap.parse_args(argv)
    setting = parse_overrides(args.set)
    print(f"setting: {setting}")
    print("| sequence | off, ms/scan | on, ms/scan | rows dropped by the check | ratio |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.runs:
            scene, seed, columns = spec.split(":")
            sim = cached_sequence(scene, seed=int(seed), duration_s=None, lidar="xt32",
                                  fmt="ros1", columns=int(columns))
            ms: dict[bool, list[float]] = {False: [], True: []}
            dropped = (0, 0)
            for _ in range(args.repeats):
                for on in (False, True):
                    cfg = load_config(None, sim.config_path, overrides=setting if on else {})
                    res = run_bag(sim.bag_path, cfg, Path(tmp) / f"{scene}_{seed}_{on}",
                                  progress=False)
                    ms[on].append(res.ms_per_scan_median)
                    if on:
                        dropped = res.local_surface_rows
            off, on_ = statistics.median(ms[False]), statistics.median(ms[True])
            share = 100.0 * dropped[0] / max(dropped[1], 1)
            print(f"| {scene} seed {seed}, {columns} columns | {off:.1f} | {on_:.1f} | "
                  f"{share:.2f} % | {on_ / off:.2f}x |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
