"""Livox CustomMsg input: the numpy (de)serialization against rosbags' own, the decoder's times
and drops, and a run on a bag of CustomMsgs against the same sweeps as PointCloud2."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from bagfactory import msg_from

from adalio.config import SensorConfig, load_config
from adalio.errors import BagError
from adalio.io.bag import Bag, ros1_typestore, ros2_typestore
from adalio.io.bagwrite import BagWriter
from adalio.io.livox import (
    LivoxCloud,
    LivoxDecoder,
    build_custom_msg,
    is_livox_type,
    lidar_decoder,
    livox_points,
    parse_custom_msg,
)
from adalio.io.pointcloud2 import CloudDecoder
from adalio.io.sequencer import imu_msg_arrays


def random_cloud(rng, n: int, frame: str) -> LivoxCloud:
    xyz = rng.normal(0, 10, (n, 3)).astype(np.float32)
    pts = livox_points(rng.integers(0, 100_000_000, n), xyz, rng.integers(0, 256, n),
                       rng.integers(0, 256, n), rng.integers(0, 4, n))
    t = int(rng.integers(0, 2**31 - 1)) * 1_000_000_000 + int(rng.integers(0, 10**9))
    return LivoxCloud(stamp_ns=t, frame_id=frame, timebase_ns=t + int(rng.integers(0, 10**6)),
                      points=pts, lidar_id=int(rng.integers(0, 256)))


def rosbags_message(store, msgtype: str, cloud: LivoxCloud, ros1: bool):
    """The same message built from rosbags' own types (one Python object per point)."""
    T = store.types
    pkg = msgtype.split("/")[0]
    P = T[f"{pkg}/msg/CustomPoint"]
    p = cloud.points
    pts = [P(offset_time=int(p["offset_time"][i]), x=float(p["x"][i]), y=float(p["y"][i]),
             z=float(p["z"][i]), reflectivity=int(p["reflectivity"][i]), tag=int(p["tag"][i]),
             line=int(p["line"][i])) for i in range(len(p))]
    sec, nsec = divmod(cloud.stamp_ns, 1_000_000_000)
    stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    hdr = T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=cloud.frame_id) if ros1 \
        else T["std_msgs/msg/Header"](stamp=stamp, frame_id=cloud.frame_id)
    return T[msgtype](header=hdr, timebase=cloud.timebase_ns, point_num=len(p),
                      lidar_id=cloud.lidar_id, rsvd=np.zeros(3, np.uint8), points=pts)


@pytest.mark.parametrize("ros1", [True, False])
@pytest.mark.parametrize("msgtype", ["livox_ros_driver/msg/CustomMsg",
                                     "livox_ros_driver2/msg/CustomMsg"])
def test_serialized_bytes_are_rosbags_own(ros1, msgtype):
    """build_custom_msg gives byte for byte what rosbags serializes, and parse_custom_msg reads
    back every field, for frame ids of every CDR padding (lengths 0-8) and 0, 1 and 7
    points."""
    store = ros1_typestore() if ros1 else ros2_typestore()
    rng = np.random.default_rng(1)
    for n in (0, 1, 7):
        for k in range(9):
            cloud = random_cloud(rng, n, "f" * k)
            msg = rosbags_message(store, msgtype, cloud, ros1)
            want = bytes(store.serialize_ros1(msg, msgtype) if ros1
                         else store.serialize_cdr(msg, msgtype))
            assert build_custom_msg(cloud, ros2=not ros1) == want
            back = parse_custom_msg(want, ros2=not ros1)
            assert (back.stamp_ns, back.frame_id, back.timebase_ns, back.lidar_id,
                    back.point_num) == (cloud.stamp_ns, cloud.frame_id, cloud.timebase_ns,
                                        cloud.lidar_id, n)
            for name in cloud.points.dtype.names:
                np.testing.assert_array_equal(back.points[name], cloud.points[name])
            # rosbags reads the bytes adalio wrote to the same message
            read = store.deserialize_ros1(want, msgtype) if ros1 \
                else store.deserialize_cdr(want, msgtype)
            assert [p.offset_time for p in read.points] == cloud.points["offset_time"].tolist()


def test_truncated_bytes_are_refused():
    cloud = random_cloud(np.random.default_rng(2), 50, "livox_frame")
    for ros2 in (False, True):
        raw = build_custom_msg(cloud, ros2=ros2)
        with pytest.raises(ValueError):
            parse_custom_msg(raw[:-30], ros2=ros2)


