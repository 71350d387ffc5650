"""sensor_msgs/PointCloud2 encoding and decoding, vectorized from ``msg.fields``.

Datatype codes are those of sensor_msgs/PointField: 1 INT8, 2 UINT8, 3 INT16, 4 UINT16,
5 INT32, 6 UINT32, 7 FLOAT32, 8 FLOAT64.

Decoding reads x, y, z (metres, LiDAR frame = the cloud's ``header.frame_id``), an optional
intensity and ring, and a per-point time field whose name, unit (s/ms/us/ns) and reference
(absolute epoch time or offset from the header stamp) are detected from the first cloud unless
configured (``sensor.point_time_*``). Output times are int64 absolute nanoseconds. Points with a
non-finite coordinate or time, and points at exactly (0, 0, 0) (many drivers' placeholder for "no
return"), are dropped together with their time; :class:`DecodeStats` counts what was dropped so
that an all-empty topic can be explained. A configured time unit/reference that gives implausible
times (a cloud spanning more than ``MAX_SPAN_SWEEPS`` sweeps, times hours from the header stamp)
is refused on the first cloud, naming the field and the unit. A cloud without a time field
gets times reconstructed from the azimuth of a spinning LiDAR (clockwise seen from above, one
sweep = ``1 / sensor.lidar_rate_hz``), starting at the header stamp; a Livox driver's cloud
without one (fields ``tag`` and ``line``: ``livox_ros_driver``'s PointCloud2) gets them spread
evenly over the frame in the points' order, as the LiDAR fires them at a constant rate.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from adalio.config import SensorConfig
from adalio.errors import BagError
from adalio.jit import kernel
from adalio.types import Scan

POINTFIELD_DTYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4",
                                     7: "f4", 8: "f8"}
DTYPE_TO_POINTFIELD: dict[str, int] = {v: k for k, v in POINTFIELD_DTYPES.items()}

TIME_FIELD_CANDIDATES: tuple[str, ...] = (
    "t", "time", "timestamp", "timestamps", "offset_time", "time_offset", "time_stamp",
    "timeoffset", "stamp", "t_ns", "point_time",
)
"""Field names tried, in order, when ``sensor.point_time_field`` is 'auto'."""

UNIT_TO_NS: dict[str, int] = {"s": 1_000_000_000, "ms": 1_000_000, "us": 1_000, "ns": 1}
INT64_MIN_NS = -(2**63)
INT64_MAX_NS = 2**63 - 1
MIN_SPAN_SWEEPS = 0.02
"""A cloud's times must span at least this fraction of a sweep for a unit to be accepted."""
MIN_POINTS_FOR_SPAN = 100
MAX_SPAN_SWEEPS = 5.0
"""A configured time unit giving a cloud longer than this many sweeps is refused."""
CONFIGURED_MIN_SPAN_SWEEPS = 0.01
CONFIGURED_MIN_SPAN_POINTS = 1000
"""... and one of at least ``CONFIGURED_MIN_SPAN_POINTS`` points spanning less than this share of
a sweep (but more than 0: constant times are no times), a unit read too small (seconds as ms).
Laxer than detection's ``MIN_SPAN_SWEEPS`` / ``MIN_POINTS_FOR_SPAN``: only the first cloud is
checked, and it may be a driver's partial sweep."""
MAX_STAMP_OFFSET_S = 3600.0
"""A configured time unit/reference putting points further than this from the header stamp is
refused (a clock offset that large is a unit or reference mismatch)."""
UNDECIDED_CLOUDS = 5
"""Clouds on which detection cannot tell the time field's unit/reference (a driver's partial
first sweep) are skipped, up to this many; then it is an error."""
AMBIGUOUS_END_S = 1e-3
"""Relative and absolute readings of a cloud near the clock's zero (:func:`detect_time_spec`)
that put the header stamp within this of each other's sweep end are not told apart; a cloud
read either way then has its times within this of each other."""
TURN_RATE_INTERVALS = 10
"""Clouds without time field: after this many header-stamp intervals their rate is compared
with ``sensor.lidar_rate_hz`` once (:meth:`CloudDecoder._check_turn_rate`)."""
TURN_RATE_MISMATCH = 0.25
"""A cloud rate this far (relative) from the configured turn rate is a mismatch."""
FULL_TURN = 0.75
"""Clouds whose points sweep at least this fraction of a turn (median) are whole turns; split
sweeps (several clouds per turn) are left alone."""
INTENSITY_FIELDS: tuple[str, ...] = ("intensity", "reflectivity", "i")
RING_FIELDS: tuple[str, ...] = ("ring", "channel", "line", "laser_id")


