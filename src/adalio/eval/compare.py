"""Run several adaptive modes on the same bag and compare them (``adalio compare``).

Each mode runs through ``adalio.pipeline.run_bag`` into ``OUT/<mode>/`` with the same config
except ``adaptive.mode``. With a ground truth, every run is scored (ATE after SE(3) alignment,
max error) and gets its own report; a mode *diverged* if its max error exceeds
``DIVERGED_MAX_ERROR_M`` or its run aborted. A run that completed but could not be scored
against the GT (no stamp within reach: another recording's GT) is an *evaluation failure*,
neither diverged nor aborted. The overlaid trajectories are drawn in the GT frame.
Writes ``compare.json``, ``compare.md`` and ``compare_top.png`` / ``compare_side.png`` (and
``compare_error.png`` with GT) into ``OUT``. Metres, seconds, milliseconds.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from adalio.config import MODES, load_config
from adalio.errors import AdalioError, BagError, ConfigError, InputError
from adalio.eval import plots
from adalio.eval.files import read_trajectory
from adalio.eval.metrics import DEFAULT_MAX_DIFF_S, align_pair, ate_from_pair
from adalio.eval.report import (
    figures_up,
    full_aligned_xyz,
    leveling,
    make_report,
    read_run_config,
)

DIVERGED_MAX_ERROR_M = 1.0
"""A run whose aligned position error exceeds this anywhere counts as diverged (metres)."""


@dataclass
class ModeResult:
    """One row of the comparison table."""

    mode: str
    out_dir: str
    n_scans: int = 0
    degenerate_pct: float = float("nan")
    ms_per_scan: float = float("nan")
    wall_s: float = float("nan")
    ate_rmse_m: float | None = None
    max_error_m: float | None = None
    diverged: bool = False
    aborted: str | None = None
    """Why the run stopped early (exception text, 'interrupted', 'no poses'), else None."""
    eval_failed: str | None = None
    """Why its trajectory could not be scored against the ground truth, else None."""
    report: str | None = None


@dataclass
class CompareResult:
    rows: list[ModeResult]
    out_dir: Path
    figures: list[Path] = field(default_factory=list)
    gt: str | None = None
    earlier: list[str] = field(default_factory=list)
    """Mode folders in ``out_dir`` of modes not compared now (an earlier comparison's), kept."""

    def failure(self) -> str | None:
        """One line saying why the comparison has no result, or None: no mode gave a usable
        trajectory (with a GT: none could be aligned to it). Diverged modes, and some modes
        aborted, are a result of a comparison; no usable mode at all is a failure of the input
        (a run that produces no pose, a GT of another recording)."""
        if any(r.report is not None for r in self.rows):
            return None
        first = next((r for r in self.rows if r.aborted or r.eval_failed), None)
        reason = "" if first is None else f" ({first.mode}: {first.aborted or first.eval_failed})"
        where = f"the tables and trajectories written so far are in {self.out_dir}"
        if self.gt is not None and any(r.n_scans > 0 for r in self.rows):
            return (f"--gt {self.gt}: no mode's trajectory could be aligned with this ground "
                    f"truth{reason}; {where}")
        return f"no mode produced a usable trajectory{reason}; {where}"


def mode_dir_name(mode: str) -> str:
    return mode.replace("+", "_plus")


def earlier_mode_dirs(out_dir: Path, modes: list[str]) -> list[str]:
    """Names of ``out_dir``'s sub-folders named after a mode not in ``modes``."""
    return [mode_dir_name(m) for m in MODES
            if m not in modes and (out_dir / mode_dir_name(m)).is_dir()]


def parse_modes(text: str) -> list[str]:
    """``"fixed,adaptive"`` -> ``["fixed", "adaptive"]``, validated against config.MODES."""
    modes = [m.strip() for m in text.split(",") if m.strip()]
    if not modes:
        raise ConfigError(f"--modes is empty: give a comma-separated list of {', '.join(MODES)}")
    for m in modes:
        if m not in MODES:
            raise ConfigError(f"--modes: unknown mode {m!r}; valid: {', '.join(MODES)}")
    if len(set(modes)) != len(modes):
        raise ConfigError(f"--modes lists a mode twice ({text!r})")
    return modes


def compare_modes(bag_path: str | Path, modes: list[str], out_dir: str | Path, *,
                  gt: str | Path | None = None, preset: str | None = None,
                  config_file: str | Path | None = None,
                  overrides: dict[str, Any] | None = None, max_scans: int | None = None,
                  progress: bool = True, max_diff_s: float = DEFAULT_MAX_DIFF_S,
                  console: Any = None) -> CompareResult:
    """Run ``modes`` on ``bag_path`` and collect the comparison (see module docstring)."""
    from adalio.io.cli import compile_notice
    from adalio.pipeline import run_bag

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if gt is not None:
        read_trajectory(gt, "ground-truth")
    rows: list[ModeResult] = []
    aligned: dict[str, np.ndarray] = {}
    errors: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    t0 = None
    up = None  # the figures' up: the modes share the initialization, so the first one's
    for mode in modes:
        cfg = load_config(preset=preset, config_file=config_file,
                          overrides={**(overrides or {}), "adaptive.mode": mode})
        run_dir = out_dir / mode_dir_name(mode)
        row = ModeResult(mode=mode, out_dir=str(run_dir))
        if console is not None:
            console.print(f"[bold]running mode {mode}[/] -> {run_dir}")
        try:
            res = run_bag(bag_path, cfg, run_dir, progress=progress, max_scans=max_scans,
                          on_compile=None if console is None else lambda: compile_notice(console))
        except (BagError, ConfigError):
            raise
        except (AdalioError, FloatingPointError, np.linalg.LinAlgError, ValueError) as exc:
            row.aborted = f"{type(exc).__name__}: {exc}".splitlines()[0]
            row.diverged = True
            rows.append(row)
            continue
        row.n_scans = int(res.n_scans)
        row.degenerate_pct = 100.0 * res.n_degenerate / res.n_scans if res.n_scans else 0.0
        row.ms_per_scan = float(res.ms_per_scan_median)
        row.wall_s = float(res.wall_s)
        if res.interrupted:
            row.aborted = "interrupted"
        traj_path = Path(res.trajectory_path)
        try:
            est = read_trajectory(traj_path, "estimate")
        except InputError as exc:
            row.aborted = row.aborted or f"no usable trajectory ({exc})"
            row.diverged = True
            rows.append(row)
            continue
        if t0 is None:
            t0 = float(est.timestamps[0])
        if gt is not None:
            try:
                pair = align_pair(traj_path, gt, "se3", max_diff_s)
            except InputError as exc:
                row.eval_failed = str(exc)
            else:
                stats = ate_from_pair(pair, max_diff_s)
                row.ate_rmse_m = stats["rmse_m"]
                row.max_error_m = stats["max_m"]
                aligned[mode] = full_aligned_xyz(traj_path, pair.T_gt_est)
                errors[mode] = (pair.t_s, pair.errors_m)
                if up is None:
                    up = figures_up(read_run_config(run_dir), pair.T_gt_est)
                row.report = str(make_report(run_dir, gt, max_diff_s=max_diff_s))
        else:
            aligned[mode] = np.asarray(est.positions_xyz, dtype=np.float64)
            row.report = str(make_report(run_dir))
            if up is None:
                up = figures_up(read_run_config(run_dir))
        row.diverged = bool(row.aborted is not None or (
            row.max_error_m is not None and row.max_error_m > DIVERGED_MAX_ERROR_M))
        rows.append(row)
        if res.interrupted:
            break
    result = CompareResult(rows=rows, out_dir=out_dir, gt=None if gt is None else str(gt),
                           earlier=earlier_mode_dirs(out_dir, modes))
    if console is not None and result.earlier:
        console.print(f"note: {', '.join(result.earlier)} in {out_dir} "
                      f"{'is' if len(result.earlier) == 1 else 'are'} from an earlier comparison "
                      "(not run now, not in this table; left as they are)", highlight=False,
                      soft_wrap=True, markup=False)
    gt_xyz = None
    if gt is not None:
        gt_xyz = np.asarray(read_trajectory(gt, "ground-truth").positions_xyz, dtype=np.float64)
    R_fig = leveling(up)
    aligned = {m: xyz @ R_fig.T for m, xyz in aligned.items()}
    if gt_xyz is not None:
        gt_xyz = gt_xyz @ R_fig.T
    result.figures += list(plots.plot_trajectories(
        aligned, gt_xyz, out_dir / "compare_top.png", out_dir / "compare_side.png",
        title="modes" + (" (SE(3)-aligned)" if gt is not None else "")))
    if errors:
        t_ref = min(float(v[0][0]) for v in errors.values())
        result.figures.append(plots.plot_error_over_time(
            {m: (t - t_ref, e) for m, (t, e) in errors.items()}, out_dir / "compare_error.png",
            title="position error after SE(3) alignment"))
    (out_dir / "compare.json").write_text(json.dumps(
        {"bag": str(bag_path), "gt": None if gt is None else str(gt),
         "figures_up": None if up is None else up.tolist(), "rows": [_json_row(r) for r in rows]}, indent=2))
    (out_dir / "compare.md").write_text(_markdown(result, gt))
    return result


def _json_row(row: ModeResult) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in asdict(row).items()}


