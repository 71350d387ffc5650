"""Commands ``adalio info``, ``adalio run`` and ``adalio config show``."""

from __future__ import annotations

import contextlib
import os
import statistics
import sys
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from adalio.errors import AdalioError, BagError, ConfigError, InputError, writing_to
from adalio.term import console

config_app = typer.Typer(help="Inspect the configuration.", no_args_is_help=True,
                         rich_markup_mode=None)


@contextlib.contextmanager
def _warnings_to(console: Console) -> Iterator[None]:
    """Show Python warnings as one 'warning:' line each on the console."""
    old = warnings.showwarning

    def show(message: Any, category: Any, filename: str, lineno: int, file: Any = None,
             line: Any = None) -> None:
        console.print(f"[yellow]warning:[/] {message}", highlight=False, soft_wrap=True)

    warnings.showwarning = show
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = show
            yield
    finally:
        warnings.showwarning = old


def check_out_dir(out: Path, option: str = "--out") -> None:
    """InputError unless ``out`` is an existing folder or can be created as one."""
    existing = out
    while not existing.exists() and existing.parent != existing:
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        where = "is a file" if existing == out else f"lies inside {existing}, which is a file"
        raise InputError(f"{option} {out} {where}: give a folder (new or existing)")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"{option} {out}: {existing} is not writable; choose another folder")


FLAG_NAMES = {"output.dense_map_voxel_m": "--dense-map"}
"""The run's flags whose name is not their config key's last part."""


def _build_config(preset: str | None, config_file: Path | None, lidar_topic: str | None,
                  imu_topic: str | None, extrinsic: str | None, mode: str | None,
                  map_format: str | None, sets: list[str] | None = None,
                  dense_map: float | None = None) -> Any:
    """The run's config: preset < ``--config`` < ``--set KEY=VALUE`` < the named flags; a
    ``--set`` of a key a flag also gives, to another value, is a ConfigError."""
    from adalio.config import load_config, set_options, transform_from_xyz_quat

    flags: dict[str, Any] = {"sensor.lidar_topic": lidar_topic,
                             "sensor.imu_topic": imu_topic, "adaptive.mode": mode,
                             "output.map_format": map_format,
                             "output.dense_map_voxel_m": dense_map}
    overrides: dict[str, Any] = set_options(sets)
    for key, value in flags.items():
        if value is None:
            continue
        if key in overrides and overrides[key] != str(value):
            flag = FLAG_NAMES.get(key, "--" + key.rpartition(".")[2].replace("_", "-"))
            raise ConfigError(f"{flag} {value} and --set {key}={overrides[key]} disagree: give "
                              "one of them")
        overrides[key] = value
    if extrinsic is not None:
        if "sensor.T_imu_lidar" in overrides:
            raise ConfigError("--extrinsic and --set sensor.T_imu_lidar=... both give the "
                              "extrinsic: give one of them")
        overrides["sensor.T_imu_lidar"] = transform_from_xyz_quat(extrinsic)
        overrides["sensor.extrinsic_source"] = "config"
    return load_config(preset, config_file, overrides)