def encode_pointcloud2(columns: dict[str, np.ndarray], layout: list[tuple[str, int, str]],
                       point_step: int, big_endian: bool = False
                       ) -> tuple[bytes, list[tuple[str, int, int, int]]]:
    """Pack per-point columns into PointCloud2 ``data`` bytes.

    ``layout`` lists ``(name, byte_offset, numpy_kind)`` with kinds from ``POINTFIELD_DTYPES``
    values (``"f4"``, ``"f8"``, ``"u2"``, ...). Bytes not covered by a field (padding) are zero.
    Returns ``(data, fields)`` where ``fields`` are ``(name, offset, datatype, count=1)`` tuples
    ready to become ``sensor_msgs/PointField`` messages.
    """
    n = len(next(iter(columns.values()))) if columns else 0
    order = ">" if big_endian else "<"
    dtype = np.dtype({"names": [f[0] for f in layout],
                      "formats": [order + f[2] for f in layout],
                      "offsets": [f[1] for f in layout],
                      "itemsize": point_step})
    arr = np.zeros(n, dtype=dtype)
    for name, _, _ in layout:
        arr[name] = columns[name]
    fields = [(name, off, DTYPE_TO_POINTFIELD[kind], 1) for name, off, kind in layout]
    return arr.tobytes(), fields


# ----------------------------------------------------------------------------- raw decoding
@dataclass(frozen=True)
class CloudLayout:
    """The binary layout of a PointCloud2 message (everything except the data)."""

    fields: tuple[tuple[str, int, int, int], ...]
    """(name, offset, datatype, count) as in sensor_msgs/PointField."""
    point_step: int
    width: int
    height: int
    row_step: int
    is_bigendian: bool

    @classmethod
    def from_msg(cls, msg: Any) -> CloudLayout:
        fields = tuple((str(f.name), int(f.offset), int(f.datatype), int(f.count))
                       for f in msg.fields)
        return cls(fields, int(msg.point_step), int(msg.width), int(msg.height),
                   int(msg.row_step), bool(msg.is_bigendian))

    def field_names(self) -> list[str]:
        return [f[0] for f in self.fields]

    def find(self, name: str) -> tuple[str, int, int, int] | None:
        for f in self.fields:
            if f[0] == name:
                return f
        return None


def decode_fields(data: Any, layout: CloudLayout, names: list[str],
                  topic: str = "") -> dict[str, np.ndarray]:
    """Decode the named fields of every point (organized clouds are flattened row by row).

    Returns native-endian 1-D arrays: read-only strided views into ``data`` where the cloud's
    byte order is the machine's (no copy), copies otherwise. Raises BagError for a field that is
    absent, has count != 1, an unknown datatype, lies outside ``point_step``, or for data
    shorter than the layout says.
    """
    where = f"PointCloud2 on {topic or '?'}"
    step = layout.point_step
    n_rows, width = layout.height, layout.width
    if step <= 0 or width < 0 or n_rows < 0:
        raise BagError(f"{where}: invalid layout (point_step={step}, width={width}, "
                       f"height={n_rows}); the message is corrupted")
    order = ">" if layout.is_bigendian else "<"
    fmts, offs = [], []
    for name in names:
        f = layout.find(name)
        if f is None:
            raise BagError(f"{where} has no field '{name}' (fields: "
                           f"{', '.join(layout.field_names()) or 'none'})")
        _, off, dt, count = f
        if dt not in POINTFIELD_DTYPES:
            raise BagError(f"{where}: field '{name}' has unknown datatype {dt}")
        if count != 1:
            raise BagError(f"{where}: field '{name}' has count {count}; only count 1 is "
                           "supported for coordinates and times")
        size = np.dtype(POINTFIELD_DTYPES[dt]).itemsize
        if off < 0 or off + size > step:
            raise BagError(f"{where}: field '{name}' (offset {off}, {size} bytes) lies outside "
                           f"point_step {step}; the message is corrupted")
        fmts.append(order + POINTFIELD_DTYPES[dt])
        offs.append(off)
    n_points = n_rows * width
    if n_points == 0:
        return {name: np.zeros(0, dtype=np.dtype(fmt).newbyteorder("=")) for name, fmt in
                zip(names, fmts, strict=True)}
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) \
        else np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    row_bytes = width * step
    row_step = max(layout.row_step, row_bytes)
    if n_rows > 1 and layout.row_step < row_bytes:
        raise BagError(f"{where}: row_step {layout.row_step} < width*point_step {row_bytes}; "
                       "the message is corrupted")
    need = (n_rows - 1) * row_step + row_bytes
    if buf.size < need:
        raise BagError(f"{where}: data has {buf.size} bytes but the layout needs {need} "
                       f"({n_rows}x{width} points of {step} bytes); the message is truncated")
    if row_step == row_bytes:
        block = buf[: n_points * step]
    else:  # each row's points, read in place: the padding is never copied (the last row's
        # may be left out, and a corrupted row_step must not size an allocation)
        rows = np.lib.stride_tricks.as_strided(buf, shape=(n_rows, row_bytes),
                                               strides=(row_step, 1), writeable=False)
        block = np.ascontiguousarray(rows).reshape(-1)
    out: dict[str, np.ndarray] = {}
    if block.flags.writeable:  # a view of the message's own buffer is never written through
        block = block.view()
        block.flags.writeable = False
    for name, fmt, off in zip(names, fmts, offs, strict=True):
        dtype = np.dtype({"names": ["v"], "formats": [fmt], "offsets": [off], "itemsize": step})
        col = block.view(dtype)["v"]
        # a copy of each column took 0.2 ms per 63k-point cloud, six of them a third of decoding
        out[name] = col if col.dtype.isnative else col.astype(col.dtype.newbyteorder("="))
    return out