def test_decoder_times_and_drops():
    """Absolute times are timebase + offset_time; NaN, (0, 0, 0) and third-or-later-return
    points (tag bits 4-5 = 2, 3) are dropped and counted, first and second returns kept; no
    rings (a line is a laser of the pattern): the lines are kept as ``Scan.line``."""
    rng = np.random.default_rng(3)
    n = 400
    xyz = rng.uniform(-20, 20, (n, 3)).astype(np.float32)
    xyz[:10] = np.nan
    xyz[10:25] = 0.0
    tag = rng.integers(0, 256, n).astype(np.uint8)
    pts = livox_points(rng.integers(0, 100_000_000, n), xyz, rng.integers(0, 256, n), tag,
                       rng.integers(0, 4, n))
    base = 1_700_000_000_123_456_789
    dec = LivoxDecoder(SensorConfig(), "/livox/lidar")
    scan = dec.decode(LivoxCloud(stamp_ns=base, frame_id="livox_frame", timebase_ns=base,
                                 points=pts))
    ret = (tag >> 4) & 3
    keep = np.isfinite(xyz).all(axis=1) & xyz.any(axis=1) & (ret <= 1)
    assert len(scan) == keep.sum() and 0 < keep.sum() < n - 25
    np.testing.assert_array_equal(scan.t_ns, base + pts["offset_time"][keep].astype(np.int64))
    np.testing.assert_array_equal(scan.points_lidar, xyz[keep].astype(np.float64))
    assert scan.ring is None  # each point's laser is kept apart, for the stray test
    np.testing.assert_array_equal(scan.line, pts["line"][keep])
    st = dec.stats
    assert (st.nonfinite, st.zero, st.later_return, st.kept) == \
        (10, 15, int(((ret >= 2) & np.isfinite(xyz).all(axis=1) & xyz.any(axis=1)).sum()),
         int(keep.sum()))
    assert "third or later return" in st.why_empty()
    assert "Livox CustomMsg" in dec.time_spec.describe()


def test_decoder_takes_rosbags_messages_too():
    """A message deserialized by rosbags (one object per point) decodes as the LivoxCloud
    parsed from the same bytes."""
    store = ros2_typestore()
    cloud = random_cloud(np.random.default_rng(4), 30, "livox_frame")
    raw = build_custom_msg(cloud, ros2=True)
    a = LivoxDecoder().decode(store.deserialize_cdr(raw, "livox_ros_driver2/msg/CustomMsg"))
    b = LivoxDecoder().decode(parse_custom_msg(raw, ros2=True))
    np.testing.assert_array_equal(a.points_lidar, b.points_lidar)
    np.testing.assert_array_equal(a.t_ns, b.t_ns)
    assert a.stamp_ns == b.stamp_ns == cloud.stamp_ns


def test_types():
    assert is_livox_type("livox_ros_driver/CustomMsg")
    assert is_livox_type("livox_ros_driver2/msg/CustomMsg")
    assert not is_livox_type("sensor_msgs/msg/PointCloud2")
    assert isinstance(lidar_decoder("livox_ros_driver/msg/CustomMsg"), LivoxDecoder)
    assert isinstance(lidar_decoder("sensor_msgs/msg/PointCloud2"), CloudDecoder)


# ----------------------------------------------------------------------------- a run
@pytest.fixture(scope="module")
def hall(tmp_path_factory):
    from adalio import simulate

    return simulate("hall", tmp_path_factory.mktemp("livox_hall"), seed=3, duration_s=5,
                    columns=256)