# ------------------------------------------------------------------------------------ info
def info(bag: Annotated[Path, typer.Argument(help="ROS1 .bag (or folder of them), ROS2 bag "
                                             "folder, or .mcap file.")],
         preset: Annotated[str | None, typer.Option(help="Preset whose topics/time settings "
                                                    "to apply.")] = None,
         config: Annotated[Path | None, typer.Option("--config", help="YAML config file.")]
         = None,
         lidar_topic: Annotated[str | None, typer.Option(
             help="PointCloud2 or Livox CustomMsg topic.")] = None,
         imu_topic: Annotated[str | None, typer.Option(help="sensor_msgs/Imu topic.")] = None,
         sample: Annotated[int, typer.Option(help="Scans decoded for the statistics.")] = 5,
         ) -> None:
    """Show a bag's topics, duration, the topics a run would use and the per-point time format."""
    from adalio.io.bag import Bag
    from adalio.io.livox import LivoxCloud, lidar_decoder
    from adalio.io.sequencer import accel_is_in_g, imu_msg_arrays

    if sample < 1:
        raise InputError(f"--sample must be >= 1 (got {sample})")
    cfg = _build_config(preset, config, lidar_topic, imu_topic, None, None, None)
    out = console()
    err = console(stderr=True)
    with _warnings_to(err), Bag(bag) as b:
        out.print(f"bag: {bag}", highlight=False)
        table = Table()
        for col in ("topic", "type", "count", "rate (Hz)"):
            table.add_column(col, justify="right" if col in ("count", "rate (Hz)") else "left")
        for t in b.topics():
            rate = b.topic_rate_hz(t.name, t.count) if t.count > 1 else 0.0
            table.add_row(t.name, t.msgtype, str(t.count), f"{rate:.1f}")
        out.print(table)
        out.print(f"duration: {b.duration_s:.3f} s  "
                  f"({b.start_ns * 1e-9:.3f} .. {b.end_ns * 1e-9:.3f})")
        try:
            lidar, imu = b.select_topics(cfg.sensor)
        except BagError as exc:
            if cfg.sensor.lidar_topic or cfg.sensor.imu_topic:
                raise  # a topic named (flag, config or preset) that a run would refuse
            out.print(f"[yellow]topics:[/] {exc}", highlight=False, soft_wrap=True)
            return
        out.print(f"would use: lidar [bold]{lidar}[/], imu [bold]{imu}[/]")
        dec = lidar_decoder(b.msgtype(lidar), cfg.sensor, lidar)
        counts = []
        strays: list[float] = []  # each sampled cloud's share of stray returns (with rings)
        layout = ""
        n_sample = sample
        span = b.end_ns - b.start_ns
        frame = ""
        seen: set[tuple[int, int, int]] = set()  # a short bag's starts can meet one cloud
        for k in range(n_sample):
            start = b.start_ns + span * k // n_sample
            for _, t_ns, msg in b.messages([lidar], limit=1, start_ns=start):
                if _msg_key(t_ns, msg) in seen:
                    continue
                seen.add(_msg_key(t_ns, msg))
                if not layout and isinstance(msg, LivoxCloud):
                    layout = ("Livox CustomMsg: offset_time (ns after timebase), x, y, z, "
                              "reflectivity, tag, line")
                    frame = msg.frame_id
                elif not layout:
                    layout = ", ".join(f"{f.name}@{f.offset}:{f.datatype}" for f in msg.fields) \
                        + f" (point_step {msg.point_step}, {msg.height}x{msg.width}, " \
                        f"{'big' if msg.is_bigendian else 'little'}-endian)"
                    frame = msg.header.frame_id
                scan = dec.decode(msg)
                counts.append(len(scan))
                share = _stray_share(scan, cfg.preprocess)
                if share is not None:
                    strays.append(share)
        out.print(f"cloud fields: {layout}  frame '{frame}'", highlight=False, soft_wrap=True)
        spec = dec.time_spec.describe() if dec.time_spec else "unknown"
        out.print(f"per-point time: {spec}", highlight=False, soft_wrap=True)
        if counts:
            out.print(f"points per scan ({len(counts)} sampled): min {min(counts)}, "
                      f"median {statistics.median(counts):.0f}, max {max(counts)}")
            limit = 100.0 * cfg.preprocess.stray_drop_share
            out.print(f"stray returns ({len(strays)} sampled): mean "
                      f"{100.0 * statistics.fmean(strays):.2f} %, largest "
                      f"{100.0 * max(strays):.2f} % of a scan's points; a run drops them in a "
                      f"scan above {limit:g} % (preprocess.stray_drop_share; dust, ghosts)"
                      if strays else "stray returns: not tested (the clouds carry no rings)",
                      highlight=False, soft_wrap=True)
        imu_by_t = {_msg_key(t, m): m for _, t, m in b.messages([imu], limit=50)}
        if imu_by_t:
            batch = imu_msg_arrays(list(imu_by_t.values()))
            unit = "g (converted)" if accel_is_in_g(batch.accel_m_s2) else "m/s^2"
            first = next(iter(imu_by_t.values()))
            out.print(f"imu frame '{first.header.frame_id}', accelerometer in {unit}")
            for k in range(1, n_sample):
                start = b.start_ns + span * k // n_sample
                imu_by_t.update((_msg_key(t, m), m)
                                for _, t, m in b.messages([imu], limit=50, start_ns=start))
            imu_msgs = list(imu_by_t.values())
            gyro = imu_msg_arrays(imu_msgs).gyro_rad_s
            finite = np.isfinite(gyro).all(axis=1)
            w = float(np.linalg.norm(gyro[finite], axis=1).max()) if finite.any() else np.nan
            bad = f", {int((~finite).sum())} with NaN/inf" if not finite.all() else ""
            out.print(f"gyro: max |w| {w:.3g} rad/s ({np.degrees(w):.3g} deg/s) over "
                      f"{len(imu_msgs)} sampled messages{bad}", highlight=False)
        tf = b.static_transforms()
        out.print(f"/tf_static: {len(tf)} transforms" if tf else "/tf_static: none")
        from scipy.spatial.transform import Rotation

        from adalio.pipeline import resolve_extrinsic

        T, source = resolve_extrinsic(b, lidar, imu, cfg)
        origin = source if source.startswith("tf_static") else _extrinsic_origin(preset, config)
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        out.print(f"extrinsic a run would use: T_imu_lidar from {origin or 'identity (fallback)'}"
                  f": t = {np.round(T[:3, 3], 6).tolist()} m, q xyzw = "
                  f"{np.round(q, 6).tolist()}", highlight=False, soft_wrap=True)
        if not origin:
            err.print("[yellow]warning:[/] no extrinsic in the preset, the config or /tf_static: "
                      "a run would treat the LiDAR frame as the IMU frame; give --preset, "
                      "--config or run --extrinsic 'tx ty tz qx qy qz qw'", highlight=False,
                      soft_wrap=True)


def _msg_key(receive_ns: int, msg: Any) -> tuple[int, int, int]:
    """A message met twice by ``info``'s sampling (receive time and header stamp)."""
    if hasattr(msg, "stamp_ns"):  # a Livox CustomMsg (LivoxCloud)
        return receive_ns, *divmod(int(msg.stamp_ns), 1_000_000_000)
    return receive_ns, int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)