@kernel()
def _xyz_rows(x, y, z):
    """(N,3) float64 points from the x/y/z columns in one pass, and which rows are usable:
    ``ok`` is False for a non-finite coordinate or for (0,0,0) ("no return" on many drivers).
    Returns ``(points, ok, n_nonfinite, n_zero)``."""
    n = x.shape[0]
    pts = np.empty((n, 3))
    ok = np.empty(n, np.bool_)
    n_nonfinite = 0
    n_zero = 0
    for i in range(n):
        a = float(x[i])
        b = float(y[i])
        c = float(z[i])
        pts[i, 0] = a
        pts[i, 1] = b
        pts[i, 2] = c
        if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(c)):
            ok[i] = False
            n_nonfinite += 1
        elif a == 0.0 and b == 0.0 and c == 0.0:
            ok[i] = False
            n_zero += 1
        else:
            ok[i] = True
    return pts, ok, n_nonfinite, n_zero


# ----------------------------------------------------------------------------- time handling
@dataclass(frozen=True)
class TimeSpec:
    """How per-point times are read: field (None = azimuth reconstruction), unit, reference."""

    field: str | None
    unit: str = "s"
    reference: str = "relative"
    detected: bool = True
    """False when every part came from the config."""
    ambiguous: bool = False
    """Detected on a cloud whose header stamp lies so near the clock's zero (a simulator's
    clock) that its times read as relative and as absolute both fit; :class:`CloudDecoder`
    then detects again on the next cloud, until one tells them apart."""

    def describe(self) -> str:
        if self.field is None:
            return "none (spread over the frame in firing order)" \
                if self.reference == "firing order" else "none (reconstructed from azimuth)"
        how = "detected" if self.detected else "from config"
        return f"'{self.field}' in {self.unit}, {self.reference} ({how})"


def _is_float(dt: int) -> bool:
    return dt in (7, 8)


def pick_time_field(layout: CloudLayout, sensor: SensorConfig, topic: str = "") -> str | None:
    """The configured or detected time field name, or None (no time field)."""
    want = sensor.point_time_field
    names = layout.field_names()
    if want == "none":
        return None
    if want != "auto":
        if want not in names:
            raise BagError(f"PointCloud2 on {topic or '?'} has no field '{want}' "
                           f"(sensor.point_time_field); fields: {', '.join(names)}")
        return want
    lower = {n.lower(): n for n in names}
    for cand in TIME_FIELD_CANDIDATES:
        if cand in lower:
            return lower[cand]
    return None