def as_livox(seq, out, fmt: str, junk: bool) -> tuple[object, int]:
    """The sequence's bag with its LiDAR rewritten as Livox CustomMsgs on /livox/lidar: the
    PointCloud2 decoder's points and times as offset_time after the sweep's first point, the
    header stamp kept; the IMU and receive times as they were. With ``junk``, each cloud also
    gets points the decoder must drop (NaN, zero, a third return) among its own, whose order
    stays."""
    cfg = load_config(config_file=seq.config_path)
    rng = np.random.default_rng(5)
    n_clouds = 0
    with Bag(seq.bag_path) as bag, BagWriter(out, fmt) as w:
        lidar, imu = bag.select_topics(cfg.sensor)
        dec = CloudDecoder(cfg.sensor, lidar)
        for topic, t_recv, msg in bag.messages([lidar, imu]):
            if topic == imu:
                b = imu_msg_arrays([msg])
                w.add_imu("/livox/imu", int(b.t_ns[0]), b.gyro_rad_s[0], b.accel_m_s2[0],
                          frame_id="livox_frame", t_recv_ns=t_recv)
                continue
            scan = dec.decode(msg)
            base = int(scan.t_ns.min())
            pts = livox_points(scan.t_ns - base, scan.points_lidar.astype(np.float32),
                               line=scan.ring)
            if junk:
                bad = livox_points(rng.integers(0, 10**8, 9), rng.normal(0, 5, (9, 3)),
                                   tag=np.full(9, 0x20))
                bad["x"][:3] = np.nan
                bad["x"][3:6] = bad["y"][3:6] = bad["z"][3:6] = 0.0
                pts = np.insert(pts, np.sort(rng.integers(0, len(pts) + 1, 9)), bad)
            w.add_livox("/livox/lidar", LivoxCloud(stamp_ns=scan.stamp_ns,
                                                   frame_id="livox_frame", timebase_ns=base,
                                                   points=pts), t_recv_ns=t_recv)
            n_clouds += 1
    return cfg, n_clouds


@pytest.mark.parametrize("fmt", ["ros1", "mcap_file"])
def test_a_run_on_custommsg_is_the_run_on_pointcloud2(hall, tmp_path, fmt):
    """The same sweeps as CustomMsgs (with junk points to drop) and as the simulator's
    PointCloud2: the topic is found without being named, and the trajectories are identical
    to the bit; the trajectory is the simulated walk's (ATE < 2 cm)."""
    from adalio.eval.metrics import ate
    from adalio.pipeline import run_bag

    path = tmp_path / ("livox.bag" if fmt == "ros1" else "livox.mcap")
    cfg, n_clouds = as_livox(hall, path, fmt, junk=True)
    with Bag(path) as bag:
        assert bag.select_topics(SensorConfig()) == ("/livox/lidar", "/livox/imu")
    cfg_livox = load_config(config_file=hall.config_path,
                            overrides={"sensor.lidar_topic": "", "sensor.imu_topic": ""})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = run_bag(hall.bag_path, cfg, tmp_path / "pc2", progress=False)
        got = run_bag(path, cfg_livox, tmp_path / "livox", progress=False)
    assert got.n_scans_in == n_clouds == ref.n_scans_in
    assert got.trajectory_path.read_text() == ref.trajectory_path.read_text()
    assert "Livox CustomMsg" in got.time_spec
    assert ate(got.trajectory_path, hall.gt_path)["rmse_m"] < 0.02


def test_info_reads_a_livox_bag(hall, tmp_path):
    from typer.testing import CliRunner

    from adalio.cli import app

    path = tmp_path / "livox.bag"
    as_livox(hall, path, "ros1", junk=False)
    res = CliRunner().invoke(app, ["info", str(path)])
    assert res.exit_code == 0, res.output
    for text in ("livox_ros_driver/msg/CustomMsg", "would use: lidar /livox/lidar",
                 "Livox CustomMsg: offset_time", "after the message's timebase",
                 "stray returns (5 sampled): mean"):  # read along each laser (Scan.line)
        assert text in res.output, res.output


def test_a_corrupted_custommsg_is_one_error(hall, tmp_path):
    """A CustomMsg whose points run past its bytes: a BagError naming the bag, not a numpy
    traceback."""
    path = tmp_path / "bad.bag"
    cloud = random_cloud(np.random.default_rng(6), 20, "livox_frame")
    with BagWriter(path, "ros1") as w:
        conn = w._conn("/livox/lidar", "livox_ros_driver/msg/CustomMsg")
        w._writer.write(conn, cloud.stamp_ns, build_custom_msg(cloud, ros2=False)[:-40])
    with Bag(path) as bag, pytest.raises(BagError, match="cannot read bag .*bad.bag"):
        list(bag.messages(["/livox/lidar"]))


