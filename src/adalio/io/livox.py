"""Livox's own point cloud message, ``livox_ros_driver/CustomMsg`` (ROS1) and
``livox_ros_driver2/msg/CustomMsg`` (ROS1 and ROS2), read and written without ROS.

Livox LiDARs (Mid-360, Avia, HAP, ...) publish either ``sensor_msgs/PointCloud2`` (read by
:mod:`adalio.io.pointcloud2` like any other) or, as FAST-LIO and most handheld rigs record them,
this message: a ``timebase`` (absolute ns of the frame's first point) and per point an
``offset_time`` (ns after it), ``x, y, z`` (float32 metres, LiDAR frame), ``reflectivity``,
``tag`` and ``line`` (the laser). The points come in firing order; there is no azimuth order and
no rings in the spinning sense.

A Mid-360 frame holds ~20 000 points, so the points are read straight from the serialized bytes
with numpy (ROS1: packed 19-byte points; CDR: 4-byte aligned, a 20-byte stride) rather than as
20 000 Python objects; :func:`parse_custom_msg` and :func:`build_custom_msg` are checked against
rosbags' own (de)serializer in the tests.

The ``tag``'s bits 4-5 give the return (Livox's documentation for Avia and Horizon); like
FAST-LIO's ``livox_handler``, points of a third or later return (bits 4-5 = 2 or 3) are dropped
and counted (:attr:`LivoxDecodeStats.later_return`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from adalio.config import SensorConfig
from adalio.errors import BagError
from adalio.io.pointcloud2 import (
    INT64_MAX_NS,
    INT64_MIN_NS,
    DecodeStats,
    TimeSpec,
    stamp_to_ns,
)
from adalio.types import Scan

LIVOX_PACKAGES = ("livox_ros_driver", "livox_ros_driver2")
LIVOX_TYPES = tuple(f"{p}/msg/CustomMsg" for p in LIVOX_PACKAGES)
"""The message types read as Livox clouds (ROS1 names ``pkg/CustomMsg`` normalize to these)."""

CUSTOM_POINT_MSGDEF = """\
uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""
CUSTOM_MSG_MSGDEF = """\
std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
CustomPoint[] points
"""