def detect_time_spec(values: np.ndarray, datatype: int, field: str, stamp_ns: int,
                     sensor: SensorConfig, topic: str = "") -> TimeSpec:
    """Choose unit and reference of raw time ``values`` (one cloud) against the header stamp.

    Hypotheses (unit, reference) are kept when the implied offsets from the header stamp lie
    within two sweeps (sweep = 1/lidar_rate_hz) and their span is between MIN_SPAN_SWEEPS (when
    the cloud has at least MIN_POINTS_FOR_SPAN points) and 2.5 sweeps; the one
    whose span is closest to one sweep (log ratio) wins, floats preferring s and integers ns on
    ties. Where both references fit the winning unit (a header stamp within a few sweeps of the
    clock's zero), the one that puts the header stamp nearer an end of the sweep wins (a driver
    stamps a sweep's start or end), relative when that does not tell them apart either; the
    spec is then marked ``ambiguous``. A header stamp of 0 is one a driver never set: it
    anchors nothing, so only the span tells the unit (read relative to 0 or as absolute, the
    times are then the same).
    """
    units = [sensor.point_time_unit] if sensor.point_time_unit != "auto" else list(UNIT_TO_NS)
    refs = [sensor.point_time_reference] if sensor.point_time_reference != "auto" \
        else ["relative", "absolute"]
    if len(units) == 1 and len(refs) == 1:
        return TimeSpec(field, units[0], refs[0], detected=False)
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    where = f"PointCloud2 on {topic or '?'}: time field '{field}'"
    if v.size == 0:
        unit = units[0] if len(units) == 1 else ("s" if _is_float(datatype) else "ns")
        return TimeSpec(field, unit, refs[0])
    sweep_s = 1.0 / max(sensor.lidar_rate_hz, 1e-3)
    stamp_s = stamp_ns * 1e-9
    vmin, vmax = float(v.min()), float(v.max())
    preferred = "s" if _is_float(datatype) else "ns"
    best: tuple[float, str, str] | None = None
    ends: dict[tuple[str, str], float] = {}
    for unit in units:
        scale = UNIT_TO_NS[unit] * 1e-9
        span_s = (vmax - vmin) * scale
        if span_s > 2.5 * sweep_s or (v.size >= MIN_POINTS_FOR_SPAN
                                       and span_s < MIN_SPAN_SWEEPS * sweep_s):
            continue
        for ref in refs:
            base = stamp_s if ref == "absolute" else 0.0
            lo, hi = vmin * scale - base, vmax * scale - base
            if stamp_ns != 0 and (lo < -2.0 * sweep_s or hi > 2.0 * sweep_s):
                continue
            ends[unit, ref] = min(abs(lo), abs(hi))
            score = abs(np.log(max(span_s, 1e-12) / sweep_s))
            score += 0.0 if unit == preferred else 1e-3
            score += 0.0 if ref == "relative" else 1e-4
            if best is None or score < best[0]:
                best = (score, unit, ref)
    if best is None:
        raise BagError(f"{where}: cannot tell its unit/reference (values {vmin:.6g}..{vmax:.6g}, "
                       f"header stamp {stamp_s:.9f} s); set sensor.point_time_unit and "
                       "sensor.point_time_reference")
    unit, ref = best[1], best[2]
    if (unit, "relative") in ends and (unit, "absolute") in ends:
        rel, ab = ends[unit, "relative"], ends[unit, "absolute"]
        if abs(rel - ab) > AMBIGUOUS_END_S:
            ref = "relative" if rel < ab else "absolute"
        return TimeSpec(field, unit, ref, ambiguous=True)
    return TimeSpec(field, unit, ref)


def times_to_ns(values: np.ndarray, spec: TimeSpec, stamp_ns: int) -> np.ndarray:
    """Absolute int64 ns from raw time values (non-finite values become int64 min)."""
    scale = UNIT_TO_NS[spec.unit]
    base = 0 if spec.reference == "absolute" else int(stamp_ns)
    if values.dtype.kind in "iu":
        return values.astype(np.int64) * np.int64(scale) + np.int64(base)
    v = values.astype(np.float64)  # a copy, worked on in place
    bad = ~np.isfinite(v)
    limit = 9.2e18 / scale
    bad |= np.abs(v) > limit
    any_bad = bool(bad.any())
    if any_bad:
        v[bad] = 0.0
    whole = np.floor(v)
    frac = np.subtract(v, whole, out=v)
    frac *= scale
    out = whole.astype(np.int64)
    out *= np.int64(scale)
    out += np.rint(frac, out=frac).astype(np.int64)
    out += np.int64(base)
    if any_bad:
        out[bad] = np.iinfo(np.int64).min
    return out