# ----------------------------------------------------------------------------- Livox PointCloud2
def livox_pc2(rng, n: int, base: int, with_time: bool):
    """A Livox driver's PointCloud2 of a forward-looking non-repetitive scan (an Avia-like
    70 deg field of view, azimuth not in time order), points in firing order at a constant
    rate over 100 ms: livox_ros_driver2's 26-byte packed layout with ``timestamp`` (float64,
    absolute ns), or livox_ros_driver's without a time field."""
    t = base + np.rint(np.arange(n) * (1e8 / n)).astype(np.int64)
    k = np.arange(n)
    az = np.deg2rad(35.0) * np.sin(k * 0.7311)  # a rosette's sweep across the view
    el = np.deg2rad(35.0) * np.sin(k * 0.5117 + 1.0)
    r = rng.uniform(2, 20, n)
    cols = {"x": (r * np.cos(el) * np.cos(az)).astype(np.float32),
            "y": (r * np.cos(el) * np.sin(az)).astype(np.float32),
            "z": (r * np.sin(el)).astype(np.float32),
            "intensity": rng.uniform(0, 255, n).astype(np.float32),
            "tag": np.full(n, 0x10, np.uint8), "line": (k % 6).astype(np.uint8)}
    layout = [("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("intensity", 12, "f4"),
              ("tag", 16, "u1"), ("line", 17, "u1")]
    if with_time:
        cols["timestamp"] = t.astype(np.float64)
        layout.append(("timestamp", 18, "f8"))
    return msg_from(cols, layout, 26 if with_time else 18, base), t


def test_livox_ros_driver2_pointcloud2_times():
    """livox_ros_driver2's PointCloud2: 'timestamp' detected as absolute ns, each point's time
    within float64's resolution at 1.7e18 ns (256 ns) of the truth; 'line' not read as a ring
    but kept as each point's laser (``Scan.line``), for the stray test, as a CustomMsg's is."""
    base = 1_700_000_000_000_000_000
    msg, t = livox_pc2(np.random.default_rng(7), 20_000, base, with_time=True)
    dec = CloudDecoder(SensorConfig(), "/livox/lidar")
    scan = dec.decode(msg)
    assert dec.time_spec.describe() == "'timestamp' in ns, absolute (detected)"
    assert np.abs(scan.t_ns - t).max() <= 256
    assert scan.ring is None
    np.testing.assert_array_equal(scan.line, np.arange(20_000) % 6)


def test_livox_ros_driver_pointcloud2_without_times_is_read_in_firing_order():
    """livox_ros_driver's PointCloud2 has no time field: its points are spread over the frame
    in their order (each within one point interval of the truth), not reconstructed from the
    azimuth, which on a forward-looking rosette is off by most of the frame."""
    from adalio.io.pointcloud2 import azimuth_times_ns

    base = 1_700_000_000_000_000_000
    n = 24_000
    msg, t = livox_pc2(np.random.default_rng(8), n, base, with_time=False)
    dec = CloudDecoder(SensorConfig(lidar_rate_hz=10.0), "/livox/lidar")
    with pytest.warns(UserWarning, match="in the points' order \\(a Livox driver's cloud"):
        scan = dec.decode(msg)
    assert np.abs(scan.t_ns - t).max() <= 1e8 / n
    assert dec.time_spec.describe() == "none (spread over the frame in firing order)"
    wrong = azimuth_times_ns(scan.points_lidar, base, 10.0)
    assert np.median(np.abs(wrong - t)) > 2e7


def test_livox_pointcloud2_frames_faster_than_the_config_take_the_clouds_rate():
    """livox_ros_driver's clouds at 10 Hz with sensor.lidar_rate_hz 5: once the clouds' rate
    is measured, the warning speaks of frames in firing order (not of azimuth or turns), and
    from there on each point is within one point interval of its true time in its 100 ms
    frame (at 5 Hz they would run 200 ms, into the next cloud)."""
    n = 6_000
    base = 1_700_000_000_000_000_000
    rng = np.random.default_rng(9)
    dec = CloudDecoder(SensorConfig(lidar_rate_hz=5.0), "/livox/lidar")
    caught, late = [], []
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        for i in range(14):
            msg, t = livox_pc2(rng, n, base + i * 100_000_000, with_time=False)
            late.append(np.abs(dec.decode(msg).t_ns - t).max())
        caught = [str(x.message) for x in w]
    rate = [m for m in caught if "clouds come at" in m]
    assert len(rate) == 1
    assert "10.0 Hz, each a whole frame, but sensor.lidar_rate_hz is 5" in rate[0]
    assert "spread over the frame in firing order at 10.0 Hz from here on" in rate[0]
    assert "azimuth" not in rate[0] and "turn" not in rate[0]
    assert late[0] > 4e7  # the configured 5 Hz: the frame's end 100 ms late
    assert max(late[-2:]) <= 1e8 / n
