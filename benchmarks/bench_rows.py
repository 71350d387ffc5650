"""Which point-to-plane rows have a map plane that is not their point's surface?

A census of the odometry's rows against the simulator's truth, with no estimator in the loop:
the scene's sweeps are undistorted with the true poses, one every 0.1 s over a window, and each
is associated (``_Association``, the degenerate parameter set of the default config) against a
map built the odometry's way (``IVox.from_config``, the finer cell) from the earlier sweeps at
their true poses, then inserted. A row is *wrong* when its fitted plane normal is more than
``--max-angle-deg`` off the true face its point was ray-cast on. Printed per scene and seed: the
share of wrong rows, the share of the claimed height information (``n_z²`` summed over rows)
they hold, and the same split by the face the point lies on: horizontal (``|n_z| > 0.9``),
vertical (``|n_z| < 0.3``) or other. The default windows lie in each scene's narrow part.

With ``--pull`` it also prints what the rows do to the pose, still at the truth: the step one
update of the filter would take from the true pose on each sweep's rows (the filter's row
weights and robust kernel, a prior of ``NOMINAL_POSE_SIGMA``; :func:`pull`), as its mean per
sweep along the height, the yaw and the direction of travel (the true velocity's, on sweeps
moving faster than ``MOVING_M_S``), with standard errors. Rows that are right pull
nowhere on average; a systematic pull is a bias the closed loop integrates, and unlike an
odometry run it has no chaos: a rule that changes the rows (``--set``) can be compared on one
window and seed. ``--future-s`` puts the next sweeps into each sweep's map too, at their true
poses, as a smoother's map would hold them: the map then has no leading edge where the sensor
moves into new space, and the pull left is what the rows owe to anything else.

    python benchmarks/bench_rows.py --scenes hall corridor spiral stairs_garage   # README, S. 35
    python benchmarks/bench_rows.py --scenes spiral --seeds 4 --pull [--set KEY=VALUE]  # S. 40
    python benchmarks/bench_rows.py --pull --warmup-s 3 --future-s 0.5                # S. 41
    python benchmarks/bench_rows.py --pull --warmup-s 3 --lidar-rate 20 --columns 1000  # S. 58
    python benchmarks/bench_rows.py --scenes corridor --pull --warmup-s 3 --lidar-tilt-deg 60  # S. 81
"""

from __future__ import annotations

import argparse
import copy
import sys

import numpy as np
from bench_modes import parse_overrides
from scipy.spatial import cKDTree

from adalio.config import Config, load_config
from adalio.errors import InputError
from adalio.lio.ivox import IVox
from adalio.lio.odometry import _Association
from adalio.lio.state import State
from adalio.lio.voxel import voxel_downsample
from adalio.sim import SCENES
from adalio.sim.generate import START_NS, T_IMU_LIDAR_HILTI, build_trajectory, check_lidar_tilt
from adalio.sim.lidar import LIDAR_MODELS, RayCaster, SweepSimulator, lidar_model
from adalio.sim.scenes import build_scene
from adalio.sim.trajectory import HandheldMotion

WINDOWS_S = {"hall": (6.0, 12.0), "corridor": (6.0, 12.0), "spiral": (24.0, 30.0),
             "stairs_garage": (8.0, 14.0)}
"""Default census windows (seconds after the start): the corridor, the shaft, a flight."""
NOMINAL_POSE_SIGMA = (0.01, float(np.radians(0.1)))
"""(position m, rotation rad) standard deviations of the prior of :func:`pull`: a prediction as
well known as the filter's over one sweep in a well-observed place (1 cm, 0.1°)."""
MOVING_M_S = 0.2
"""A sweep counts for the along-track pull when the sensor moves faster than this (m/s)."""


def nominal_prior() -> np.ndarray:
    """(6,6) ``diag(NOMINAL_POSE_SIGMA²)`` in the error order [δp, δθ]: the prior of :func:`pull`
    and the pose covariance its robust kernel's width reads."""
    s_p, s_th = NOMINAL_POSE_SIGMA
    return np.diag([s_p**2] * 3 + [s_th**2] * 3)