def azimuth_times_ns(points: np.ndarray, stamp_ns: int, lidar_rate_hz: float) -> np.ndarray:
    """Per-point times of a clockwise spinning LiDAR from the azimuth atan2(y, x).

    The first point is at the header stamp; time grows with the clockwise angle swept from it,
    one full turn = 1 / lidar_rate_hz.
    """
    if points.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    az = np.arctan2(points[:, 1], points[:, 0])
    swept = np.mod(az[0] - az, 2.0 * np.pi)
    sweep_ns = 1e9 / max(lidar_rate_hz, 1e-3)
    return np.int64(stamp_ns) + np.rint(swept / (2.0 * np.pi) * sweep_ns).astype(np.int64)


def firing_order_times_ns(n: int, stamp_ns: int, lidar_rate_hz: float) -> np.ndarray:
    """Per-point times of a LiDAR that fires at a constant rate and sends its points in firing
    order (Livox): point ``i`` of ``n`` at ``stamp + i / n`` of one frame (``1 /
    lidar_rate_hz``)."""
    frame_ns = 1e9 / max(lidar_rate_hz, 1e-3)
    return np.int64(stamp_ns) + np.rint(np.arange(n) * (frame_ns / max(n, 1))).astype(np.int64)


LIVOX_FIELDS = ("tag", "line")
"""A PointCloud2 with both fields is a Livox driver's (``livox_ros_driver``'s has no time field:
its points come in firing order, not azimuth order)."""


def stamp_to_ns(stamp: Any) -> int:
    """int64 ns of a builtin_interfaces/Time or ROS1 time (``sec``, ``nanosec``)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def check_time_spec(values: np.ndarray, datatype: int, spec: TimeSpec, stamp_ns: int,
                    sensor: SensorConfig, topic: str = "") -> None:
    """BagError if a configured unit/reference makes the raw times of one cloud implausible:
    spanning more than MAX_SPAN_SWEEPS sweeps, or under CONFIGURED_MIN_SPAN_SWEEPS of one (a
    cloud of CONFIGURED_MIN_SPAN_POINTS or more), or further than MAX_STAMP_OFFSET_S from the
    header stamp (or beyond int64 ns). The message names the field, the configured unit and, if
    detection finds one, the unit the values look like."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return
    sweep_s = 1.0 / max(sensor.lidar_rate_hz, 1e-3)
    scale = UNIT_TO_NS[spec.unit] * 1e-9
    base = stamp_ns * 1e-9 if spec.reference == "absolute" else 0.0
    vmin, vmax = float(v.min()), float(v.max())
    span_s = (vmax - vmin) * scale
    lo, hi = vmin * scale - base, vmax * scale - base
    if span_s > MAX_SPAN_SWEEPS * sweep_s:
        what = f"one cloud spanning {span_s:.4g} s ({sensor.lidar_rate_hz:g} Hz LiDAR)"
    elif 0.0 < span_s < CONFIGURED_MIN_SPAN_SWEEPS * sweep_s and \
            v.size >= CONFIGURED_MIN_SPAN_POINTS:
        what = (f"one cloud of {v.size} points spanning {span_s:.3g} s, a sliver of a "
                f"{sweep_s:.3g} s sweep ({sensor.lidar_rate_hz:g} Hz LiDAR)")
    elif (stamp_ns != 0 and max(abs(lo), abs(hi)) > MAX_STAMP_OFFSET_S) or \
            max(abs(vmin), abs(vmax)) * UNIT_TO_NS[spec.unit] > 9.2e18:  # stamp 0: never set
        what = f"points {lo:.4g}..{hi:.4g} s away from the header stamp"
    else:
        return
    guess = ""
    try:
        auto = dataclasses.replace(sensor, point_time_unit="auto", point_time_reference="auto")
        found = detect_time_spec(v, datatype, spec.field or "", stamp_ns, auto, topic)
        if (found.unit, found.reference) != (spec.unit, spec.reference):
            guess = f"; the values look like {found.unit}, {found.reference}"
    except BagError:
        pass
    raise BagError(f"PointCloud2 on {topic or '?'}: time field '{spec.field}' read as "
                   f"{spec.unit}, {spec.reference} (sensor.point_time_unit / "
                   f"point_time_reference) gives {what}: the unit or reference is likely wrong"
                   f"{guess}; set sensor.point_time_unit and sensor.point_time_reference "
                   "(or 'auto')")