def _extrinsic_origin(preset: str | None, config_file: Path | None) -> str:
    """Which layer sets ``sensor.T_imu_lidar``: 'config file F', 'preset P', or '' (defaults)."""
    import yaml

    from adalio.config import preset_dict

    if config_file is not None:
        data = yaml.safe_load(config_file.read_text()) or {}
        if isinstance(data, dict):
            if "T_imu_lidar" in (data.get("sensor") or {}):
                return f"config file {config_file}"
            preset = preset or data.get("preset")
    if preset and "T_imu_lidar" in (preset_dict(str(preset)).get("sensor") or {}):
        return f"preset {preset}"
    return ""


# ------------------------------------------------------------------------------------ run
def run(bag: Annotated[Path, typer.Argument(help="ROS1 .bag (or folder of them), ROS2 bag "
                                            "folder, or .mcap file.")],
        preset: Annotated[str | None, typer.Option(help="Preset name (adalio config show).")]
        = None,
        config: Annotated[Path | None, typer.Option("--config", help="YAML config file.")]
        = None,
        lidar_topic: Annotated[str | None, typer.Option(
            help="PointCloud2 or Livox CustomMsg topic.")] = None,
        imu_topic: Annotated[str | None, typer.Option(help="sensor_msgs/Imu topic.")] = None,
        extrinsic: Annotated[str | None, typer.Option(
            help="T_imu_lidar as 'tx ty tz qx qy qz qw' (maps LiDAR points into the IMU "
                 "frame).")] = None,
        mode: Annotated[str | None, typer.Option(help="adaptive | fixed | adaptive+")] = None,
        out: Annotated[Path | None, typer.Option(
            help="Output folder (default: runs/BAGNAME, or runs/BAGNAME_K with the first free K).")]
        = None,
        map_format: Annotated[str | None, typer.Option(help="ply | pcd")] = None,
        dense_map: Annotated[float | None, typer.Option(
            "--dense-map", help="map_dense.ply (or .pcd): every scan's still points at the "
                                "scan's pose, one per voxel of this many metres (at least "
                                "0.01; 0: not written; default output.dense_map_voxel_m, 0.05)."
                                )] = None,
        gt: Annotated[Path | None, typer.Option(help="Ground-truth TUM file: write an "
                                                "evaluation report too.")] = None,
        max_scans: Annotated[int | None, typer.Option(help="Stop after N scans.")] = None,
        start_s: Annotated[float, typer.Option(
            "--start-s", help="Skip the bag's first seconds (start wherever the sensor is).")]
        = 0.0,
        sigma_warn_m: Annotated[float, typer.Option(
            "--sigma-warn-m", help="Name the stretches whose position standard deviation "
                                   "(scans.csv sigma_x/y/z_m) exceeds this many metres.")]
        = 0.10,
        profile: Annotated[bool, typer.Option(help="Print per-stage timings per scan.")]
        = False,
        no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bar.")]
        = False,
        view: Annotated[bool, typer.Option("--view", help="Show the run live in a rerun viewer "
                                           "(needs adalio[view] and a display).")] = False,
        rrd: Annotated[Path | None, typer.Option(help="Record the live view to this .rrd file "
                                                 "(no display needed; open with `rerun FILE`).")]
        = None,
        set_: Annotated[list[str] | None, typer.Option(
            "--set", help="Config override KEY=VALUE (repeatable), over the preset and "
                          "--config, e.g. --set imu.accel_bias_cov=1e-4.")] = None,
        ) -> None:
    """Estimate the trajectory and map of a bag; write trajectory.tum, map, scans.csv, config."""
    from adalio.pipeline import default_out_dir, run_bag

    cfg = _build_config(preset, config, lidar_topic, imu_topic, extrinsic, mode, map_format,
                        set_, dense_map)
    if gt is not None and not gt.is_file():
        raise InputError(f"ground truth {gt} does not exist: check --gt")
    out_dir = out if out is not None else default_out_dir(bag)
    check_out_dir(out_dir)
    if rrd is not None and rrd.is_dir():
        raise InputError(f"--rrd {rrd} is a folder: give a file name for the recording, e.g. "
                         f"{rrd / 'run.rrd'}")
    if rrd is not None and rrd.suffix.lower() != ".rrd":
        raise InputError(f"--rrd {rrd}: the recording is written over that file, so give a name "
                         f"ending in .rrd (e.g. {rrd.with_suffix('.rrd').name})"
                         + ("; this one exists, and is kept" if rrd.exists() else ""))
    con = console(stderr=True)
    viewer = None
    try:
        with _warnings_to(con):
            if view or rrd is not None:
                from adalio.view import RerunView

                viewer = RerunView(spawn=view, rrd_path=rrd)
            with writing_to(out_dir):
                res = run_bag(bag, cfg, out_dir, progress=not no_progress and con.is_terminal,
                              max_scans=max_scans, on_estimate=viewer, start_s=start_s,
                              sigma_warn_m=sigma_warn_m, on_compile=lambda: compile_notice(con))
        origin = ("--extrinsic" if extrinsic is not None else
                  _extrinsic_origin(preset, config) or "identity (fallback)")
        _summary(con, res, profile, origin)
    except KeyboardInterrupt:
        res = None
    finally:
        if viewer is not None:
            viewer.close()
    if viewer is not None and viewer.rrd_path is not None:
        con.print(f"live view recorded to {viewer.rrd_path} (open with: rerun "
                  f"{viewer.rrd_path})", highlight=False, soft_wrap=True)
    if gt is not None and res is not None and not res.interrupted:
        _report(con, res.out_dir, gt)
    if res is None or res.interrupted:
        raise typer.Exit(130)  # the entry point prints the 'interrupted' line