def pull(H: np.ndarray, r: np.ndarray, R_world_imu: np.ndarray,
         laser_point_cov: float) -> np.ndarray:
    """The pose step, world frame ``[δp (m), δθ (rad)]``, of one update from a prior with
    covariance :func:`nominal_prior` on the rows ``H`` (m, ≥6), ``r`` (m,) evaluated there (as
    ``_Association.measure`` returns them: with the filter's row weights and, when the
    association was built with that prior, its robust kernel):
    ``δ = −(P⁻¹ + HᵀH/R)⁻¹ Hᵀ r / R``. The rotation is turned from the body frame
    (``R ⊞ δθ = R Exp(δθ)``, ``R = R_world_imu``) into the world frame."""
    H = H[:, :6]
    info = np.diag(1.0 / np.diag(nominal_prior())) + H.T @ H / laser_point_cov
    step = -np.linalg.solve(info, H.T @ r / laser_point_cov)
    return np.r_[step[:3], R_world_imu @ step[3:]]


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c = np.abs(np.sum(a * b, axis=1)) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def map_sweeps(times_s: np.ndarray, k: int, future_s: float) -> np.ndarray:
    """Indices of the sweeps in sweep ``k``'s map: every earlier one, and with ``future_s > 0``
    the later ones up to ``future_s`` after it; never sweep ``k`` itself."""
    later = np.flatnonzero((times_s > times_s[k]) & (times_s <= times_s[k] + future_s + 1e-9))
    return np.r_[np.arange(k), later].astype(np.int64)  # times_s increases: later ones are > k