@dataclass
class DecodeStats:
    """Points seen and dropped by a :class:`CloudDecoder` (all clouds so far)."""

    clouds: int = 0
    clouds_without_points: int = 0
    """Clouds whose message holds no point at all (width x height = 0)."""
    points: int = 0
    nonfinite: int = 0
    """Points dropped for a NaN/inf coordinate."""
    zero: int = 0
    """Points dropped for being exactly (0, 0, 0)."""
    bad_time: int = 0
    """Points dropped for a NaN/inf or out-of-range time."""
    kept: int = 0

    def add(self, n: int, nonfinite: int, zero: int, bad_time: int, kept: int) -> None:
        self.clouds += 1
        self.clouds_without_points += int(n == 0)
        self.points += n
        self.nonfinite += nonfinite
        self.zero += zero
        self.bad_time += bad_time
        self.kept += kept

    def why_empty(self) -> str:
        """What the dropped points were, for the 'all clouds empty' error."""
        parts = [f"{n} {what}" for n, what in (
            (self.clouds_without_points, "clouds hold no points at all"),
            (self.nonfinite, "points have a NaN/inf coordinate"),
            (self.zero, "points are exactly (0, 0, 0), a driver's 'no return'"),
            (self.bad_time, "points have an invalid time (sensor.point_time_*)")) if n]
        return "; ".join(parts)