COMPILE_NOTICE = ("[cyan]note:[/] first run after an install or an update of adalio: its "
                  "kernels compile now (about 20 s on two cores, 35-40 s on one; once: later "
                  "runs load them from numba's cache)")


def compile_notice(con: Console) -> None:
    """``run_bag``'s ``on_compile``: say that the run compiles adalio's kernels now (a cold numba
    cache); it would otherwise sit at its first scan for that long without a word."""
    con.print(COMPILE_NOTICE, highlight=False, soft_wrap=True)


def _report(con: Console, out_dir: Path, gt: Path) -> None:
    """``run --gt``: write the report and print the ATE (or HILTI score) and its path."""
    import json

    from adalio.eval.report import make_report

    report = make_report(out_dir, gt=gt)
    metrics = json.loads((report.parent / "metrics.json").read_text())
    if "ate_se3" in metrics:
        a = metrics["ate_se3"]
        con.print(f"ATE (SE(3)-aligned, {a['n']} poses): RMSE {a['rmse_m']:.4f} m, max "
                  f"{a['max_m']:.4f} m", highlight=False, soft_wrap=True)
    elif "hilti" in metrics:
        h = metrics["hilti"]
        con.print(f"HILTI 2022 score: {h['score']:.1f} / 100 ({h['n_matched']}/{h['n_gt']} "
                  "control points)", highlight=False, soft_wrap=True)
    err = console(stderr=True)
    for text in metrics.get("warnings") or []:
        err.print("[yellow]warning:[/] ", end="", highlight=False)
        err.print(text, markup=False, highlight=False, soft_wrap=True)
    con.print(f"report: {report}", highlight=False, soft_wrap=True)


def _stray_share(scan: Any, pre: Any) -> float | None:
    """The share of a decoded cloud's finite points that are stray returns
    (``adalio.lio.stray``), None where it has no rings, one ring id, or ids of no LiDAR, which
    a run does not test either."""
    from adalio.lio.stray import ring_id_span, rings_testable, stray_returns

    ids = scan.ring if scan.ring is not None else scan.line  # a Livox cloud's lasers
    if not rings_testable(ring_id_span(ids)):
        return None
    ring = np.asarray(ids, np.int64)
    pts = np.asarray(scan.points_lidar, np.float64)
    ok = np.isfinite(pts).all(axis=1)
    if not ok.any():
        return None
    return float(stray_returns(pts[ok], np.asarray(scan.t_ns)[ok], ring[ok],
                               pre.stray_tolerance_m, pre.stray_tolerance_rel,
                               scan.ring is None).mean())


def _ranges_text(ranges_s: list[tuple[float, float]], limit: int = 8) -> str:
    """'a-b s, c-d s' for the first ``limit`` (start, end) ranges, ' ...' if there are more."""
    text = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in ranges_s[:limit])
    return text + (" ..." if len(ranges_s) > limit else "")


NO_POSE_WARN_FRACTION = 0.1
"""The summary flags a moving start whose refused fits left more than this share of the scans
read without a pose (issue #12's target for a moving start is a pose for 90 % of them). The
scans of a still start's window are not flagged: the sensor rests there, at the first pose."""


def _unsettled_text(check: Any, value: str, precise: str, cause: str, used: str) -> str:
    """'not settled ...' / 'not checked ...' for a check that closed without a conclusion
    (:class:`adalio.types.UnsettledCheck`): its last ``value`` against the ``precise`` enough
    one; without an estimate, the ``cause`` (when the span was long enough); and the value
    ``used`` (the config's, or the one the run restarted with)."""
    from adalio.lio.time_offset import END_MIN_SPAN_S

    span = f"{check.span_s:.0f} s of updates" + ("" if check.gave_up else
                                                  " (the recording ended)")
    if check.estimate is not None:
        return (f"not settled over {span}: {value}, where it settles at {precise} (too little "
                f"rotation, or too noisy a registration, to settle it); {used} used as it is")
    if check.span_s < END_MIN_SPAN_S:
        return (f"not checked: {check.span_s:.1f} s of updates, it needs {END_MIN_SPAN_S:g}; "
                f"{used} used as it is")
    return f"not checked over {span}: {cause}; {used} used as it is"


def _check_tail(unsettled: Any, left: Any, show: Callable[[Any], str], precise: str,
                cause: str, used: str,
                against: str = "left against the LiDAR-registered rotation",
                significant: str = " (see the warning)") -> str:
    """What a sensor check's final run says: unsettled (:func:`_unsettled_text`), or the value
    it concluded on (``show`` formats an estimate with its deviation), or ''."""
    if unsettled is not None:
        est = unsettled.estimate
        return _unsettled_text(unsettled, "" if est is None else show(est), precise, cause, used)
    if left is None:
        return ""
    return (f"{show(left)} {against} over {left.span_s:.0f} s"
            + (significant if left.significant else ""))