def census(scene: str, seed: int, lidar: str, columns: int, t0_s: float, t1_s: float,
           max_angle_deg: float, cfg: Config | None = None, with_pull: bool = False,
           warmup_s: float = 0.0, handheld: HandheldMotion | None = None,
           future_s: float = 0.0, lidar_rate_hz: float | None = None,
           lidar_tilt_deg: float = 0.0) -> dict:
    """Rows of every sweep in [t0_s, t1_s): true face normal, fitted normal (world frame); with
    ``with_pull`` also each sweep's :func:`pull` at the true pose. The map starts with the
    sweeps of the ``warmup_s`` before ``t0_s`` (0: empty at ``t0_s``); ``handheld``: a recorded
    walk's motion instead of the synthetic one. ``future_s > 0``: each sweep's map also holds
    the sweeps of the next ``future_s`` seconds, at their true poses (:func:`map_sweeps`), as a
    smoother's would: what is left of the pull when the map has no leading edge.
    ``lidar_rate_hz``: the sweeps' rate (None: the model's 10 Hz); the pull stays per sweep.
    ``lidar_tilt_deg``: the LiDAR pitched nose down on the handle (``simulate``'s)."""
    cfg = cfg or Config()
    deg = cfg.adaptive.degenerate
    T_il = np.asarray(T_IMU_LIDAR_HILTI, dtype=np.float64)
    scn = build_scene(scene, seed)
    traj = build_trajectory(scn, T_il, seed, handheld, lidar_tilt_deg)
    model = lidar_model(lidar, columns, lidar_rate_hz)
    sim = SweepSimulator(RayCaster(scn.mesh, seed), traj, model, T_il, START_NS)
    period_s = model.period_ns * 1e-9

    def lidar_pose(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = traj.sample((np.asarray(t_ns, dtype=np.int64) - START_NS) * 1e-9)
        return s.R_world_imu @ T_il[:3, :3], s.p_world_imu_m + s.R_world_imu @ T_il[:3, 3]

    ivox = IVox.from_config(cfg.map)
    cell_m = min(cfg.map.map_leaf_m, deg.voxel_size_m)
    start_s = max(t0_s - warmup_s, 0.0)
    n_sweeps = len(np.arange(start_s, t1_s, period_s))
    times_s = np.arange(start_s, t1_s + future_s, period_s)
    sweeps: dict[int, tuple] = {}

    def sweep_at(j: int) -> tuple:
        """Sweep ``j``, undistorted at the true poses: its downsampled points at the sweep end
        (LiDAR frame) and in the world, their true face normals, the end's LiDAR pose and time."""
        if j not in sweeps:
            sw = sim.sweep(START_NS + round(times_s[j] * 1e9), np.random.default_rng([seed, j]))
            v = sw.valid & (sw.face >= 0)
            R, p = lidar_pose(sw.t_ns[v])
            world = np.einsum("nij,nj->ni", R, sw.xyz_lidar_m[v].astype(np.float64)) + p
            R_e, p_e = lidar_pose(np.array([sw.t_ns[v].max()]))
            end = (world - p_e[0]) @ R_e[0]
            down = voxel_downsample(end, deg.voxel_size_m)
            true_n = sim.caster.face_normals[sw.face[v]][cKDTree(end).query(down)[1]]
            sweeps[j] = (down, down @ R_e[0].T + p_e[0], true_n, R_e[0], p_e[0],
                         (sw.t_ns[v].max() - START_NS) * 1e-9)
        return sweeps[j]

    face_n, fit_n, pulls = [], [], []
    for k in range(n_sweeps):
        down, down_world, true_n, R_e, p_e, t_end_s = sweep_at(k)
        if k and times_s[k] >= t0_s - 1e-9:
            later = [j for j in map_sweeps(times_s, k, future_s) if j > k]
            local = ivox
            if later:  # the earlier sweeps are in ``ivox`` already
                local = copy.deepcopy(ivox)
                for j in later:
                    local.add_points(sweep_at(j)[1], cell_m)
            R_wi = R_e @ T_il[:3, :3].T
            x = State(R=R_wi, p=p_e - R_wi @ T_il[:3, 3], R_LI=T_il[:3, :3].copy(),
                      t_LI=T_il[:3, 3].copy())
            # the kernel (with the prior) scales rows and selects none: same rows either way
            assoc = _Association(down, local, cfg, deg.search_radius_m, deg.plane_margin_m,
                                 deg.voxel_size_m,
                                 prior_pose_cov=nominal_prior() if with_pull else None)
            H, r = assoc.measure(x, True)
            sel = assoc.selected
            face_n.append(true_n[sel])
            fit_n.append(assoc.normals[sel])
            if with_pull:
                step = pull(H, r, x.R, cfg.filter.laser_point_cov)
                vel = traj.sample(np.array([t_end_s])).v_world_m_s[0]
                speed = float(np.linalg.norm(vel))
                along = step[:3] @ vel / speed if speed > MOVING_M_S else np.nan
                pulls.append(np.r_[step, along])
        ivox.add_points(down_world, cell_m)
        sweeps.pop(k)
    face = np.vstack(face_n)
    fit = np.vstack(fit_n)
    wrong = _angle_deg(fit, face) > max_angle_deg
    hz = fit[:, 2] ** 2
    out = {"rows": int(wrong.size), "wrong": float(wrong.mean()),
           "wrong_height_info": float(hz[wrong].sum() / hz.sum())}
    fz = np.abs(face[:, 2])
    for name, on in (("horizontal", fz > 0.9), ("vertical", fz < 0.3),
                     ("other", (fz >= 0.3) & (fz <= 0.9))):
        out[f"{name}_rows"] = float(on.mean())
        out[f"{name}_wrong"] = float(wrong[on].mean()) if on.any() else float("nan")
        out[f"{name}_wrong_height_info"] = float(hz[on & wrong].sum() / hz.sum())
    if pulls:
        steps = np.array(pulls)
        se = steps[:, :6].std(axis=0) / np.sqrt(len(steps))
        out["pull_z_mm"], out["pull_z_se_mm"] = steps[:, 2].mean() * 1e3, se[2] * 1e3
        out["pull_yaw_mdeg"] = float(np.degrees(steps[:, 5].mean()) * 1e3)
        out["pull_yaw_se_mdeg"] = float(np.degrees(se[5]) * 1e3)
        moving = steps[np.isfinite(steps[:, 6]), 6]
        out["pull_along_mm"] = float(moving.mean() * 1e3) if moving.size else float("nan")
        out["pull_along_se_mm"] = (float(moving.std() / np.sqrt(moving.size) * 1e3)
                                   if moving.size > 1 else float("nan"))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["spiral", "stairs_garage"],
                    choices=list(SCENES))
    ap.add_argument("--seeds", type=int, default=2, help="number of seeds (0 .. N-1)")
    ap.add_argument("--lidar", default="xt32", choices=sorted(LIDAR_MODELS))
    ap.add_argument("--columns", type=int, default=512)
    ap.add_argument("--lidar-rate", type=float, default=None, metavar="HZ",
                    help="sweeps per second (default the model's 10; the pull stays per sweep)")
    ap.add_argument("--window-s", type=float, nargs=2, default=None, metavar=("T0", "T1"),
                    help="census window in seconds after the start (default: per scene)")
    ap.add_argument("--max-angle-deg", type=float, default=30.0)
    ap.add_argument("--pull", action="store_true",
                    help="also the rows' pull on the pose at the truth (height, yaw)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override, e.g. --set map.cell_point=uniform")
    ap.add_argument("--warmup-s", type=float, default=0.0,
                    help="the map starts with the sweeps of this many seconds before the window")
    ap.add_argument("--motion-from", default=None, metavar="TUM",
                    help="a recorded walk's handheld motion (as bench_modes.py)")
    ap.add_argument("--future-s", type=float, default=0.0,
                    help="each sweep's map also holds the sweeps of the next seconds, at their "
                         "true poses (a smoother's map; 0: only earlier sweeps, as the filter's)")
    ap.add_argument("--lidar-tilt-deg", type=float, default=0.0,
                    help="the LiDAR pitched this many degrees nose down on the handle "
                         "(simulate --lidar-tilt-deg; default 0: level)")
    args = ap.parse_args(argv)
    if (args.seeds < 1 or args.columns < 16 or not args.warmup_s >= 0
            or not 0 <= args.future_s < np.inf):
        raise SystemExit("error: --seeds must be >= 1, --columns >= 16, and --warmup-s and "
                         "--future-s finite and >= 0")
    cfg = load_config(overrides=parse_overrides(args.set))
    try:
        model = lidar_model(args.lidar, args.columns, args.lidar_rate)
        check_lidar_tilt(args.lidar_tilt_deg)
    except InputError as exc:
        raise SystemExit(f"error: {exc}") from None
    try:
        handheld = (None if args.motion_from is None
                    else HandheldMotion.load(args.motion_from))
    except (OSError, ValueError, InputError) as exc:
        raise SystemExit(f"error: --motion-from: {exc}") from None
    print(f"Command: `python benchmarks/bench_rows.py {' '.join(argv or sys.argv[1:])}`"
          f"  ({args.lidar} at {args.columns} columns and {model.rate_hz:g} Hz, map from true "
          f"poses"
          f"{f' (and the next {args.future_s:g} s of sweeps)' if args.future_s else ''}, "
          f"a row is wrong "
          f"beyond {args.max_angle_deg:g} deg)\n")
    pull_head = (" pull per sweep, mean (standard error): height, mm, + up | yaw, mdeg | "
                 "along the travel, mm, + ahead |" if args.pull else "")
    print("| scene | seed | window | rows | wrong | their share of the height information | "
          "horizontal faces: rows / wrong / height info | vertical faces | other faces |"
          + pull_head)
    print("|---|---|---|---|---|---|---|---|---|" + ("---|---|---|" if args.pull else ""))
    for scene in args.scenes:
        t0, t1 = args.window_s or WINDOWS_S[scene]
        for seed in range(args.seeds):
            c = census(scene, seed, args.lidar, args.columns, t0, t1, args.max_angle_deg, cfg,
                       args.pull, args.warmup_s, handheld, args.future_s, args.lidar_rate,
                       args.lidar_tilt_deg)
            cols = " | ".join(
                f"{c[f'{n}_rows'] * 100:.0f} / {c[f'{n}_wrong'] * 100:.1f} / "
                f"{c[f'{n}_wrong_height_info'] * 100:.0f} %"
                for n in ("horizontal", "vertical", "other"))
            pulls = (f" {c['pull_z_mm']:+.2f} ({c['pull_z_se_mm']:.2f}) | "
                     f"{c['pull_yaw_mdeg']:+.1f} ({c['pull_yaw_se_mdeg']:.1f}) | "
                     f"{c['pull_along_mm']:+.2f} ({c['pull_along_se_mm']:.2f}) |"
                     if args.pull else "")
            print(f"| {scene} | {seed} | {t0:g}-{t1:g} s | {c['rows']} | "
                  f"{c['wrong'] * 100:.1f} % | {c['wrong_height_info'] * 100:.0f} % | {cols} |"
                  + pulls, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
