"""Cold start and peak memory of adalio (issue #15 item 3).

Cold start: ``adalio run`` on a short simulated bag (hall, 8 s, PandarXT-32 at 512 columns, mcap)
in a subprocess whose numba cache (``NUMBA_CACHE_DIR``) is an empty folder, as after a fresh
install, then the same command again with that cache filled. The cold run is made twice, each
with its own empty cache: as a user gets it (the update's kernels compile meanwhile in a helper
process, ``adalio.lio.warmup``) and with that helper switched off (``ADALIO_PARALLEL_COMPILE=0``),
alternating ``--repeat`` times. Prints the wall times, the compilation a fresh install pays once
(cold minus warm) and the import time of the CLI.

Peak memory: a long walk simulated on the fly and fed straight to the estimator (no bag is
written): ``--minutes`` of laps around the hall (its pillars, beams and walls; no clutter, so the
closed loop stays clear), ray-cast sweep by sweep, with the IMU of the whole walk synthesized up
front. Everything ``adalio run`` does per scan after decoding runs: ``Odometry``, the trajectory
and ``scans.csv`` writers, and at the end the map export. Prints the resident set size (RSS) every
``--report-min`` minutes, the peak RSS of the process (``getrusage``), the RSS before the first
scan (simulator, scene and IMU stream: not adalio's), the map size and the ATE against the walk's
ground truth.

    python benchmarks/bench_resources.py --minutes 30 --columns 512
    python benchmarks/bench_resources.py --skip-long            # cold start only (3 min)
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

IMU_RATE_HZ = 400.0


def rss_mb() -> float:
    """Current resident set size of this process (MB), from /proc (Linux)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def adalio_cmd() -> list[str]:
    exe = Path(sys.executable).with_name("adalio")
    return [str(exe)] if exe.exists() else [shutil.which("adalio") or "adalio"]


def cold_start(columns: int, repeat: int = 1) -> None:
    from adalio.sim import cached_sequence

    sim = cached_sequence("hall", seed=0, duration_s=8.0, lidar="xt32", fmt="mcap",
                          columns=columns)
    runs = [("cold, helper process", "1"), ("cold, no helper", "0")] * repeat + [("warm", "1")]
    with tempfile.TemporaryDirectory(prefix="adalio-cold-") as tmp:
        rows: dict[str, list[float]] = {}
        for i, (label, helper) in enumerate(runs):
            cache = Path(tmp) / ("numba-warm" if label == "warm" else f"numba-{i}")
            if label == "warm":  # the cache the first cold run filled
                shutil.copytree(Path(tmp) / "numba-0", cache)
            env = {**os.environ, "NUMBA_CACHE_DIR": str(cache),
                   "ADALIO_PARALLEL_COMPILE": helper}
            out = Path(tmp) / f"out-{i}"
            cmd = adalio_cmd() + ["run", str(sim.bag_path), "--config", str(sim.config_path),
                                  "--out", str(out), "--no-progress"]
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, check=False, env=env, capture_output=True, text=True)
            wall = time.perf_counter() - t0
            if proc.returncode != 0:
                print(proc.stdout[-2000:], proc.stderr[-2000:], sep="\n")
                raise SystemExit(f"adalio run failed ({label}), exit {proc.returncode}")
            rows.setdefault(label, []).append(wall)
        t0 = time.perf_counter()
        subprocess.run(adalio_cmd() + ["--help"], env=env, capture_output=True, check=True)
        help_s = time.perf_counter() - t0
    warm = rows["warm"][0]
    print(f"cold start: adalio run, hall 8 s ({columns} columns, 80 scans)")
    for label, walls in rows.items():
        paid = "" if label == "warm" else \
            f"  (compilation paid once: {' / '.join(f'{w - warm:.1f}' for w in walls)} s)"
        print(f"  {label:<22} {' / '.join(f'{w:5.1f}' for w in walls)} s{paid}")
    print(f"  adalio --help          {help_s:5.1f} s")


def lap_scene(seed: int):
    """The hall without clutter, and a closed rectangular lap inside its walls."""
    from adalio.sim.scenes import RIG_HEIGHT_M, build_scene

    scene = build_scene("hall", seed, n_clutter=0)
    lo, hi = scene.waypoints_m[:, :2].min(axis=0), scene.waypoints_m[:, :2].max(axis=0)
    lap = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    return scene, np.column_stack([lap, np.full(4, RIG_HEIGHT_M)])