def _timing_text(res: Any) -> str:
    """What the IMU time offset check concluded, or that it could not ('' if it is off)."""
    from adalio.lio.time_offset import SIGMA_DONE_S, SIGMA_SIGNIFICANT_S

    found = getattr(res, "time_offset_found", None)
    text = ""
    if found is not None:
        text = (f"sensor.imu_time_offset_s {found.offset_s:.4f} found over the first "
                f"{found.n_scans} scans in {len(found.passes)} passes (the first run saw "
                f"{found.detected_s * 1e3:+.1f} ms), the run restarted with it; ")
    return text + _check_tail(
        getattr(res, "time_offset_unsettled", None), getattr(res, "time_offset", None),
        lambda e: f"{e.offset_s * 1e3:+.1f} ms (+-{e.sigma_s * 1e3:.1f})",
        f"+-{SIGMA_DONE_S * 1e3:g} ms, or on a significant offset at "
        f"+-{SIGMA_SIGNIFICANT_S * 1e3:g} ms", "no change of the rotation rate beyond the "
        "gyro's noise to time it against the LiDAR, or too few scan pairs",
        "the offset found" if found is not None else "sensor.imu_time_offset_s")


def _rotation_text(res: Any) -> str:
    """What the LiDAR-IMU rotation check concluded, or that it could not ('' if it is off)."""
    from adalio.lio.extrinsic_check import SIGMA_DONE_RAD, SIGMA_SIGNIFICANT_RAD

    found = getattr(res, "extrinsic_rotation_found", None)
    text = ""
    gross = getattr(res, "extrinsic_rotation_gross_found", None)
    if gross is not None:
        text = (f"sensor.T_imu_lidar turned by {gross.text()}, a gross error found by a LiDAR "
                f"registration without the gyro over the first {gross.span_s:.0f} s, the run "
                "restarted with it; then ")
    refuted = getattr(res, "extrinsic_rotation_gross_refuted", None)
    if refuted is not None:
        gross, left = refuted
        text = (f"a gross error of {gross.text()} registered without the gyro over the first "
                f"{gross.span_s:.0f} s refused, as corrected by it the filter's LiDAR-only "
                f"rotation disagreed with the gyro more ({np.degrees(left.angle_rad):.2f} deg "
                f"against {np.degrees(gross.fine_rad):.2f} deg); then ")
    if found is not None:
        weighed = ("" if found.found_rad is None else
                   f" ({np.degrees(np.linalg.norm(found.found_rad)):.2f} deg as found, weighed "
                   "by its noise)")
        text += (f"sensor.T_imu_lidar turned by {found.angle_deg:.2f} deg{weighed}, found "
                 f"over the first {found.n_scans} scans in {len(found.passes)} passes (the first "
                 f"run saw {np.degrees(np.linalg.norm(found.detected_rad)):.2f} deg), the run "
                 "restarted with it; ")
    return text + _check_tail(
        getattr(res, "extrinsic_rotation_unsettled", None),
        getattr(res, "extrinsic_rotation", None),
        lambda e: f"{np.degrees(e.angle_rad):.2f} deg (+-{np.degrees(e.sigma_rad):.2f})",
        f"+-{np.degrees(SIGMA_DONE_RAD):g} deg, or on a significant rotation at "
        f"+-{np.degrees(SIGMA_SIGNIFICANT_RAD):g} deg", "the rig turned about one axis only, or "
        "too few scan pairs, to tell the gyro's axes from the LiDAR's",
        "the corrected rotation" if found is not None else "sensor.T_imu_lidar's rotation")


def _gyro_scale_text(res: Any) -> str:
    """What the gyro scale check concluded, or that it could not ('' if it is off)."""
    from adalio.lio.gyro_scale import SIGMA_DONE, SIGMA_SIGNIFICANT

    found = getattr(res, "gyro_scale_found", None)
    text = ""
    if found is not None:
        text = (f"sensor.gyro_sensitivity corrected by {found.text()}, found over the first "
                f"{found.n_scans} scans in {len(found.passes)} passes (the first run saw "
                f"{100 * np.abs(found.detected).max():.2f} %), the run restarted with it; ")
    return text + _check_tail(
        getattr(res, "gyro_scale_unsettled", None), getattr(res, "gyro_scale", None),
        lambda e: e.text(),
        f"+-{SIGMA_DONE * 100:g} %, or on a significant error at +-{SIGMA_SIGNIFICANT * 100:g} %",
        "too few scan pairs whose rotation the LiDAR registers to 0.09 deg (a shaft's, a "
        "corridor's walls hold it too weakly), or too little rotation about some axis, to tell "
        "the gyro's scales", "the corrected sensitivity" if found is not None else
        "sensor.gyro_sensitivity", against="left against the LiDAR-registered rates")


def _translation_text(res: Any) -> str:
    """What the LiDAR-IMU translation check concluded, or that it could not ('' if it is off)."""
    from adalio.lio.lever_arm import SIGMA_DONE_M, SIGMA_SIGNIFICANT_M

    return _check_tail(
        getattr(res, "extrinsic_translation_unsettled", None),
        getattr(res, "extrinsic_translation", None), lambda e: e.text(),
        f"+-{SIGMA_DONE_M * 100:g} cm, or on a significant correction at "
        f"+-{SIGMA_SIGNIFICANT_M * 100:g} cm", "the rig turned too little, or too few scan "
        "triples, to tell a lever arm", "sensor.T_imu_lidar's translation",
        against="off against the LiDAR-registered motion, in the IMU frame,",
        significant=": check sensor.T_imu_lidar's translation (this estimate is good to a "
        "centimetre or two; the part along the rig's vertical is not checked)")