POINT_DTYPE_ROS1 = np.dtype([("offset_time", "<u4"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                             ("reflectivity", "u1"), ("tag", "u1"), ("line", "u1")])
"""One ``CustomPoint`` as ROS1 serializes it (packed, 19 bytes)."""
POINT_DTYPE_CDR = np.dtype({"names": list(POINT_DTYPE_ROS1.names),
                            "formats": [POINT_DTYPE_ROS1.fields[n][0]
                                        for n in POINT_DTYPE_ROS1.names],
                            "offsets": [POINT_DTYPE_ROS1.fields[n][1]
                                        for n in POINT_DTYPE_ROS1.names],
                            "itemsize": 20})
"""One ``CustomPoint`` in a CDR sequence: each element starts 4-byte aligned (a 20-byte stride;
the last element has no padding after it)."""

LATER_RETURN_TAGS = (2, 3)
"""Values of the tag's bits 4-5 whose points are dropped (a third or later return)."""


def is_livox_type(msgtype: str) -> bool:
    """True for ``livox_ros_driver[2]/[msg/]CustomMsg``."""
    parts = msgtype.split("/")
    return parts[0] in LIVOX_PACKAGES and parts[-1] == "CustomMsg"


def register_livox_types(store: Any) -> None:
    """Register both packages' ``CustomMsg`` and ``CustomPoint`` in a rosbags typestore (ROS2
    sqlite3 bags of Humble carry no message definitions; the writer needs them too)."""
    from rosbags.typesys import get_types_from_msg

    types: dict[str, Any] = {}
    for pkg in LIVOX_PACKAGES:
        if f"{pkg}/msg/CustomMsg" in store.types:
            continue
        types.update(get_types_from_msg(CUSTOM_POINT_MSGDEF, f"{pkg}/msg/CustomPoint"))
        types.update(get_types_from_msg(CUSTOM_MSG_MSGDEF.replace(
            "CustomPoint[]", f"{pkg}/CustomPoint[]"), f"{pkg}/msg/CustomMsg"))
    if types:
        store.register(types)


@dataclass
class LivoxCloud:
    """One ``CustomMsg``, its points as a numpy structured array (fields of
    :data:`POINT_DTYPE_ROS1`)."""

    stamp_ns: int
    """The header stamp, int64 ns."""
    frame_id: str
    timebase_ns: int
    """Absolute time of the frame's first point, ns (``offset_time`` counts from it)."""
    points: np.ndarray
    lidar_id: int = 0
    point_num: int = -1
    """The message's own count (``-1``: not given); not used: the points' array is what is
    read."""


class _Cursor:
    def __init__(self, raw: bytes | memoryview, start: int, cdr: bool) -> None:
        self.raw, self.pos, self.start, self.cdr = memoryview(raw), start, start, cdr

    def align(self, n: int) -> None:
        if self.cdr:
            self.pos += -(self.pos - self.start) % n

    def take(self, fmt: str, size: int) -> Any:
        self.align(size)
        if self.pos + size > len(self.raw):
            raise ValueError("message ends early")
        (value,) = struct.unpack_from("<" + fmt, self.raw, self.pos)
        self.pos += size
        return value

    def string(self) -> str:
        n = self.take("I", 4)
        if self.pos + n > len(self.raw):
            raise ValueError("string runs past the message")
        s = bytes(self.raw[self.pos:self.pos + n])
        self.pos += n
        return s.rstrip(b"\0").decode("utf-8", "replace")


def parse_custom_msg(raw: bytes | memoryview, ros2: bool) -> LivoxCloud:
    """A serialized ``CustomMsg`` (ROS1 bytes, or CDR with its 4-byte encapsulation header) →
    :class:`LivoxCloud`. ValueError if the bytes do not hold one."""
    if ros2:
        head = bytes(memoryview(raw)[:4])
        if len(head) < 4 or head[1] != 1:
            raise ValueError("not little-endian CDR")
        c = _Cursor(raw, 4, cdr=True)
        sec, nsec = c.take("i", 4), c.take("I", 4)
    else:
        c = _Cursor(raw, 0, cdr=False)
        c.take("I", 4)  # seq
        sec, nsec = c.take("I", 4), c.take("I", 4)
    frame = c.string()
    timebase = c.take("Q", 8)
    point_num = c.take("I", 4)
    lidar_id = c.take("B", 1)
    c.pos += 3  # rsvd
    n = c.take("I", 4)
    dtype = POINT_DTYPE_CDR if ros2 else POINT_DTYPE_ROS1
    size = 0 if n == 0 else (n - 1) * dtype.itemsize + POINT_DTYPE_ROS1.itemsize
    if c.pos + size > len(c.raw):
        raise ValueError(f"{n} points run past the message's {len(c.raw)} bytes")
    if n == 0:
        pts = np.zeros(0, POINT_DTYPE_ROS1)
    elif ros2:
        buf = bytes(c.raw[c.pos:c.pos + size]) + b"\0"  # the last element's missing pad byte
        pts = np.frombuffer(buf, dtype=POINT_DTYPE_CDR, count=n)
    else:
        pts = np.frombuffer(c.raw, dtype=POINT_DTYPE_ROS1, count=n, offset=c.pos)
    return LivoxCloud(stamp_ns=int(sec) * 1_000_000_000 + int(nsec), frame_id=frame,
                      timebase_ns=int(timebase), points=pts, lidar_id=int(lidar_id),
                      point_num=int(point_num))


def build_custom_msg(cloud: LivoxCloud, ros2: bool, seq: int = 0) -> bytes:
    """:class:`LivoxCloud` → the serialized ``CustomMsg`` (the inverse of
    :func:`parse_custom_msg`; ``point_num`` is the points' count)."""
    pts = cloud.points
    n = int(pts.shape[0])
    frame = cloud.frame_id.encode()
    sec, nsec = divmod(int(cloud.stamp_ns), 1_000_000_000)
    out = bytearray()
    if ros2:
        out += b"\x00\x01\x00\x00"
        out += struct.pack("<iI", sec, nsec)
        out += struct.pack("<I", len(frame) + 1) + frame + b"\0"
        out += b"\0" * (-(len(out) - 4) % 8)
    else:
        out += struct.pack("<III", seq, sec, nsec)
        out += struct.pack("<I", len(frame)) + frame
    out += struct.pack("<QIB", int(cloud.timebase_ns), n, int(cloud.lidar_id)) + b"\0\0\0"
    if ros2:
        out += b"\0" * (-(len(out) - 4) % 4)
    out += struct.pack("<I", n)
    if n:
        packed = np.zeros(n, POINT_DTYPE_CDR if ros2 else POINT_DTYPE_ROS1)
        for name in POINT_DTYPE_ROS1.names:
            packed[name] = pts[name]
        body = packed.tobytes()
        out += body[:len(body) - (1 if ros2 else 0)]
    return bytes(out)


def livox_points(offset_time_ns: np.ndarray, xyz: np.ndarray, reflectivity: np.ndarray | None = None,
                 tag: np.ndarray | None = None, line: np.ndarray | None = None) -> np.ndarray:
    """A structured array of ``CustomPoint`` s (fields of :data:`POINT_DTYPE_ROS1`)."""
    n = int(xyz.shape[0])
    pts = np.zeros(n, POINT_DTYPE_ROS1)
    pts["offset_time"] = offset_time_ns
    pts["x"], pts["y"], pts["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for name, v in (("reflectivity", reflectivity), ("tag", tag), ("line", line)):
        if v is not None:
            pts[name] = v
    return pts


@dataclass(frozen=True)
class LivoxTimeSpec(TimeSpec):
    """A CustomMsg's times: ``timebase + offset_time``, in ns, by the message's definition."""

    def describe(self) -> str:
        return "'offset_time' in ns after the message's timebase (Livox CustomMsg)"


@dataclass
class LivoxDecodeStats(DecodeStats):
    """:class:`DecodeStats` and the points dropped as a later return."""

    later_return: int = 0
    """Points dropped for the tag's bits 4-5 saying a third or later return."""

    def why_empty(self) -> str:
        base = super().why_empty()
        extra = f"{self.later_return} points are a third or later return (tag bits 4-5)" \
            if self.later_return else ""
        return "; ".join(p for p in (base, extra) if p)


class LivoxDecoder:
    """Decode ``CustomMsg`` s (:class:`LivoxCloud`, or rosbags' deserialized message) of one
    topic into :class:`Scan` objects, as :class:`~adalio.io.pointcloud2.CloudDecoder` does
    PointCloud2: absolute int64 ns per point (``timebase + offset_time``), NaN/inf and
    (0, 0, 0) points dropped, ``reflectivity`` as the intensity. No rings: a Livox ``line`` is
    one of the lasers that draw the pattern, not a beam at a fixed elevation of a spinning head,
    so the options that need rings (``filter.local_surface_check``, ``filter.one_ring_max_deg``)
    check nothing on it, as on any cloud without a ring field. Each point's ``line`` is kept
    (``Scan.line``) for the stray test, which reads a laser's points in firing order."""

    def __init__(self, sensor: SensorConfig | None = None, topic: str = "") -> None:
        self.sensor = sensor or SensorConfig()
        self.topic = topic
        self.time_spec = LivoxTimeSpec("offset_time", "ns", "after the message's timebase")
        self.stats = LivoxDecodeStats()

    def decode(self, msg: Any) -> Scan:
        where = f"Livox CustomMsg on {self.topic or '?'}"
        if not isinstance(msg, LivoxCloud):
            try:
                pts = np.array([(p.offset_time, p.x, p.y, p.z, p.reflectivity, p.tag, p.line)
                                for p in msg.points], POINT_DTYPE_ROS1)
                msg = LivoxCloud(stamp_ns=stamp_to_ns(msg.header.stamp),
                                 frame_id=str(msg.header.frame_id), timebase_ns=int(msg.timebase),
                                 points=pts, lidar_id=int(msg.lidar_id),
                                 point_num=int(msg.point_num))
            except (AttributeError, TypeError, ValueError, OverflowError):
                raise BagError(f"{where}: the message has no timebase/points (x, y, z, "
                               "offset_time); pick the right lidar topic (--lidar-topic)") \
                    from None
        stamp_ns, base = int(msg.stamp_ns), int(msg.timebase_ns)
        for what, v in (("header stamp", stamp_ns), ("timebase", base)):
            if not INT64_MIN_NS <= v <= INT64_MAX_NS:
                raise BagError(f"{where}: {what} {v} ns is out of range; the message is "
                               "corrupted")
        p = msg.points
        n = int(p.shape[0])
        xyz = np.empty((n, 3), np.float64)
        xyz[:, 0], xyz[:, 1], xyz[:, 2] = p["x"], p["y"], p["z"]
        finite = np.isfinite(xyz).all(axis=1)
        zero = finite & ~xyz.any(axis=1)
        later = finite & ~zero & np.isin((p["tag"] >> 4) & 3, LATER_RETURN_TAGS)
        ok = finite & ~zero & ~later
        self.stats.add(n, int((~finite).sum()), int(zero.sum()), 0, int(ok.sum()))
        self.stats.later_return += int(later.sum())
        t_ns = base + p["offset_time"][ok].astype(np.int64)
        return Scan(points_lidar=xyz[ok], t_ns=t_ns, stamp_ns=stamp_ns,
                    intensity=p["reflectivity"][ok].astype(np.float32),
                    line=p["line"][ok].astype(np.uint8))


def lidar_decoder(msgtype: str, sensor: SensorConfig | None = None,
                  topic: str = "") -> LivoxDecoder | Any:
    """The decoder for a LiDAR topic of ``msgtype``: :class:`LivoxDecoder` for a Livox
    ``CustomMsg``, :class:`~adalio.io.pointcloud2.CloudDecoder` otherwise."""
    from adalio.io.pointcloud2 import CloudDecoder

    return LivoxDecoder(sensor, topic) if is_livox_type(msgtype) else CloudDecoder(sensor, topic)
