"""Markdown report of one run directory (``adalio report RUN_DIR``, ``adalio run --gt``).

Reads what ``adalio.pipeline.run_bag`` writes (``trajectory.tum``, ``scans.csv``,
``map.ply|map.pcd``, ``config.yaml``), computes ATE / RPE against an optional ground truth
(``adalio.eval.metrics``; the estimate is SE(3)-aligned to the GT for the figures) and writes
PNG figures plus ``report.md`` and ``metrics.json`` next to them. Metres and seconds.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from adalio.errors import InputError
from adalio.eval import plots
from adalio.eval.files import read_map_points, read_scans_csv, read_trajectory
from adalio.eval.metrics import (
    DEFAULT_MAX_DIFF_S,
    DEFAULT_RPE_DELTAS_M,
    MEDIAN_ABS_Z,
    align_pair,
    associate,
    ate_from_pair,
    rpe,
    sigma_consistency,
)
from adalio.io.writers import REPORT_FILES
from adalio.lio.so3 import rotation_to_z

REPORT_NAME = REPORT_FILES[0]


def read_run_config(run_dir: Path) -> dict[str, Any]:
    path = run_dir / "config.yaml"
    if not path.is_file():
        return {}
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError:
        return {}
    return data if isinstance(data, dict) else {}


def world_up(config: dict[str, Any]) -> np.ndarray | None:
    """The world's up (unit, world frame) from a run's ``config.yaml``: against the gravity the
    filter took at initialization (``measured.gravity_world_m_s2``). The world is the IMU frame
    at init, so its z is up only for an IMU mounted z-up. None when the file does not say (a run
    older than this field, or none that initialized)."""
    measured = config.get("measured") if config else None
    g = measured.get("gravity_world_m_s2") if isinstance(measured, dict) else None
    try:
        g = np.asarray(g, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        return None
    norm = float(np.linalg.norm(g))
    return -g / norm if np.isfinite(norm) and norm > 0 else None


def figures_up(config: dict[str, Any], T_gt_est: Any = None) -> np.ndarray | None:
    """The up the figures stand on: :func:`world_up`, turned into the GT's frame by the
    alignment ``T_gt_est`` (4x4) when the figures are drawn there; None as ``world_up``."""
    up = world_up(config)
    if up is not None and T_gt_est is not None:
        up = np.asarray(T_gt_est)[:3, :3] @ up
    return up


FLIP_BELOW_Z = -np.sqrt(0.5)
"""An ``up`` whose z is below this (more than 45 deg below the horizon: a z-down IMU) is first
turned by 180 deg about x in :func:`leveling`."""


def leveling(up: np.ndarray | None) -> np.ndarray:
    """The rotation taking ``up`` to +z that the figures use (identity for None), so a top view
    looks down and a side view stands up whatever the IMU's mounting: the smallest such
    rotation, except for an ``up`` more than 45 deg below the horizon (a z-down IMU), first
    turned by 180 deg about x (``diag(1, -1, -1)``) and then by the smallest rotation. The
    smallest rotation alone is a 180 deg turn about an axis set by the sub-degree tilt of an
    ``up`` near -z, so one walk came out in headings 100 deg apart in one report's figures; this
    way the heading moves as little as ``up`` does at every axis-aligned mounting (the switch
    lies 45 deg below the horizon)."""
    if up is None:
        return np.eye(3)
    up = np.asarray(up, dtype=np.float64).reshape(3)
    flip = np.eye(3)
    if up[2] / np.linalg.norm(up) < FLIP_BELOW_Z:
        flip = np.diag([1.0, -1.0, -1.0])
    # not Rotation.align_vectors, whose one-vector result is not the smallest rotation in SciPy
    # 1.11, the lower bound (an up 3.4 deg off +z came out as a 90 deg rotation there)
    return rotation_to_z(flip @ up / np.linalg.norm(up)) @ flip


def _find_map(run_dir: Path) -> Path | None:
    for name in ("map.ply", "map.pcd"):
        if (run_dir / name).is_file():
            return run_dir / name
    return None


def scan_summary(scans: dict[str, np.ndarray]) -> dict[str, float]:
    """Scan count, share of degenerate scans (%) and median per-scan wall time (ms)."""
    n = len(scans["t_s"])
    degen = np.asarray(scans.get("degenerate", np.zeros(n, bool)), dtype=bool)
    wall = np.asarray(scans.get("wall_ms", np.full(n, np.nan)), dtype=np.float64)
    return {
        "n_scans": n,
        "degenerate_pct": float(100.0 * degen.mean()) if n else 0.0,
        "ms_per_scan_median": float(np.nanmedian(wall)) if n and np.any(np.isfinite(wall))
        else float("nan"),
    }


def full_aligned_xyz(est_path: Path, T_gt_est: np.ndarray) -> np.ndarray:
    """All estimated positions mapped into the GT frame by the alignment transform."""
    traj = read_trajectory(est_path, "estimate")
    xyz = np.asarray(traj.positions_xyz, dtype=np.float64)
    return xyz @ T_gt_est[:3, :3].T + T_gt_est[:3, 3]


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def make_report(run_dir: str | Path, gt: str | Path | None = None, *,
                hilti: bool | None = None,
                max_diff_s: float = DEFAULT_MAX_DIFF_S,
                rpe_deltas_m: tuple[float, ...] = DEFAULT_RPE_DELTAS_M,
                skip_unalignable_gt: bool = False) -> Path:
    """Write figures, ``metrics.json`` and ``report.md`` into ``run_dir``; return the report path.

    ``skip_unalignable_gt``: a ground truth that pairs with the run but cannot be SE(3)-aligned
    to it (fewer than 3 pairs, or a stretch at rest: a GT of the still start only) gives the
    report without its ground-truth sections, the reason in ``metrics.json``'s ``warnings``,
    instead of an InputError. A GT with no pose near the run's is an InputError either way.

    ``hilti=True`` treats ``gt`` as HILTI 2022 control points and adds the HILTI score
    (:func:`adalio.eval.hilti.hilti_score`) instead of the dense ATE/RPE; ``None`` decides from
    the file (identity quaternions, >= 1 s between poses: control points).
    """
    run_dir = Path(run_dir)
    if run_dir.is_file():
        raise InputError(f"run directory {run_dir} is a file: give the --out folder of a run")
    if not run_dir.is_dir():
        raise InputError(f"run directory {run_dir} does not exist: give the --out of a run")
    est_path = run_dir / "trajectory.tum"
    if not est_path.is_file():
        raise InputError(f"{run_dir} has no trajectory.tum: is it the output folder of a run?")
    est = read_trajectory(est_path, "estimate")
    est_xyz = np.asarray(est.positions_xyz, dtype=np.float64)
    t0 = float(est.timestamps[0])
    config = read_run_config(run_dir)
    mode = str(config.get("adaptive", {}).get("mode", "?")) if config else "?"
    scans_path = run_dir / "scans.csv"
    scans = read_scans_csv(scans_path) if scans_path.is_file() else None
    if scans is not None and len(scans["t_s"]):
        t0 = min(t0, float(scans["t_s"][0]))
    metrics: dict[str, Any] = {"run_dir": str(run_dir), "mode": mode,
                               "n_poses": int(est.num_poses)}
    figures: list[tuple[str, Path]] = []
    warnings: list[str] = []
    metrics["warnings"] = warnings
    gt_xyz = None
    aligned_xyz = est_xyz
    pair = None
    if gt is not None:
        gt_traj = read_trajectory(gt, "ground-truth")
        gt_t = np.asarray(gt_traj.timestamps, dtype=np.float64)
        in_span = (gt_t >= est.timestamps[0] - 1.0) & (gt_t <= est.timestamps[-1] + 1.0)
        gt_xyz = np.asarray(gt_traj.positions_xyz, dtype=np.float64)[in_span]
        if hilti is None:
            from adalio.eval.hilti import looks_like_control_points

            hilti = looks_like_control_points(gt_traj)
        if hilti:
            from adalio.eval.hilti import hilti_score

            metrics["hilti"] = hilti_score(est_path, gt)
            aligned_xyz = full_aligned_xyz(est_path, np.asarray(metrics["hilti"]["T_gt_est"]))
        else:
            try:
                pair = align_pair(est_path, gt, "se3", max_diff_s)
            except InputError as exc:
                if not skip_unalignable_gt:
                    raise
                associate(est_path, gt, max_diff_s)  # no pair at all: an error still
                metrics["gt_not_used"] = str(exc)
                warnings.append(f"--gt {gt} is not used: {exc}; the report has no "
                                "ground-truth sections")
                gt_xyz = None
            else:
                metrics["ate_se3"] = ate_from_pair(pair, max_diff_s)
                pair_first = align_pair(est_path, gt, "first", max_diff_s)
                metrics["ate_first"] = ate_from_pair(pair_first, max_diff_s)
                metrics["rpe"] = rpe(est_path, gt, rpe_deltas_m, max_diff_s)
                aligned_xyz = full_aligned_xyz(est_path, pair.T_gt_est)
    up_world = world_up(config)
    T_gt_est = pair.T_gt_est if pair is not None else metrics.get("hilti", {}).get("T_gt_est")
    up = figures_up(config, T_gt_est)
    R_fig = leveling(up)
    metrics["figures_up"] = None if up is None else up.tolist()
    aligned_xyz = aligned_xyz @ R_fig.T
    if gt_xyz is not None:
        gt_xyz = gt_xyz @ R_fig.T
    label = f"adalio ({mode})"
    top, side = plots.plot_trajectories({label: aligned_xyz}, gt_xyz,
                                        run_dir / "trajectory_top.png",
                                        run_dir / "trajectory_side.png",
                                        title="trajectory" + (" (SE(3)-aligned)"
                                                              if T_gt_est is not None else ""))
    figures += [("Trajectory, top view", top), ("Trajectory, side view", side)]
    degen_series = None
    if scans is not None:
        degen_series = (np.asarray(scans["t_s"]) - t0,
                        np.asarray(scans.get("degenerate", np.zeros(len(scans["t_s"]), bool))))
        metrics["scans"] = scan_summary(scans)
    if pair is not None:
        figures.append(("Position error over time", plots.plot_error_over_time(
            {f"{label}, SE(3)-aligned": (pair.t_s - t0, pair.errors_m),
             f"{label}, first-pose-aligned": (pair_first.t_s - t0, pair_first.errors_m)},
            run_dir / "error.png", degenerate=degen_series)))
    cons = None
    if pair is not None and scans is not None:
        with contextlib.suppress(InputError):  # no (finite) sigma columns: an older scans.csv
            cons = sigma_consistency(est_path, gt, scans, max_diff_s)
    if cons is not None:
        metrics["sigma"] = {"within_3sigma_xyz": cons.within_3sigma.tolist(),
                            "mean_nees": cons.mean_nees, "n": len(cons.t_s),
                            "anchor_t_s": cons.anchor_t_s - t0,
                            "first_scan_t_s": cons.first_scan_t_s - t0,
                            "anchor_is_first_scan": cons.anchor_is_first_scan,
                            "anchor_sigma_max_m": float(np.nanmax(cons.anchor_sigma_m))
                            if np.any(np.isfinite(cons.anchor_sigma_m)) else None,
                            "median_abs_z_xyz": cons.median_abs_z.tolist(),
                            "increment_correlation_xyz": [
                                float(v) if np.isfinite(v) else None
                                for v in cons.increment_correlation]}
        at = metrics["sigma"]["anchor_sigma_max_m"]
        along = np.nanmax(np.asarray(cons.sigma_world_m, dtype=np.float64), axis=1)
        if not cons.anchor_is_first_scan and (
                at is None or not np.any(np.isfinite(along)) or
                at > ANCHOR_SIGMA_SHARE * float(np.nanmedian(along))):
            warnings.append(sigma_anchor_warning(metrics["sigma"]))
        figures.append(("Position error against the filter's ±3σ", plots.plot_error_sigma(
            cons.t_s - t0, cons.errors_world_m, cons.sigma_world_m, run_dir / "error_sigma.png")))
    if scans is not None:
        adaptive = config.get("adaptive", {}) if config else {}
        figures.append(("Degeneracy timeline", plots.plot_degeneracy(
            scans, run_dir / "degeneracy.png", t0_s=t0, tau_n=adaptive.get("tau_n"),
            tau_near=adaptive.get("tau_near"))))
    map_path = _find_map(run_dir)
    if map_path is not None:
        pts = read_map_points(map_path)
        metrics["map_points"] = len(pts)
        R_map = leveling(up_world)
        figures.append(("Map, top view", plots.plot_map_top(pts @ R_map.T,
                                                             run_dir / "map_top.png",
                                                             traj_xyz=est_xyz @ R_map.T)))
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    report = run_dir / REPORT_NAME
    report.write_text(_markdown(metrics, figures, gt))
    written = {Path(path).name for _, path in figures}
    for name in REPORT_FILES:  # an earlier report's figures that this one does not make
        if name.endswith(".png") and name not in written and (run_dir / name).is_file():
            (run_dir / name).unlink()
    return report


ANCHOR_SIGMA_SHARE = 0.25
"""A GT that starts after the filter's first scan is warned about when the sigma at the scan it
is aligned on exceeds this share of the run's median sigma (below it, the figures barely move:
a GT one scan late)."""


def sigma_anchor_warning(sigma: dict[str, Any]) -> str:
    """Why the uncertainty figures of a GT that starts after the filter's first scan flatter
    the sigmas (``sigma``: ``metrics.json``'s ``sigma``)."""
    at = sigma.get("anchor_sigma_max_m")
    told = "" if at is None else f" (σ up to {100 * at:.1f} cm there)"
    return (f"the ground truth starts after the filter's first scan ({sigma['first_scan_t_s']:.2f}"
            f" s), so the uncertainty check aligns it on the scan at {sigma['anchor_t_s']:.2f} s"
            f"{told}: errors measured from there are small against σ measured from the first "
            "scan, and the within-3σ share, NEES and median |error| / σ come out optimistic")


def _markdown(metrics: dict[str, Any], figures: list[tuple[str, Path]],
              gt: str | Path | None) -> str:
    lines = [f"# adalio run report: `{Path(metrics['run_dir']).name}`", "",
             f"- mode: `{metrics['mode']}`", f"- poses: {metrics['n_poses']}"]
    if "scans" in metrics:
        s = metrics["scans"]
        lines += [(f"- scans: {s['n_scans']}, degenerate set active on "
                  f"{s['degenerate_pct']:.1f} %"), (f"- median wall time per scan: "
                  f"{_fmt(s['ms_per_scan_median'], 1)} ms")]
    if "map_points" in metrics:
        lines.append(f"- map points: {metrics['map_points']}")
    lines.append(f"- ground truth: `{gt}`" if gt is not None else "- ground truth: none")
    if "gt_not_used" in metrics:
        lines.append(f"- **not used**: {metrics['gt_not_used']}")
    lines.append("")
    if "ate_se3" in metrics:
        lines += ["## Absolute trajectory error (translation, m)", "",
                  "| alignment | RMSE | mean | median | max | pairs |",
                  "|---|---|---|---|---|---|"]
        for key in ("ate_se3", "ate_first"):
            a = metrics[key]
            lines.append(f"| {a['align']} | {_fmt(a['rmse_m'], 4)} | {_fmt(a['mean_m'], 4)} | "
                         f"{_fmt(a['median_m'], 4)} | {_fmt(a['max_m'], 4)} | {a['n']} |")
        lines += ["", "## Relative pose error", "",
                  ("| segment (m) | RMSE (m) | mean (m) | max (m) | drift (%) | rot RMSE (deg) "
                  "| pairs |"), "|---|---|---|---|---|---|---|"]
        for r in metrics["rpe"]:
            lines.append(f"| {r['delta_m']:g} | {_fmt(r['rmse_m'], 4)} | {_fmt(r['mean_m'], 4)} | "
                         f"{_fmt(r['max_m'], 4)} | {_fmt(r['drift_pct'], 2)} | "
                         f"{_fmt(r['rot_rmse_deg'], 2)} | {r['n']} |")
        lines.append("")
    if "sigma" in metrics:
        c = metrics["sigma"]
        w = c["within_3sigma_xyz"]
        if c.get("anchor_is_first_scan", True):
            where = "the filter's first scan"
            if c.get("anchor_t_s") is not None:
                where += f", at {c['anchor_t_s']:.2f} s"
        else:
            where = (f"the scan at {c['anchor_t_s']:.2f} s, the first the ground truth covers; "
                     f"not the filter's first scan at {c['first_scan_t_s']:.2f} s")
        lines += ["## Uncertainty (scans.csv sigma columns against the ground truth)", ""]
        if not c.get("anchor_is_first_scan", True):
            lines += [f"**Warning:** {sigma_anchor_warning(c)}", ""]
        lines += [(f"Scans whose error (aligned on {where}) lies within 3σ: "
                   f"x {100 * w[0]:.1f} %, y {100 * w[1]:.1f} %, z {100 * w[2]:.1f} % "
                   f"(99.7 % if the σ were honest and Gaussian); "
                   f"mean NEES {c['mean_nees']:.1f} (3 if consistent), {c['n']} scans."), ""]
        mz = c.get("median_abs_z_xyz")
        if mz:
            lines += [(f"Median |error| / σ: x {mz[0]:.2f}, y {mz[1]:.2f}, z {mz[2]:.2f} "
                       f"({MEDIAN_ABS_Z:.2f} if honest; far below it: σ much larger than the "
                       "error, which the two figures above do not show)."), ""]
        r = c.get("increment_correlation_xyz") or []
        if any(v is not None for v in r):
            cells = ", ".join(f"{a} {'n/a' if v is None else f'{v:+.2f}'}"
                              for a, v in zip("xyz", r, strict=False))
            lines += [(f"Correlation of consecutive 1 s increments of that error: {cells} (near"
                       " +1: the error drifts one way, as with a biased map; near 0: a random"
                       " walk; below 0: it swings back)."), ""]
    if "hilti" in metrics:
        h = metrics["hilti"]
        lines += ["## HILTI 2022 score", "",
                  (f"**{h['score']:.1f} / 100** ({h['n_matched']} of {h['n_gt']} control points "
                  "matched)"), "", "| # | t (s) | error (cm) | points |", "|---|---|---|---|"]
        for k, (t, e, p) in enumerate(zip(h["t_s"], h["errors_m"], h["points"], strict=True)):
            lines.append(f"| {k} | {t:.2f} | {_fmt(None if e is None else 100 * e, 1)} | {p} |")
        lines.append("")
    lines += ["## Figures", ""]
    for caption, path in figures:
        lines += [f"### {caption}", "", f"![{caption}]({Path(path).name})", ""]
    return "\n".join(lines)
