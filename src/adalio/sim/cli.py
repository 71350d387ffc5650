"""``adalio simulate``: generate a simulated LiDAR + IMU bag with ground truth."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    """Add the ``simulate`` command to the adalio CLI."""

    @app.command()
    def simulate(
        scene: str = typer.Option(..., "--scene", help="hall, corridor, spiral or stairs_garage"),
        out: Path = typer.Option(..., "--out", help="Output folder (created)."),
        seed: int = typer.Option(0, "--seed", help="Seed of clutter, motion and noise."),
        duration: float | None = typer.Option(None, "--duration",
                                              help="Seconds (default: the whole route)."),
        lidar: str = typer.Option("xt32", "--lidar", help="xt32 or ouster64"),
        fmt: str = typer.Option("ros1", "--format", help="ros1, ros2 (sqlite3) or mcap"),
        columns: int | None = typer.Option(None, "--columns",
                                           help="Columns per sweep (default: the model's)."),
        noise_scale: float = typer.Option(1.0, "--noise-scale",
                                          help="Multiplier of all sensor noise (0 = perfect)."),
    ) -> None:
        """Simulate a handheld LiDAR + IMU walk through an indoor scene into a ROS bag."""
        import json
        import time

        from rich.console import Console

        from adalio.sim import simulate as run_simulation

        t0 = time.perf_counter()
        res = run_simulation(scene, out, seed=seed, duration_s=duration, lidar=lidar, fmt=fmt,
                             columns=columns, noise_scale=noise_scale, progress=True)
        meta = json.loads(res.meta_path.read_text())
        Console().print(
            f"[green]wrote[/] {res.bag_path} ({meta['n_scans']} sweeps, {meta['n_imu']} IMU, "
            f"{meta['duration_s']:.1f} s) in {time.perf_counter() - t0:.1f} s\n"
            f"ground truth {res.gt_path}, config {res.config_path}\n"
            f"run: adalio run {res.bag_path} --config {res.config_path}", highlight=False)
