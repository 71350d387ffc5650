"""Small synthetic bags for the io tests: a static LiDAR + IMU rig inside a box room.

The LiDAR is a 16-ring spinning sensor (clockwise, 10 Hz) whose rays are intersected exactly with
the six walls of an axis-aligned box; per-point times are Ouster-like (``t`` u32 ns relative to
the header stamp = sweep start). The IMU reads zero rate and +g along its z axis (at rest).
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from adalio.io.bagwrite import BagWriter
from adalio.io.pointcloud2 import encode_pointcloud2

OUSTER_LAYOUT = [("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("intensity", 16, "f4"),
                 ("t", 20, "u4"), ("ring", 26, "u2")]
OUSTER_STEP = 32
T0_NS = 1_700_000_000_000_000_000
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
"""A zstd frame's first bytes (RFC 8878), to tell a compressed message from a CDR one."""
BOX_LO = np.array([-6.0, -4.0, -1.5])
BOX_HI = np.array([5.0, 3.0, 2.5])


def box_scan(columns: int = 360, rings: int = 16, sweep_ns: int = 100_000_000,
             lo: np.ndarray = BOX_LO, hi: np.ndarray = BOX_HI):
    """(points (N,3), t_rel_ns (N,) uint32, ring (N,)) of one sweep from the origin."""
    col = np.arange(columns)
    az = -2.0 * np.pi * col / columns
    el = np.deg2rad(np.linspace(-25.0, 25.0, rings))
    AZ, EL = np.meshgrid(az, el, indexing="ij")
    d = np.stack([np.cos(EL) * np.cos(AZ), np.cos(EL) * np.sin(AZ), np.sin(EL)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t_hi = np.where(d > 0, hi / d, np.inf)
        t_lo = np.where(d < 0, lo / d, np.inf)
    rng = np.minimum(t_hi, t_lo).min(axis=1)
    pts = d * rng[:, None]
    t_rel = np.repeat(col * sweep_ns // columns, rings).astype(np.uint32)
    ring = np.tile(np.arange(rings), columns).astype(np.uint16)
    return pts, t_rel, ring


def write_static_rig(path: Path, fmt: str = "ros1", *, duration_s: float = 2.0,
                     imu_rate_hz: float = 200.0, lidar_rate_hz: float = 10.0,
                     accel_scale: float = 1.0, lidar_topic: str = "/points",
                     imu_topic: str = "/imu", tf_static: list | None = None,
                     imu_frame: str = "imu", lidar_frame: str = "lidar",
                     empty_scans: tuple[int, ...] = (), columns: int = 360,
                     imu_offset_s: float = 0.0, layout: list | None = None,
                     point_step: int = OUSTER_STEP, compression: str | None = None) -> Path:
    """Write a static rig bag; IMU receive time = stamp, cloud receive time = sweep end + 5 ms."""
    sweep_ns = int(1e9 / lidar_rate_hz)
    pts, t_rel, ring = box_scan(columns=columns, sweep_ns=sweep_ns)
    n_imu = int(duration_s * imu_rate_hz)
    n_scans = int(duration_s * lidar_rate_hz) - 1
    events = []
    for k in range(n_imu):
        t = T0_NS + int(imu_offset_s * 1e9) + int(k * 1e9 / imu_rate_hz)
        events.append((t, "imu", k))
    for k in range(n_scans):
        stamp = T0_NS + k * sweep_ns
        events.append((stamp + sweep_ns + 5_000_000, "cloud", k))
    events.sort(key=lambda e: (e[0], e[1]))
    with BagWriter(path, fmt, compression) as w:
        if tf_static:
            w.add_tf_static(tf_static, T0_NS)
        for t_recv, kind, k in events:
            if kind == "imu":
                w.add_imu(imu_topic, t_recv, [0.0, 0.0, 0.0],
                          [0.0, 0.0, 9.81 * accel_scale], frame_id=imu_frame)
            else:
                stamp = T0_NS + k * sweep_ns
                p = pts[:0] if k in empty_scans else pts
                cols = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2],
                        "intensity": np.ones(len(p)), "t": t_rel[: len(p)],
                        "ring": ring[: len(p)]}
                w.add_cloud(lidar_topic, stamp, cols, layout or OUSTER_LAYOUT, point_step,
                            frame_id=lidar_frame, t_recv_ns=t_recv)
    return path


def msg_from(columns, layout, step, stamp_ns, big=False, height=1, row_pad=0):
    """A PointCloud2 message (duck-typed, as rosbags deserializes one) of ``columns`` packed
    with ``layout``; ``row_pad`` bytes of padding after each row."""
    data, fields = encode_pointcloud2(columns, layout, step, big)
    n = len(columns["x"])
    width = n // height
    if row_pad:
        rows = np.frombuffer(data, np.uint8).reshape(height, width * step)
        pad = np.full((height, row_pad), 0xAB, np.uint8)
        data = np.hstack([rows, pad]).tobytes()
    return SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=stamp_ns // 10**9,
                                                     nanosec=stamp_ns % 10**9),
                               frame_id="lidar"),
        fields=[SimpleNamespace(name=a, offset=b, datatype=c, count=d) for a, b, c, d in fields],
        point_step=step, width=width, height=height, row_step=width * step + row_pad,
        is_bigendian=big, data=np.frombuffer(data, np.uint8))