def long_walk(minutes: float, columns: int, seed: int, report_min: float) -> None:
    from adalio.config import load_config
    from adalio.eval.metrics import ate
    from adalio.io.writers import ScansCsvWriter, TumWriter, write_map
    from adalio.lio import Odometry
    from adalio.lio.voxel import voxel_downsample
    from adalio.sim import cached_sequence
    from adalio.sim.generate import START_NS, T_IMU_LIDAR_HILTI, mesh_distance_m
    from adalio.sim.imu import ImuNoise, synthesize_imu
    from adalio.sim.lidar import Occluder, RayCaster, SweepSimulator, lidar_model
    from adalio.sim.trajectory import Trajectory

    t_build = time.perf_counter()
    scene, lap = lap_scene(seed)
    T_il = np.asarray(T_IMU_LIDAR_HILTI)
    one = Trajectory(np.vstack([lap, lap[:1]]), np.full(5, 1.25), T_il[:3, :3].T, seed=seed)
    n_laps = int(np.ceil(minutes * 60.0 / max(one.duration_s - 4.0, 1.0)))
    while True:  # a lap inside a long walk is quicker than alone (no start and stop)
        waypoints = np.vstack([lap] * n_laps + [lap[:1]])
        traj = Trajectory(waypoints, np.full(len(waypoints), 1.25), T_il[:3, :3].T, seed=seed)
        if traj.duration_s >= minutes * 60.0:
            break
        n_laps += max(1, n_laps // 20)
    dur_s = minutes * 60.0
    model = lidar_model("xt32", columns)
    caster = RayCaster(scene.mesh, seed)
    clearance = float(mesh_distance_m(caster, traj.sample(np.arange(0.0, dur_s, 0.5))
                                      .p_world_imu_m).min())
    t0 = START_NS
    dt_ns = round(1e9 / IMU_RATE_HZ)
    t_imu = t0 + np.arange(round(dur_s * 1e9) // dt_ns + 1, dtype=np.int64) * dt_ns
    imu = synthesize_imu(traj, t_imu, t0, np.random.default_rng([seed, 200]), ImuNoise(),
                         1.0, IMU_RATE_HZ)
    sim = SweepSimulator(caster, traj, model, T_il, t0, Occluder())
    # the simulator's own config for this LiDAR and mounting (the one next to any of its bags)
    cfg = load_config(config_file=cached_sequence("hall", seed=seed, duration_s=8.0, lidar="xt32",
                                                  fmt="mcap", columns=columns).config_path)
    with tempfile.TemporaryDirectory(prefix="adalio-long-") as tmp:
        odom = Odometry(cfg)
        tum = TumWriter(Path(tmp) / "trajectory.tum")
        csvw = ScansCsvWriter(Path(tmp) / "scans.csv")
        n_scans = int(round(dur_s * 1e9) // model.period_ns)
        print(f"long walk: {n_laps} laps of {one.route_length_m:.0f} m in the hall, "
              f"{dur_s / 60:.1f} min, {n_scans} sweeps of {columns} columns, min clearance "
              f"{clearance:.2f} m (set-up {time.perf_counter() - t_build:.0f} s)")
        base = rss_mb()
        print(f"RSS before the first scan (simulator, scene, IMU stream): {base:.0f} MB")
        print(f"{'minute':>6} {'RSS MB':>7} {'map points':>10} {'median ms/scan':>14}")
        i_imu, ms, est_t = 0, [], []
        next_report = report_min
        t_run = time.perf_counter()
        for k in range(n_scans):
            stamp = t0 + k * model.period_ns
            j = int(np.searchsorted(t_imu, stamp + model.period_ns, side="right"))
            if j > i_imu:
                odom.add_imu(t_imu[i_imu:j], imu.gyro_rad_s[i_imu:j], imu.accel_m_s2[i_imu:j])
                i_imu = j
            sw = sim.sweep(stamp, np.random.default_rng([seed, 100, k]))
            pts = sw.xyz_lidar_m[sw.valid].astype(np.float64)
            t_pts = sw.t_ns[sw.valid]
            c0 = time.perf_counter()
            est = odom.add_scan(pts, t_pts)
            ms.append((time.perf_counter() - c0) * 1e3)
            if est is not None:
                tum.write(est.t_ns, est.T_world_imu)
                est.stats.t_ns = int(est.t_ns)
                csvw.write(est.stats)
                est_t.append(int(est.t_ns))
            minute = (stamp - t0) * 1e-9 / 60.0
            if minute >= next_report or k == n_scans - 1:
                recent = ms[-int(report_min * 600):]
                print(f"{minute:6.1f} {rss_mb():7.0f} {odom._ivox.num_points:10d} "
                      f"{np.median(recent):14.2f}", flush=True)
                next_report += report_min
        tum.close()
        csvw.close()
        pts = odom.map_points()
        write_map(Path(tmp) / "map.ply", voxel_downsample(pts, cfg.output.map_voxel_m), "ply")
        run_s = time.perf_counter() - t_run
        # ground truth as run_bag's evaluation sees it: IMU pose, world = IMU frame at t0
        t_gt = np.array(est_t, dtype=np.int64)
        s = traj.sample((t_gt - t0) * 1e-9)
        s0 = traj.sample(np.array([0.0]))
        R0, p0 = s0.R_world_imu[0], s0.p_world_imu_m[0]
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(np.einsum("ji,njk->nik", R0, s.R_world_imu)).as_quat()
        p = (s.p_world_imu_m - p0) @ R0
        gt_path = Path(tmp) / "gt.tum"
        np.savetxt(gt_path, np.column_stack([t_gt * 1e-9, p, q]), fmt="%.9f")
        err = ate(Path(tmp) / "trajectory.tum", gt_path)
    print(f"peak RSS {peak_rss_mb():.0f} MB (before the first scan {base:.0f} MB); "
          f"{len(est_t)} poses from {n_scans} sweeps; map {pts.shape[0]} points; "
          f"ATE {err['rmse_m'] * 100:.1f} cm (max {err['max_m'] * 100:.1f} cm); "
          f"wall {run_s / 60:.1f} min incl. ray casting")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0, help="length of the long walk")
    ap.add_argument("--columns", type=int, default=512, help="PandarXT-32 columns per sweep")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--report-min", type=float, default=5.0, help="RSS report interval")
    ap.add_argument("--skip-cold", action="store_true", help="no cold-start measurement")
    ap.add_argument("--skip-long", action="store_true", help="no long walk")
    ap.add_argument("--repeat", type=int, default=2,
                    help="cold runs with and without the helper process, alternating")
    args = ap.parse_args()
    if not args.skip_cold:
        cold_start(args.columns, args.repeat)
    if not args.skip_long:
        long_walk(args.minutes, args.columns, args.seed, args.report_min)


if __name__ == "__main__":
    main()
