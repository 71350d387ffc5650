"""``adalio eval``, ``adalio report``, ``adalio compare`` and ``adalio demo``."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from adalio.config import set_options
from adalio.errors import InputError
from adalio.term import console as term_console


def _parse_floats(text: str, option: str) -> tuple[float, ...]:
    """Numbers separated by commas and/or whitespace (``1,5``, ``"1 5"``, ``"1, 5"``)."""
    try:
        values = tuple(float(v) for v in re.split(r"[,\s]+", text) if v)
    except ValueError:
        raise InputError(f"{option} must be numbers separated by commas or spaces "
                         f"(got {text!r})") from None
    if not values:
        raise InputError(f"{option} is empty (e.g. {option} 1,5)")
    return values


def _f(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _pairing(n: int, n_interpolated: int | None) -> str:
    """How the table's pairs got their GT pose."""
    if n_interpolated == n:
        return "GT interpolated"
    if not n_interpolated:
        return "nearest GT pose"
    return f"GT interpolated at {n_interpolated}, nearest GT pose at {n - n_interpolated}"


def eval_command(
    est: Annotated[Path, typer.Argument(help="Estimated trajectory (TUM: t x y z qx qy qz qw).")],
    gt: Annotated[Path, typer.Argument(help="Ground truth (TUM), or HILTI control points.")],
    align: Annotated[str, typer.Option(help="se3 (Umeyama, no scale), first (first associated "
                                            "pose) or none.")] = "se3",
    json_out: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    hilti: Annotated[bool, typer.Option("--hilti", help="HILTI 2022 score against control "
                                                        "points (IMU-frame estimate).")] = False,
    max_diff: Annotated[float | None, typer.Option(
        "--max-diff", help="Max time gap (s) to associate poses [default: 0.02, --hilti: 2]")
    ] = None,
    rpe_delta: Annotated[str, typer.Option(
        "--rpe-delta", help="RPE segment lengths in metres, separated by commas or spaces.")] = "1,5",
    nearest: Annotated[bool, typer.Option(
        "--nearest", help="Pair each estimate with the nearest GT pose (evo's association) "
                          "instead of the GT interpolated at its time stamp.")] = False,
) -> None:
    """Accuracy of a trajectory: ATE and RPE (evo), or the HILTI 2022 score."""
    console = term_console()
    if hilti:
        from adalio.eval.hilti import MAX_DIFF_S, hilti_score, not_control_points_warning

        if align != "se3":
            raise InputError("--hilti always aligns with se3 (the official rule): drop --align")

        diff = max_diff if max_diff is not None else MAX_DIFF_S
        res = hilti_score(est, gt, max_diff_s=diff)
        warning = not_control_points_warning(gt, "eval", diff)
        if warning:
            term_console(stderr=True).print(warning, highlight=False, soft_wrap=True,
                                            markup=False)
        if json_out:
            print(json.dumps(res))
            return
        table = Table(title=f"HILTI 2022 score: {res['score']:.1f} / 100 "
                            f"({res['n_matched']}/{res['n_gt']} control points matched)")
        for col in ("#", "t (s)", "dt to estimate (s)", "error (cm)", "points"):
            table.add_column(col, justify="right")
        for k, (t, dt, e, p) in enumerate(zip(res["t_s"], res["dt_s"], res["errors_m"],
                                              res["points"], strict=True)):
            table.add_row(str(k), f"{t:.3f}", _f(dt, 3), _f(None if e is None else 100 * e, 2),
                          str(p))
        console.print(table)
        return
    from adalio.eval.metrics import DEFAULT_MAX_DIFF_S, ate, rpe

    diff = max_diff if max_diff is not None else DEFAULT_MAX_DIFF_S
    a = ate(est, gt, align=align, max_diff_s=diff, interpolate=not nearest)
    r = rpe(est, gt, _parse_floats(rpe_delta, "--rpe-delta"), max_diff_s=diff,
            interpolate=not nearest)
    if json_out:
        print(json.dumps({"est": str(est), "gt": str(gt), "ate": a, "rpe": r}))
        return
    pairing = _pairing(a["n"], a["n_interpolated"])
    table = Table(title=f"ATE (translation, align={align}, {a['n']} pairs within {diff} s, "
                        f"{pairing}, "
                        f"{a['duration_s']:.1f} s)")
    for col in ("RMSE (m)", "mean (m)", "median (m)", "std (m)", "max (m)"):
        table.add_column(col, justify="right")
    table.add_row(*(f"{a[k]:.4f}" for k in ("rmse_m", "mean_m", "median_m", "std_m", "max_m")))
    console.print(table)
    table = Table(title="RPE (translation per GT path segment; alignment-free)")
    for col in ("segment (m)", "pairs", "RMSE (m)", "mean (m)", "max (m)", "drift (%)",
                "rot RMSE (deg)"):
        table.add_column(col, justify="right")
    for row in r:
        table.add_row(f"{row['delta_m']:g}", str(row["n"]), _f(row["rmse_m"], 4),
                      _f(row["mean_m"], 4), _f(row["max_m"], 4), _f(row["drift_pct"], 2),
                      _f(row["rot_rmse_deg"], 2))
    console.print(table)