FAR_DEVIATIONS = 5.0
"""A sensor check that closed unsettled with an estimate this many standard deviations from the
configured value: the value is likely wrong by more than the check can settle (its precision
rule is for small corrections), a warning."""


FAR_PRECISION = 10.0
"""... and only where its deviation is within this many times the precision at which the check
concludes on a significant value (an estimate of 5 m +- 78 cm from a robot's one-axis turns is
the check's own degeneracy, not the rig's)."""


def _far_unsettled(res: Any) -> list[str]:
    """Warnings for the sensor checks that closed unsettled far from the configured value (a
    rotation off by 10 deg, a lever arm by 20 cm, a gyro read in the wrong unit): the run used
    the configured value, which its own data contradict."""
    from adalio.lio import extrinsic_check, gyro_scale, lever_arm, time_offset

    out = []
    for name, attr, size, precise, setting in (
            ("IMU time offset", "time_offset_unsettled",
             lambda e: (abs(e.offset_s), e.sigma_s, f"{e.offset_s * 1e3:+.1f} ms"),
             time_offset.SIGMA_SIGNIFICANT_S, "sensor.imu_time_offset_s"),
            ("LiDAR-IMU rotation", "extrinsic_rotation_unsettled",
             lambda e: (e.angle_rad, e.sigma_rad, f"{np.degrees(e.angle_rad):.2f} deg"),
             extrinsic_check.SIGMA_SIGNIFICANT_RAD,
             "sensor.T_imu_lidar's rotation (or the axes' order in a quaternion: x y z w)"),
            ("gyro scale", "gyro_scale_unsettled",
             lambda e: (e.largest, e.sigma, e.text()), gyro_scale.SIGMA_SIGNIFICANT,
             "sensor.gyro_unit and sensor.gyro_sensitivity"),
            ("LiDAR-IMU translation", "extrinsic_translation_unsettled",
             lambda e: (e.length_m, e.sigma_m, e.text()), lever_arm.SIGMA_SIGNIFICANT_M,
             "sensor.T_imu_lidar's translation (in metres)")):
        check = getattr(res, attr, None)
        est = getattr(check, "estimate", None)
        if est is None:
            continue
        value, sigma, shown = size(est)
        if est.significant and 0 < sigma <= FAR_PRECISION * precise and \
                value >= FAR_DEVIATIONS * sigma:
            out.append(f"the {name} check's estimate, {shown}, is {value / sigma:.0f} standard "
                       f"deviations from the configured value: it could not settle it at its "
                       f"precision, but the data contradict the setting; check {setting}")
    return out