def _f(value: float | None, digits: int = 3) -> str:
    if value is None or not math.isfinite(value):
        return "-"
    return f"{value:.{digits}f}"


TABLE_HEADER = ("mode", "ATE rmse (m)", "max err (m)", "diverged", "degenerate (%)",
                "ms/scan", "scans")


def _diverged_cell(row: ModeResult) -> str:
    if row.aborted:
        return "yes (aborted)"
    if row.eval_failed:
        return "- (evaluation failed)"
    return "yes" if row.diverged else "no"


def table_rows(rows: list[ModeResult]) -> list[tuple[str, ...]]:
    """The comparison table as strings, columns as in ``TABLE_HEADER``."""
    return [(r.mode, _f(r.ate_rmse_m, 4), _f(r.max_error_m, 4), _diverged_cell(r),
             _f(r.degenerate_pct, 1), _f(r.ms_per_scan, 1), str(r.n_scans)) for r in rows]


def notes(row: ModeResult) -> list[str]:
    """What the table's diverged column abbreviates for one mode, one line each."""
    out = [f"`{row.mode}` aborted: {row.aborted}"] if row.aborted else []
    if row.eval_failed:
        out.append(f"`{row.mode}` evaluation against the ground truth failed (the run "
                   f"{'stopped early' if row.aborted else 'completed'}): {row.eval_failed}")
    return out


def _markdown(result: CompareResult, gt: str | Path | None) -> str:
    lines = ["# adalio mode comparison", "", f"- ground truth: `{gt}`" if gt else
             "- ground truth: none (no accuracy columns)", "",
             "| " + " | ".join(TABLE_HEADER) + " |", "|" + "---|" * len(TABLE_HEADER)]
    lines += ["| " + " | ".join(cells) + " |" for cells in table_rows(result.rows)]
    for r in result.rows:
        lines += [f"\n- {note}" for note in notes(r)]
    if result.earlier:
        lines.append(f"\n- folders from an earlier comparison, not run now: "
                     f"{', '.join(f'`{d}`' for d in result.earlier)}")
    lines += ["", "## Figures", ""]
    lines += [f"![{p.stem}]({p.name})\n" for p in result.figures]
    lines += ["## Per-mode reports", ""]
    for r in result.rows:
        if r.report:
            rel = Path(r.report).resolve().relative_to(result.out_dir.resolve())
            lines.append(f"- `{r.mode}`: [{rel}]({rel})")
    return "\n".join(lines) + "\n"
