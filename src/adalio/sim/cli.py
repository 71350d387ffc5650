"""``adalio simulate``: generate a simulated LiDAR + IMU bag with ground truth."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Annotated

import typer


def register(app: typer.Typer) -> None:
    """Add the ``simulate`` command to the adalio CLI."""

    @app.command()
    def simulate(
        scene: Annotated[str, typer.Option("--scene",
                                           help="hall, corridor, spiral or stairs_garage")],
        out: Annotated[Path, typer.Option("--out", help="Output folder (created).")],
        seed: Annotated[int, typer.Option("--seed", help="Seed of clutter, motion, noise.")] = 0,
        duration: Annotated[float | None, typer.Option(
            "--duration", help="Seconds (default: the whole route).")] = None,
        lidar: Annotated[str, typer.Option(
            "--lidar", help="xt32, ouster64, ouster128, vlp16, mid360 (a Livox Mid-360-like "
            "non-repetitive LiDAR, 360 x -7..52 deg) or avia (a Livox Avia-like forward-looking "
            "rosette, 70.4 x 77.2 deg, looking along the walk); both written as Livox's "
            "CustomMsg, their IMU's accelerometer in g")] = "xt32",
        fmt: Annotated[str, typer.Option("--format", help="ros1, ros2 (sqlite3) or mcap")] = "ros1",
        columns: Annotated[int | None, typer.Option(
            "--columns", help="Columns per sweep (default: the model's; mid360: firing "
            "cycles of its 4 lasers a frame, 5000; avia: of its 6 lasers, 4000).")] = None,
        noise_scale: Annotated[float, typer.Option(
            "--noise-scale", help="Multiplier of all sensor noise (0 = perfect).")] = 1.0,
        imu_noise_scale: Annotated[float, typer.Option(
            "--imu-noise-scale", help="Further multiplier of the IMU white noise only (x the "
            "HILTI BMI085 densities).")] = 1.0,
        imu_bias_scale: Annotated[float, typer.Option(
            "--imu-bias-scale", help="Further multiplier of the IMU's initial biases and bias "
            "random walks only (0 = an IMU without bias).")] = 1.0,
        motion_from: Annotated[Path | None, typer.Option(
            "--motion-from", help="TUM trajectory (>= 10 Hz) of a real handheld walk: its hand "
            "and gait motion replace the synthetic one (e.g. the HILTI 2022 exp04-06 dense "
            "ground truth); 'none': no hand motion, the route's own attitude (a robot).")] = None,
        extrinsic: Annotated[str | None, typer.Option(
            "--extrinsic", help="How the IMU sits on the LiDAR: T_imu_lidar as 'tx ty tz qx qy "
            "qz qw' (maps LiDAR points into the IMU frame, as `run --extrinsic`; default: the "
            "HILTI 2022 rig's; mid360 and avia: their built-in IMU, where their preset puts "
            "it). The LiDAR stays level (or as --lidar-tilt-deg says); the IMU "
            "turns.")] = None,
        imu_rate: Annotated[float, typer.Option(
            "--imu-rate", help="IMU samples per second (default: the HILTI BMI085's 400; an "
            "Ouster's internal IMU gives 100). The noise densities stay the same.")] = 400.0,
        lidar_rate: Annotated[float | None, typer.Option(
            "--lidar-rate", help="LiDAR sweeps per second, 2-50 (default: the model's 10). "
            "--columns stays per sweep: a head turning at 20 Hz with the same firing rate has "
            "half the columns.")] = None,
        imu_time_offset_ms: Annotated[float, typer.Option(
            "--imu-time-offset-ms", help="The IMU's stamps run this many ms late against the "
            "LiDAR's (negative: early), as an IMU stamped on arrival; within +-1000. config.yaml "
            "does not say it (meta.json does).")] = 0.0,
        imu_scale_error_pct: Annotated[float, typer.Option(
            "--imu-scale-error-pct", help="The gyro and the accelerometer read the truth "
            "through I + E, E's nine entries drawn N(0, PCT %) from the seed: scale factors and "
            "cross-axis sensitivity, as an uncalibrated MEMS IMU (0-10; default 0). config.yaml "
            "does not say it (meta.json gives E).")] = 0.0,
        people: Annotated[int, typer.Option(
            "--people", help="That many people walk along the route while the rig does "
            "(upright cylinders 0.4 m wide, 1.75 m tall, 0.8-1.5 m/s, both ways; 0-20, default "
            "0); meta.json says where.")] = 0,
        lidar_tilt: Annotated[float, typer.Option(
            "--lidar-tilt-deg", help="The LiDAR sits pitched this many degrees nose down on the "
            "handle (negative: nose up; within +-90), its spin axis leaning forward, so that it "
            "sees the floor ahead and the ceiling behind; the IMU stays fixed to it "
            "(--extrinsic). Default 0: level.")] = 0.0,
        ghosts: Annotated[float, typer.Option(
            "--ghosts", help="Share of the returns that lie 0.3-2.0 m (uniform) further along "
            "their ray, behind their surface: multipath off glass or metal, cross-talk (0-0.5, "
            "default 0; beyond the LiDAR's range they are dropped). meta.json says it.")] = 0.0,
        dust: Annotated[float, typer.Option(
            "--dust", help="Share of the returns that come 0.3-2.0 m (uniform) nearer along "
            "their ray, from dust in front of their surface (0-0.5, default 0; below the LiDAR's "
            "minimum range they are dropped; no return is both dust and a ghost). meta.json "
            "says it.")] = 0.0,
        pace: Annotated[float, typer.Option(
            "--pace", help="Walk the route this many times as fast as the scene's speeds (0.25-3, "
            "default 1: the shaft's 0.45 m/s, the corridor's 1.1 m/s): its speed limits and "
            "turn-rate bound times PACE, its acceleration bound times PACE squared; the hand "
            "and the gait keep their times. meta.json says it.")] = 1.0,
        imu_vibration: Annotated[float, typer.Option(
            "--imu-vibration", help="While the rig moves, the IMU shakes (a robot's motors or "
            "legs): white noise of X times the IMU's white-noise densities added to its samples, "
            "in full from 0.3 m/s on, so the still start stays quiet (0-300, default 0). "
            "config.yaml does not say it (meta.json does).")] = 0.0,
    ) -> None:
        """Simulate a handheld LiDAR + IMU walk through an indoor scene into a ROS bag."""
        import json
        import time

        from adalio.config import transform_from_xyz_quat
        from adalio.errors import InputError, writing_to
        from adalio.io.cli import check_out_dir
        from adalio.sim import simulate as run_simulation
        from adalio.term import console

        if seed < 0:
            raise InputError(f"--seed must be >= 0 (got {seed})")
        held = [n for n in ("gt.tum", "meta.json") if (out / n).exists()]
        if held:  # its gt.tum would be replaced beside the other sequence's bag
            raise InputError(f"--out {out} already holds a simulated sequence ({', '.join(held)})"
                             ": choose another folder, or delete that one first")
        T_imu_lidar = None if extrinsic is None else transform_from_xyz_quat(extrinsic)
        check_out_dir(out)
        t0 = time.perf_counter()
        with writing_to(out):
            res = run_simulation(scene, out, seed=seed, duration_s=duration, lidar=lidar,
                                 fmt=fmt, columns=columns, noise_scale=noise_scale,
                                 progress=True, imu_noise_scale=imu_noise_scale,
                                 imu_bias_scale=imu_bias_scale, motion_from=motion_from,
                                 T_imu_lidar=T_imu_lidar, imu_rate_hz=imu_rate,
                                 lidar_rate_hz=lidar_rate,
                                 imu_time_offset_s=imu_time_offset_ms * 1e-3,
                                 imu_scale_error_pct=imu_scale_error_pct, people=people,
                                 lidar_tilt_deg=lidar_tilt, ghosts=ghosts, dust=dust,
                                 pace=pace, imu_vibration=imu_vibration)
        meta = json.loads(res.meta_path.read_text())
        console().print(
            f"[green]wrote[/] {res.bag_path} ({meta['n_scans']} sweeps, {meta['n_imu']} IMU, "
            f"{meta['duration_s']:.1f} s) in {time.perf_counter() - t0:.1f} s\n"
            f"ground truth {res.gt_path}, config {res.config_path}\n"
            f"run: adalio run {shlex.quote(str(res.bag_path))} "
            f"--config {shlex.quote(str(res.config_path))}", highlight=False)