def _summary(con: Console, res: Any, profile: bool, origin: str = "") -> None:
    """The run's summary; ``origin`` names where a configured extrinsic came from (the preset,
    the config file, --extrinsic, or 'identity (fallback)', which is warned about)."""
    status = "[yellow]interrupted[/]" if res.interrupted else "[green]done[/]"
    before = getattr(res, "calibration_wall_s", 0.0)
    restarted = (f", after {before:.1f} s on the first run and the passes that found the "
                 "IMU timing, rotation or gyro scale" if before > 0 else "")
    con.print(f"{status}: {res.n_scans} poses from {res.n_scans_in} scans in {res.wall_s:.1f} s "
              f"({res.n_scans_in / max(res.wall_s, 1e-9):.1f} scans/s, median "
              f"{res.ms_per_scan_median:.1f} ms/scan{restarted}) → {res.out_dir}",
              highlight=False, soft_wrap=True)
    source = res.extrinsic_source
    if source == "config" and origin:
        source = origin
    con.print(f"topics: {res.lidar_topic} + {res.imu_topic}; extrinsic from "
              f"{source}; point time {res.time_spec}", highlight=False,
              soft_wrap=True)
    if source == "identity (fallback)":
        con.print("[yellow]warning:[/] no extrinsic in the preset, the config, --extrinsic or "
                  "/tf_static: the run treated the LiDAR frame as the IMU frame; give "
                  "sensor.T_imu_lidar in a config or --extrinsic 'tx ty tz qx qy qz qw'",
                  highlight=False, soft_wrap=True)
    rep = res.init_report
    if rep is not None:
        con.print(f"initialization: {rep.describe()}", highlight=False, soft_wrap=True)
        left = rep.scans_left_without_pose
        if rep.refused_fits and left > NO_POSE_WARN_FRACTION * res.n_scans_in:
            con.print(f"[yellow]at risk:[/] {left}/{res.n_scans_in} scans have no pose: the "
                      f"filter started {rep.wait_s:.1f} s after the first scan "
                      f"({rep.describe_wait()}) and the backfill reached {rep.backfilled} of the "
                      f"{rep.scans_without_pose} scans before it (imu.backfill_s); the "
                      "trajectory and map start after them; a recording that begins with the "
                      "sensor at rest (imu.init_window_s) initializes at once (README, "
                      "Initialization)",
                      highlight=False, soft_wrap=True)
    timing = _timing_text(res)
    if timing:
        con.print(f"IMU timing: {timing}", highlight=False, soft_wrap=True)
    rotation = _rotation_text(res)
    if rotation:
        con.print(f"LiDAR-IMU rotation: {rotation}", highlight=False, soft_wrap=True)
    scale = _gyro_scale_text(res)
    if scale:
        con.print(f"gyro scale: {scale}", highlight=False, soft_wrap=True)
    translation = _translation_text(res)
    if translation:
        con.print(f"LiDAR-IMU translation: {translation}", highlight=False, soft_wrap=True)
    for text in _far_unsettled(res):
        con.print("[yellow]warning:[/] ", end="", highlight=False)
        con.print(text, markup=False, highlight=False, soft_wrap=True)
    ranges = _ranges_text(res.degenerate_ranges_s)
    con.print(f"degenerate scans: {res.n_degenerate}/{res.n_scans}"
              + (f" at {ranges}" if ranges else ""), highlight=False, soft_wrap=True)
    view = getattr(res, "lidar_view", None)
    if view is not None and not view.sees_horizon:  # a LiDAR pitched beyond its view
        con.print(f"LiDAR view: {view.describe()}", highlight=False, soft_wrap=True)
    if getattr(res, "n_sigma_warn", 0):
        ext_m = getattr(res, "sigma_warn_extrinsic_m", 0.0)
        con.print(f"[yellow]at risk:[/] position sigma above {res.sigma_warn_m:g} m (scans.csv "
                  f"sigma_x/y/z_m) in {res.n_sigma_warn}/{res.n_scans} scans at "
                  f"{_ranges_text(res.sigma_warn_ranges_s)}"
                  + (f"; the LiDAR-IMU extrinsic's own uncertainty gives up to {ext_m:.2g} m of "
                     "it (sensor.extrinsic_rotation_sigma_deg, extrinsic_translation_sigma_m: "
                     "how well you know it)"
                     if ext_m >= 0.1 * res.sigma_warn_m else ""),
                  highlight=False, soft_wrap=True)
    gaps = getattr(res, "lidar_gaps", [])
    if gaps:
        t_s, gap_s, sigma_m = max(gaps, key=lambda g: g[1])
        con.print(f"[yellow]at risk:[/] {len(gaps)} LiDAR gap{'s' if len(gaps) > 1 else ''} "
                  f"(scans.csv lidar_gap), the longest {gap_s:.2f} s at {t_s:.1f} s: the IMU "
                  f"alone carried the pose, its position sigma grew to {sigma_m:.2g} m",
                  highlight=False, soft_wrap=True)
    raises = getattr(res, "noise_raises", [])
    if raises:
        t_s, gyro_x, accel_x = raises[-1]
        when = (f"raised at {t_s:.1f} s" if len(raises) == 1 else
                f"raised {len(raises)} times from {raises[0][0]:.1f} s to {t_s:.1f} s")
        con.print(f"[yellow]at risk:[/] the IMU is noisier in motion than at the start "
                  f"(vibration?): its white noise measured over the run reached {gyro_x:.3g}x "
                  f"(gyro) and {accel_x:.3g}x (accelerometer) the density the filter started "
                  f"with, {when}; the filter uses it from there (imu.track_noise_ratio), so "
                  f"the sigmas grow with it", highlight=False, soft_wrap=True)
    for sensor in ("accelerometer", "gyro"):
        axes = [(sat, t_s) for sat, t_s in getattr(res, "imu_saturation", [])
                if sat.sensor == sensor]
        if axes:
            said = "; ".join(f"{sat.axis}: {sat.value:+.4g} {sat.unit} on {sat.n_samples} samples "
                             f"in {sat.n_stretches} stretch{'es' if sat.n_stretches > 1 else ''}, "
                             f"the first at {t_s:.1f} s" for sat, t_s in axes)
            con.print(f"[yellow]at risk:[/] the {sensor} reads the end of its range ({said}): "
                      f"it clips there, so the motion it gives falls short of the real one and "
                      f"the LiDAR has to correct it; record with a wider range if the IMU has one",
                      highlight=False, soft_wrap=True)
    if getattr(res, "n_height_blind", 0):
        con.print(f"[yellow]at risk:[/] height left to the IMU (scans.csv height_blind: the "
                  f"scans' height is mostly what their fitted normals' noise fakes; the height "
                  f"sigma grows) in "
                  f"{res.n_height_blind}/{res.n_scans} scans at "
                  f"{_ranges_text(res.height_blind_ranges_s)}", highlight=False, soft_wrap=True)
    kept_out, seen, n_scans_moving = getattr(res, "moving_points", (0, 0, 0))
    if kept_out or seen:
        body = ", or on the same body" if getattr(res, "moving_body", False) else ""
        con.print(f"moving things (map.remove_moving): {kept_out} points of {n_scans_moving} "
                  f"scans kept out of the update and the map (in space an earlier sweep saw "
                  f"through{body}; scans.csv n_moving), {seen} map points "
                  f"removed as seen through "
                  f"(n_seen_through)", highlight=False, soft_wrap=True)
    from adalio.pipeline import STRAY_NOTE_SHARE

    n_read = getattr(res, "stray_points", (0, 0))[1]
    n_share, n_scans_share, kept = getattr(res, "stray_drops", (0, 0, 0))
    if n_share and getattr(res, "stray_dropped", False):
        con.print(f"stray returns (preprocess.drop_stray_returns): {n_share} of {n_read} points "
                  f"({100.0 * n_share / n_read:.2f} %) dropped, their range continuing neither "
                  f"side along their ring (dust, ghosts, mixed pixels, thin things; scans.csv "
                  f"n_stray, n_stray_dropped)", highlight=False, soft_wrap=True)
    elif n_read:
        if n_share:
            share = 100.0 * getattr(res, "stray_drop_share", 1.0)
            con.print(f"stray returns (preprocess.stray_drop_share): {n_scans_share}/"
                      f"{res.n_scans} scans had more than {share:g} % (dust or rain in front of "
                      f"surfaces, ghosts behind them) and dropped {n_share} points "
                      f"({100.0 * n_share / n_read:.1f} % of those read), the stray "
                      f"returns and the points only an adjacent ring continues (scans.csv "
                      f"n_stray, n_stray_dropped), at "
                      f"{_ranges_text(getattr(res, 'stray_dropped_ranges_s', []))}",
                      highlight=False, soft_wrap=True)
        if kept and kept >= STRAY_NOTE_SHARE * n_read:
            con.print(f"note: {kept} of {n_read} points ({100.0 * kept / n_read:.1f} %) are "
                      f"stray returns kept, their range continuing neither side along their ring "
                      f"and no adjacent ring's return there (dust or rain in front of surfaces, "
                      f"ghosts behind them, mixed pixels; scans.csv n_stray): where the map shows "
                      f"them, --set preprocess.stray_drop_share=0.01 drops them in every sweep "
                      f"where they are more than 1 % (README, Stray returns)",
                      highlight=False, soft_wrap=True)
    left_out, n_map = getattr(res, "map_left_out", (0, 0))
    if left_out:
        k = getattr(res, "map_min_returns", 2)
        con.print(f"map: {left_out} of {n_map} points ({100.0 * left_out / n_map:.1f} %) left "
                  f"out of {res.map_path.name}, their cell reached by fewer than {k} of the "
                  f"scans' points over the run and on no plane of the map (stray returns: "
                  f"dust, rain, ghosts; output.map_min_returns, 1 keeps them)",
                  highlight=False, soft_wrap=True)
    dense_path = getattr(res, "dense_map_path", None)
    if dense_path is not None:
        n_dense, dense_left_out = getattr(res, "dense_map_points", (0, 0))
        con.print(f"dense map: {n_dense} points in {dense_path.name}, one per "
                  f"{res.dense_map_voxel_m:g} m voxel; {dense_left_out} left out, no point of "
                  f"{res.map_path.name} within a map cell of them (what later sweeps saw "
                  f"through; stray returns)", highlight=False, soft_wrap=True)
    dropped, rows = getattr(res, "local_surface_rows", (0, 0))
    if rows:
        con.print(f"local-surface check: {dropped}/{rows} rows dropped "
                  f"({100.0 * dropped / rows:.2f} %), their map plane off the scan's own surface",
                  highlight=False, soft_wrap=True)
    if getattr(res, "n_held", 0):
        con.print(f"scans with a direction left to the IMU (adaptive+, see held_dirs in "
                  f"scans.csv): {res.n_held}/{res.n_scans} at "
                  f"{_ranges_text(res.held_ranges_s)}", highlight=False, soft_wrap=True)
    if res.sequencer is not None:
        for msg in res.sequencer.messages:
            if msg.startswith(("skipped", "re-sorted", "dropped")):
                con.print(f"[yellow]note:[/] {msg}", highlight=False, soft_wrap=True)
    if res.stage_ms:
        n = max(res.n_scans_in, 1)
        total = sum(res.stage_ms.values())
        table = Table(title="per-stage time")
        for col in ("stage", "total s", "ms/scan", "share"):
            table.add_column(col, justify="left" if col == "stage" else "right")
        for stage, ms in res.stage_ms.items():
            table.add_row(stage, f"{ms / 1e3:.2f}", f"{ms / n:.2f}",
                          f"{100 * ms / max(total, 1e-9):.0f}%")
        if profile:
            con.print(table)
            sq = res.sequencer
            if sq is not None:
                con.print(f"sequencer: {sq.imu_samples} IMU samples ({sq.imu_duplicates} "
                          f"duplicate, {sq.imu_reordered} reordered), {sq.scans_in} scans in, "
                          f"{sq.scans_out} out", highlight=False, soft_wrap=True)
        else:
            con.print("stages (ms/scan): " + ", ".join(
                f"{stage} {ms / n:.1f}" for stage, ms in res.stage_ms.items()),
                highlight=False, soft_wrap=True)
    if getattr(res, "compiled", False):
        con.print("[cyan]note:[/] this run compiled adalio's kernels (first run after an install "
                  "or an update): its wall time, scans/s and stage times include that one-time "
                  "compilation; the median ms/scan hardly does", highlight=False,
                  soft_wrap=True)


# ------------------------------------------------------------------------------------ config
@config_app.command("show")
def config_show(preset: Annotated[str | None, typer.Argument(help="Preset name.")] = None,
                config: Annotated[Path | None, typer.Option("--config", help="YAML file.")]
                = None) -> None:
    """Print the effective config (defaults < preset < file) as YAML."""
    from adalio.config import available_presets, load_config

    cfg = load_config(preset, config)
    head = f"# preset: {preset}" if preset else \
        f"# defaults (presets: {', '.join(available_presets())})"
    sys.stdout.write(head + "\n" + cfg.to_yaml())


def register(app: typer.Typer) -> None:
    """Add info, run and config to the main app."""
    app.command("info")(info)
    app.command("run")(run)
    app.add_typer(config_app, name="config")


__all__ = ["AdalioError", "ConfigError", "check_out_dir", "register"]