# ----------------------------------------------------------------------------- decoder
class CloudDecoder:
    """Decode PointCloud2 messages of one topic into :class:`Scan` objects.

    The time spec is detected on the first non-empty cloud and reused (``self.time_spec``).
    """

    def __init__(self, sensor: SensorConfig | None = None, topic: str = "") -> None:
        self.sensor = sensor or SensorConfig()
        self.topic = topic
        self.time_spec: TimeSpec | None = None
        self._warned_azimuth = False
        self._turn_hz = float(self.sensor.lidar_rate_hz)
        """The turn rate the azimuth times use (``sensor.lidar_rate_hz``, or the measured one)."""
        self._turn_stamps: list[int] = []
        self._turn_covers: list[float] = []
        self._turn_checked = False
        self._constant_fields: set[str] = set()
        self._spec_checked = False
        self._ambiguous_reads: list[tuple[str, int]] = []
        """(reference, header stamp ns) of each cloud read with an ambiguous detection where
        the two readings differ (a header stamp further than AMBIGUOUS_END_S from 0)."""
        self._undecided = 0
        """Clouds skipped so far because detection could not tell their times' unit."""
        self.stats = DecodeStats()

    def decode(self, msg: Any) -> Scan:
        """One message → Scan (may have 0 points). Raises BagError on unusable layouts."""
        where = f"PointCloud2 on {self.topic or '?'}"
        try:
            stamp_ns = stamp_to_ns(msg.header.stamp)
            layout = CloudLayout.from_msg(msg)
        except (TypeError, ValueError, OverflowError):
            raise BagError(f"{where}: header or field list is malformed (stamp, offsets, "
                           "datatypes, sizes must be integers); the message is corrupted") \
                from None
        return self.decode_raw(msg.data, layout, stamp_ns)

    def decode_raw(self, data: Any, layout: CloudLayout, stamp_ns: int) -> Scan:
        """Decode raw ``data`` laid out as ``layout`` (see :meth:`decode`)."""
        if not INT64_MIN_NS <= int(stamp_ns) <= INT64_MAX_NS:
            raise BagError(f"PointCloud2 on {self.topic or '?'}: header stamp {stamp_ns} ns is "
                           "out of range; the message is corrupted")
        names = layout.field_names()
        missing = [c for c in ("x", "y", "z") if c not in names]
        if missing:
            raise BagError(f"PointCloud2 on {self.topic or '?'} has no {'/'.join(missing)} field "
                           f"(fields: {', '.join(names) or 'none'}); pick the right lidar topic "
                           "(--lidar-topic)")
        tfield = pick_time_field(layout, self.sensor, self.topic)
        want = ["x", "y", "z"] + ([tfield] if tfield else [])
        extras = {}
        for group, key in ((INTENSITY_FIELDS, "intensity"), (RING_FIELDS, "ring")):
            for name in group:
                f = layout.find(name)
                if f is not None and f[3] == 1 and f[2] in POINTFIELD_DTYPES \
                        and 0 <= f[1] and f[1] + np.dtype(POINTFIELD_DTYPES[f[2]]).itemsize \
                        <= layout.point_step and name not in want:
                    extras[key] = name
                    break
        cols = decode_fields(data, layout, want + list(extras.values()), self.topic)
        pts, ok, n_nonfinite, n_zero = _xyz_rows(cols["x"], cols["y"], cols["z"])
        n_xyz_ok = int(pts.shape[0]) - n_nonfinite - n_zero
        t_ns = None
        if tfield is not None and tfield not in self._constant_fields:
            raw_t = cols[tfield]
            if (self.time_spec is None or self.time_spec.field != tfield
                    or self.time_spec.ambiguous):
                finite = raw_t[ok & np.isfinite(raw_t)] if raw_t.dtype.kind == "f" else raw_t
                if (self.sensor.point_time_field == "auto" and finite.size >= MIN_POINTS_FOR_SPAN
                        and finite.min() == finite.max()):
                    self._constant_fields.add(tfield)
                elif finite.size:
                    try:
                        spec = detect_time_spec(finite, layout.find(tfield)[2], tfield,
                                                stamp_ns, self.sensor, self.topic)
                    except BagError:
                        if self.time_spec is not None and self.time_spec.field == tfield:
                            spec = self.time_spec  # ambiguous so far: this cloud tells nothing
                        else:
                            spec = None
                            self._undecided += 1
                            if self._undecided >= UNDECIDED_CLOUDS:
                                raise
                    if spec is None:
                        warnings.warn(f"PointCloud2 on {self.topic or '?'}: cannot tell the "
                                      f"unit of time field '{tfield}' on the cloud stamped "
                                      f"{stamp_ns * 1e-9:.3f} s ({finite.size} points; a partial "
                                      "sweep?): skipped, detecting on the next", stacklevel=2)
                        self.stats.add(int(pts.shape[0]), 0, 0, int(pts.shape[0]), 0)
                        return Scan(points_lidar=pts[:0], t_ns=np.zeros(0, np.int64),
                                    stamp_ns=int(stamp_ns))
                    if spec is not self.time_spec:
                        self.time_spec = spec
                        self._settle_reference(spec, int(stamp_ns))
            if tfield not in self._constant_fields:
                spec = self.time_spec
                if spec is None:
                    t_ns = np.zeros(pts.shape[0], dtype=np.int64)
                else:
                    if not self._spec_checked and not spec.detected and ok.any():
                        self._spec_checked = True
                        check_time_spec(raw_t[ok], layout.find(tfield)[2], spec, stamp_ns,
                                        self.sensor, self.topic)
                    t_ns = times_to_ns(raw_t, spec, stamp_ns)
                    ok &= t_ns != np.iinfo(np.int64).min
        livox = all(f in names for f in LIVOX_FIELDS)
        if t_ns is None:
            if self.time_spec is None or self.time_spec.field is not None:
                self.time_spec = TimeSpec(None, "ns", "firing order" if livox else "relative",
                                          detected=self.sensor.point_time_field == "auto")
            if not self._warned_azimuth:
                self._warned_azimuth = True
                why = f"its time field '{tfield}' is constant" if tfield else \
                    "it has no per-point time field"
                how = ("spread over the frame in the points' order (a Livox driver's cloud, "
                       "fields tag and line: a constant firing rate, no azimuth order)"
                       if livox else "reconstructed from azimuth")
                warnings.warn(f"PointCloud2 on {self.topic or '?'}: {why}; times {how} at "
                              f"{self.sensor.lidar_rate_hz} Hz (set sensor.point_time_field if "
                              "it has one)", stacklevel=2)
        n_total = int(pts.shape[0])
        if not ok.all():  # np.compress: numpy's boolean index of an (N, 3) array took 4x as long
            pts = np.compress(ok, pts, axis=0)
        self.stats.add(n_total, n_nonfinite, n_zero, n_xyz_ok - int(pts.shape[0]),
                       int(pts.shape[0]))
        if t_ns is None:
            t_ns = firing_order_times_ns(n_total, stamp_ns, self._turn_hz)[ok] if livox \
                else azimuth_times_ns(pts, stamp_ns, self._turn_hz)
            self._check_turn_rate(t_ns, int(stamp_ns), livox)
        else:
            t_ns = t_ns[ok]
        intensity = cols[extras["intensity"]][ok].astype(np.float32) if "intensity" in extras \
            else None
        ring = line = None
        if "ring" in extras and cols[extras["ring"]].dtype.kind in "iu":
            r = cols[extras["ring"]][ok]
            if not livox:
                ring = np.clip(r, 0, 65535).astype(np.uint16)
            elif extras["ring"] == "line":
                # a Livox 'line' is a laser of its pattern, no ring: only the stray test reads it
                line = np.clip(r, 0, 255).astype(np.uint8)
        return Scan(points_lidar=pts, t_ns=t_ns, stamp_ns=int(stamp_ns), intensity=intensity,
                    ring=ring, line=line)

    def _settle_reference(self, spec: TimeSpec, stamp_ns: int) -> None:
        """Near the clock's zero each cloud is read with the reference detected on it
        (:attr:`TimeSpec.ambiguous`). A BagError if the first cloud that tells relative from
        absolute apart contradicts how an earlier one was read where the two readings differ
        by more than :data:`AMBIGUOUS_END_S` (they differ by the header stamp)."""
        if spec.ambiguous:
            if abs(stamp_ns) * 1e-9 > AMBIGUOUS_END_S:  # stamps of 0 read alike both ways
                self._ambiguous_reads.append((spec.reference, stamp_ns))
            return
        wrong = [t for ref, t in self._ambiguous_reads if ref != spec.reference]
        self._ambiguous_reads = []
        if wrong:
            raise BagError(
                f"PointCloud2 on {self.topic or '?'}: time field '{spec.field}' reads as "
                f"{spec.unit}, {spec.reference} from the cloud stamped {stamp_ns * 1e-9:.3f} s "
                f"on, but the cloud stamped {wrong[0] * 1e-9:.3f} s, near the clock's zero where "
                "relative and absolute times look alike, was read the other way; set "
                f"sensor.point_time_reference: {spec.reference}")

    def _check_turn_rate(self, t_ns: np.ndarray, stamp_ns: int, livox: bool = False) -> None:
        """Azimuth times assume one turn per ``1 / sensor.lidar_rate_hz``, and a Livox cloud's
        firing-order times one frame per it (``livox``). Once, after
        :data:`TURN_RATE_INTERVALS` clouds: if each cloud is a whole turn (its points sweep at
        least :data:`FULL_TURN` of it) and they come at a rate more than
        :data:`TURN_RATE_MISMATCH` off the configured one, warn. Clouds coming faster than the
        head turns cannot each be a whole turn, so then the measured rate (the median of the
        header-stamp intervals) is used from here on (the clouds before keep the configured
        one); clouds coming slower may be a recording throttled to fewer clouds, so the
        configured rate stays."""
        if self._turn_checked:
            return
        if t_ns.size:
            sweep_ns = 1e9 / max(self._turn_hz, 1e-3)
            self._turn_covers.append(float(t_ns.max() - stamp_ns) / sweep_ns)
        if not self._turn_stamps or stamp_ns > self._turn_stamps[-1]:
            self._turn_stamps.append(stamp_ns)
        if len(self._turn_stamps) <= TURN_RATE_INTERVALS or not self._turn_covers:
            return
        self._turn_checked = True
        cloud_hz = 1e9 / float(np.median(np.diff(self._turn_stamps)))
        cfg_hz = float(self.sensor.lidar_rate_hz)
        if (float(np.median(self._turn_covers)) < FULL_TURN
                or abs(cloud_hz / cfg_hz - 1.0) <= TURN_RATE_MISMATCH):
            return
        whole, times = (("a whole frame", "the times spread over the frame in firing order")
                        if livox else ("a whole turn", "the times reconstructed from azimuth"))
        seen = (f"PointCloud2 on {self.topic or '?'}: its clouds come at {cloud_hz:.1f} Hz, "
                f"each {whole}, but sensor.lidar_rate_hz is {cfg_hz:g}: ")
        if cloud_hz > cfg_hz:
            self._turn_hz = cloud_hz
            warnings.warn(f"{seen}{times} at {cloud_hz:.1f} Hz from here on (set "
                          f"sensor.lidar_rate_hz: {cloud_hz:.3g})", stacklevel=3)
        else:
            warnings.warn(f"{seen}{times} take {'a frame' if livox else 'a turn'} as "
                          f"{1e3 / cfg_hz:.0f} ms; set sensor.lidar_rate_hz: {cloud_hz:.3g} if "
                          f"the {'LiDAR frames' if livox else 'head turns'} at that rate (keep "
                          "it for a recording throttled to fewer clouds)", stacklevel=3)


def decode_pointcloud2(msg: Any, sensor: SensorConfig | None = None, topic: str = "") -> Scan:
    """Decode one PointCloud2 message (time spec detected on this message alone)."""
    return CloudDecoder(sensor, topic).decode(msg)
