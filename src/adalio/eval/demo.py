"""The one-command demo: simulate a spiral staircase descent, run fixed vs adaptive, compare.

Needs no data: the sequence comes from ``adalio.sim.cached_sequence("spiral", ...)`` (generated
once into ``$ADALIO_CACHE_DIR``, default ``~/.cache/adalio``), and both modes run through
:func:`adalio.eval.compare.compare_modes` with the simulator's own ``config.yaml``. ``short``
uses a much shorter, sparser sequence for CI.

Disk: the cached sequence is an mcap bag with zstd-compressed chunks at 1000 azimuth columns
(half the XT-32's 2000 at 10 Hz): about 0.25 GB for the 60 s descent, against 1.8 GB for an
uncompressed ROS1 bag at 2000 columns.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from adalio.eval.compare import CompareResult, compare_modes

DEMO_SCENE = "spiral"
DEMO_MODES = ("fixed", "adaptive")
FULL_DURATION_S: float | None = None
"""Sequence length of the full demo (None = the scene's own default length)."""
FULL_COLUMNS: int | None = 1000
"""Azimuth columns per sweep of the full demo (None = the LiDAR model's default, 2000)."""
DEMO_FORMAT = "mcap"
"""Bag format of the cached demo sequence (mcap: zstd-compressed chunks)."""
DEFAULT_OUT = Path("runs") / "demo"
"""Where ``adalio demo`` writes without ``--out`` (``runs/`` is git-ignored)."""
SHORT_DURATION_S = 18.0
SHORT_COLUMNS = 500


@dataclass
class DemoResult:
    compare: CompareResult
    bag_path: Path
    gt_path: Path
    sim_s: float
    total_s: float
    cache_bytes: int = 0
    """Disk use of the cached sequence (bag, ground truth, scene mesh, metadata)."""


def disk_bytes(path: str | Path) -> int:
    """Size of a file, or of all files under a folder (bytes)."""
    p = Path(path)
    if p.is_file():
        return p.stat().st_size
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def run_demo(out_dir: str | Path, *, short: bool = False, progress: bool = True,
             console: Any = None) -> DemoResult:
    """Simulate (or reuse the cached) spiral sequence and compare the demo modes into ``out_dir``."""
    from adalio.sim import cached_sequence

    t_start = time.perf_counter()
    duration = SHORT_DURATION_S if short else FULL_DURATION_S
    columns = SHORT_COLUMNS if short else FULL_COLUMNS
    if console is not None:
        console.print(f"[bold]simulating[/] the '{DEMO_SCENE}' scene"
                      f"{' (short)' if short else ''} (cached after the first time) ...")
    sim = cached_sequence(DEMO_SCENE, seed=0, duration_s=duration, columns=columns,
                          fmt=DEMO_FORMAT)
    sim_s = time.perf_counter() - t_start
    result = compare_modes(sim.bag_path, list(DEMO_MODES), out_dir, gt=sim.gt_path,
                           config_file=sim.config_path, progress=progress, console=console)
    return DemoResult(compare=result, bag_path=Path(sim.bag_path), gt_path=Path(sim.gt_path),
                      sim_s=sim_s, total_s=time.perf_counter() - t_start,
                      cache_bytes=disk_bytes(Path(sim.gt_path).parent))