def report_command(
    run_dir: Annotated[Path, typer.Argument(help="Output folder of `adalio run`.")],
    gt: Annotated[Path | None, typer.Option(help="Ground-truth TUM trajectory.")] = None,
    hilti: Annotated[bool | None, typer.Option(
        "--hilti/--no-hilti", help="GT is HILTI 2022 control points [default: detect]")] = None,
) -> None:
    """Figures (trajectory, error, degeneracy timeline, map) and report.md for a run folder."""
    from adalio.eval.report import make_report

    if hilti and gt is not None:
        from adalio.eval.hilti import not_control_points_warning

        warning = not_control_points_warning(gt, "report")
        if warning:
            term_console(stderr=True).print(warning, highlight=False, soft_wrap=True,
                                            markup=False)
    path = make_report(run_dir, gt, hilti=hilti, skip_unalignable_gt=True)
    for warning in json.loads((path.parent / "metrics.json").read_text()).get("warnings", []):
        term_console(stderr=True).print(f"warning: {warning}", highlight=False, soft_wrap=True,
                                        markup=False)
    term_console().print(f"report written to [bold]{path}[/]")


def _print_table(console: Console, title: str, header, rows) -> None:
    """One table whose first column (``mode``) is text and the rest figures."""
    table = Table(title=title)
    for col in header:
        table.add_column(col, justify="left" if col == "mode" else "right")
    for cells in rows:
        table.add_row(*cells)
    console.print(table)


def _print_compare(console: Console, result) -> None:
    from rich.markup import escape

    from adalio.eval.compare import TABLE_HEADER, notes, table_rows

    _print_table(console, "adalio mode comparison", TABLE_HEADER, table_rows(result.rows))
    for row in result.rows:
        for note in notes(row):
            console.print(escape(note).replace(f"`{row.mode}`", f"[yellow]{row.mode}[/]", 1),
                          highlight=False)


def compare_command(
    bag: Annotated[Path, typer.Argument(help="ROS1 .bag file, ROS2 bag folder or .mcap file.")],
    modes: Annotated[str, typer.Option(help="Comma-separated modes to run.")
                     ] = "fixed,adaptive,adaptive+",
    gt: Annotated[Path | None, typer.Option(help="Ground-truth TUM trajectory.")] = None,
    preset: Annotated[str | None, typer.Option(help="Config preset (see `adalio config`).")
                      ] = None,
    config: Annotated[Path | None, typer.Option(help="Config YAML file.")] = None,
    set_: Annotated[list[str] | None, typer.Option("--set", help="Config override KEY=VALUE "
                                                                 "(repeatable).")] = None,
    out: Annotated[Path, typer.Option(help="Output folder (one sub-folder per mode).")
                   ] = Path("adalio_compare"),
    max_scans: Annotated[int | None, typer.Option(help="Stop each run after this many scans.")
                         ] = None,
) -> None:
    """Run several modes on the same bag and print one comparison table."""
    from adalio.eval.compare import compare_modes, parse_modes
    from adalio.io.cli import check_out_dir

    check_out_dir(out)
    console = term_console()
    result = compare_modes(bag, parse_modes(modes), out, gt=gt, preset=preset,
                           config_file=config, overrides=set_options(set_), max_scans=max_scans,
                           console=console)
    _print_compare(console, result)
    console.print(f"table and figures: [bold]{out / 'compare.md'}[/]")
    failure = result.failure()
    if failure is not None:
        raise InputError(failure)


def demo_command(
    out: Annotated[Path | None, typer.Option(
        help="Output folder [default: runs/demo]")] = None,
    short: Annotated[bool, typer.Option("--short", help="Much shorter sequence (CI).")] = False,
    seeds: Annotated[int | None, typer.Option(
        help="Sequences to compare on, seeds 0..N-1 [default: 3, or 1 with --short].")] = None,
) -> None:
    """Simulate a spiral staircase descent and compare fixed vs adaptive (no data needed)."""
    from adalio.eval.demo import DEFAULT_OUT, run_demo, summary_header, summary_rows, wins_line
    from adalio.io.cli import check_out_dir
    from adalio.sim.cache import cache_root

    out = DEFAULT_OUT if out is None else out
    check_out_dir(out)
    console = term_console()
    t0 = time.perf_counter()
    res = run_demo(out, short=short, seeds=seeds, console=console)
    for s in res.seeds:
        console.print(f"[bold]seed {s.seed}[/]")
        _print_compare(console, s.compare)
    _print_table(console, "adalio demo: SE(3) ATE over the seeds", summary_header(res),
                 summary_rows(res))
    console.print(wins_line(res))
    console.print(f"cached sequences: {res.cache_bytes / 1e6:.0f} MB in {cache_root()} "
                  "(reused next time)", highlight=False)
    for s in res.seeds:
        for row in s.compare.rows:
            if row.report:
                console.print(f"report (seed {s.seed}, {row.mode}): [bold]{row.report}[/]")
    console.print(f"where each mode switched parameters: "
                  f"{Path(out) / 'seed<k>' / '<mode>' / 'degeneracy.png'}")
    console.print(f"comparison: [bold]{Path(out) / 'demo.md'}[/]  "
                  f"(total {time.perf_counter() - t0:.0f} s)")
    failure = res.failure()
    if failure is not None:
        raise InputError(f"demo: {failure}")


def register(app: typer.Typer) -> None:
    """Add eval, report, compare and demo to the adalio CLI."""
    app.command("eval")(eval_command)
    app.command("report")(report_command)
    app.command("compare")(compare_command)
    app.command("demo")(demo_command)
