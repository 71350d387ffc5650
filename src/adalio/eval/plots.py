"""Matplotlib (Agg) figures of a run: trajectories, errors, degeneracy timeline, map top view.

Positions are metres in the GT world frame once aligned (or the estimate's world frame without
GT); times are seconds relative to the first pose / scan. Every function writes one PNG and
returns its path.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np

_DPI = 110
_GT_STYLE = {"color": "black", "lw": 1.6, "ls": "--", "label": "ground truth"}
_DEGEN_COLOR = "#f4a261"


def _save(fig: plt.Figure, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def _shade_intervals(ax: plt.Axes, t_s: np.ndarray, mask: np.ndarray, label: str | None) -> None:
    """Shade the time spans where ``mask`` is true (each sample covers up to the next one)."""
    if t_s.size == 0 or not np.any(mask):
        return
    step = float(np.median(np.diff(t_s))) if t_s.size > 1 else 0.1
    edges = np.append(t_s, t_s[-1] + step)
    m = np.concatenate([[False], mask.astype(bool), [False]])
    starts = np.nonzero(~m[:-1] & m[1:])[0]
    ends = np.nonzero(m[:-1] & ~m[1:])[0]
    for k, (a, b) in enumerate(zip(starts, ends, strict=True)):
        ax.axvspan(edges[a], edges[b], color=_DEGEN_COLOR, alpha=0.35, lw=0,
                   label=label if k == 0 else None)


def plot_trajectories(est_xyz: dict[str, np.ndarray], gt_xyz: np.ndarray | None,
                      top_path: Path, side_path: Path, title: str = "") -> tuple[Path, Path]:
    """Top (x-y) and side (x-z) views of one or more trajectories against the ground truth."""
    paths = []
    for path, (i, j), view in ((top_path, (0, 1), "top view"), (side_path, (0, 2), "side view")):
        fig, ax = plt.subplots(figsize=(6.4, 5.4))
        if gt_xyz is not None and len(gt_xyz):
            ax.plot(gt_xyz[:, i], gt_xyz[:, j], **_GT_STYLE)
        for label, xyz in est_xyz.items():
            if len(xyz):
                ax.plot(xyz[:, i], xyz[:, j], lw=1.2, label=label)
                ax.plot(xyz[0, i], xyz[0, j], "o", color="green", ms=5)
        ax.set_xlabel(f"{'xyz'[i]} [m]")
        ax.set_ylabel(f"{'xyz'[j]} [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        if ax.get_legend_handles_labels()[0]:  # nothing drawn (every compare mode aborted): no key
            ax.legend(loc="best", fontsize=8)
        ax.set_title(f"{title} {view}".strip())
        paths.append(_save(fig, path))
    return paths[0], paths[1]


def plot_error_over_time(series: dict[str, tuple[np.ndarray, np.ndarray]], path: Path,
                         degenerate: tuple[np.ndarray, np.ndarray] | None = None,
                         title: str = "position error after alignment") -> Path:
    """Position error (m) against time (s) for each labelled ``(t_s, error_m)`` series.

    ``degenerate = (t_s, mask)`` shades the scans where the degenerate parameter set was active.
    """
    fig, ax = plt.subplots(figsize=(8.0, 3.6))
    if degenerate is not None:
        _shade_intervals(ax, degenerate[0], degenerate[1], "degenerate set active")
    for label, (t_s, err_m) in series.items():
        ax.plot(t_s, err_m, lw=1.2, label=label)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [m]")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title)
    return _save(fig, path)


def plot_degeneracy(scans: dict[str, np.ndarray], path: Path, t0_s: float | None = None,
                    tau_n: float | None = None, tau_near: float | None = None) -> Path:
    """Timeline of ``scans.csv``: point counts, weakest eigenvalue(s), triggers, degenerate mode
    and (adaptive+) the scans with a direction held at the IMU prediction."""
    t = np.asarray(scans["t_s"], dtype=np.float64)
    t = t - (t0_s if t0_s is not None else (t[0] if t.size else 0.0))
    degen = np.asarray(scans.get("degenerate", np.zeros(t.size, bool)), dtype=bool)
    fig, axes = plt.subplots(3, 1, figsize=(8.0, 7.0), sharex=True,
                             gridspec_kw={"height_ratios": [3, 3, 1.3]})
    ax = axes[0]
    _shade_intervals(ax, t, degen, "degenerate set active")
    for name, style in (("n_down_general", "-"), ("n_down", ":"), ("n_near", "--")):
        if name in scans:
            counts = np.asarray(scans[name], dtype=np.float64)
            ax.plot(t, np.where(counts > 0, counts, np.nan), style, lw=1.1, label=name)
    if tau_n is not None:
        ax.axhline(tau_n, color="red", lw=0.8, label="tau_n")
    if tau_near is not None:
        ax.axhline(tau_near, color="green", lw=0.8, ls="-.", label="tau_near")
    ax.set_ylabel("points (downsampled)")
    ax.set_yscale("log")
    ax.legend(loc="upper right", fontsize=7, ncol=2)
    ax.grid(True, alpha=0.3)
    ax.set_title("degeneracy timeline")

    ax = axes[1]
    _shade_intervals(ax, t, degen, None)
    eig_cols = [f"eig{k}" for k in range(6) if f"eig{k}" in scans]
    if eig_cols:
        eig = np.column_stack([scans[c] for c in eig_cols])
        eig = np.where(eig > 0, eig, np.nan)
        for k, c in enumerate(eig_cols):
            ax.plot(t, eig[:, k], lw=1.6 if k == 0 else 0.7, alpha=1.0 if k == 0 else 0.5,
                    label="weakest (eig0)" if k == 0 else c)
        if np.any(np.isfinite(eig)):
            ax.set_yscale("log")
    ax.set_ylabel("information eigenvalues")
    ax.legend(loc="upper right", fontsize=7, ncol=3)
    ax.grid(True, alpha=0.3)

    ax = axes[2]
    triggers = np.asarray(scans.get("trigger", np.array([""] * t.size, dtype=object)), dtype=str)
    names = sorted({s for s in triggers if s and s.lower() not in ("nan", "none")})
    rows = [(name, triggers == name) for name in names]
    if "held_dirs" in scans and np.any(np.asarray(scans["held_dirs"], dtype=float) > 0):
        rows.append(("held (IMU)", np.asarray(scans["held_dirs"], dtype=float) > 0))
    names = [name for name, _ in rows]
    for row, (name, sel) in enumerate(rows):
        ax.plot(t[sel], np.full(int(sel.sum()), row), "|", ms=10, label=name)
    ax.set_yticks(range(len(names)), names if names else [])
    ax.set_ylim(-0.8, max(len(names), 1) - 0.2)
    ax.set_ylabel("trigger / held")
    ax.set_xlabel("time [s]")
    ax.grid(True, axis="x", alpha=0.3)
    return _save(fig, path)


def plot_map_top(points_world: np.ndarray, path: Path, traj_xyz: np.ndarray | None = None,
                 cell_m: float = 0.1, title: str = "map (top view)") -> Path:
    """Log point density of the map on an x-y grid, with the trajectory drawn on top."""
    fig, ax = plt.subplots(figsize=(6.8, 6.0))
    pts = np.asarray(points_world, dtype=np.float64)
    pts = pts[np.all(np.isfinite(pts), axis=1)] if pts.size else pts.reshape(0, 3)
    if len(pts):
        lo = np.percentile(pts[:, :2], 0.5, axis=0) - 1.0
        hi = np.percentile(pts[:, :2], 99.5, axis=0) + 1.0
        span = float(np.max(hi - lo))
        cell = max(cell_m, span / 800.0)
        bins = [max(int((hi[k] - lo[k]) / cell), 1) for k in range(2)]
        hist, xe, ye = np.histogram2d(pts[:, 0], pts[:, 1], bins=bins,
                                      range=[[lo[0], hi[0]], [lo[1], hi[1]]])
        img = np.log1p(hist.T)
        img = np.ma.masked_where(img == 0, img)
        ax.imshow(img, origin="lower", extent=(xe[0], xe[-1], ye[0], ye[-1]), cmap="viridis",
                  interpolation="nearest", aspect="equal")
    else:
        ax.text(0.5, 0.5, "empty map", ha="center", va="center", transform=ax.transAxes)
    if traj_xyz is not None and len(traj_xyz):
        ax.plot(traj_xyz[:, 0], traj_xyz[:, 1], color="red", lw=1.0, label="trajectory")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{title}, {len(pts)} points")
    return _save(fig, path)


def plot_error_sigma(t_s: np.ndarray, errors_m: np.ndarray, sigma_m: np.ndarray,
                     path: Path) -> Path:
    """Per-axis error (aligned on the filter's first scan, world frame) against the filter's
    ±3σ band."""
    fig, axes = plt.subplots(3, 1, figsize=(8, 6.5), sharex=True)
    for k, (ax, name) in enumerate(zip(axes, "xyz", strict=True)):
        ax.fill_between(t_s, -300 * sigma_m[:, k], 300 * sigma_m[:, k], color="tab:blue",
                        alpha=0.25, lw=0, label="±3σ (filter)")
        ax.plot(t_s, 100 * errors_m[:, k], color="tab:red", lw=1.0, label="error")
        ax.set_ylabel(f"{name} (cm)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8)
    axes[-1].set_xlabel("time (s)")
    axes[0].set_title("position error vs. the filter's 3σ "
                      "(aligned on its first scan, world frame)")
    return _save(fig, path)
