"""Reading bags written with rosbags in every supported format; /tf_static extrinsics."""

from __future__ import annotations

import contextlib
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bagfactory as bf

from adalio.config import Config, SensorConfig
from adalio.errors import BagError
from adalio.io.bag import Bag, chain_transform
from adalio.io.bagwrite import BagWriter
from adalio.io.pointcloud2 import stamp_to_ns
from adalio.io.sequencer import Sequencer
from adalio.pipeline import resolve_extrinsic
from adalio.types import ImuBatch, Scan

FORMATS = [("ros1", "rig.bag"), ("sqlite3", "rig_db3"), ("mcap", "rig_mcap"),
           ("mcap_file", "rig.mcap")]


def random_T(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    return T


@pytest.mark.parametrize("fmt,name", FORMATS)
def test_formats_read_back_counts_order_and_points(tmp_path, fmt, name):
    path = bf.write_static_rig(tmp_path / name, fmt, duration_s=1.0, imu_rate_hz=100.0,
                               columns=90)
    pts, t_rel, _ = bf.box_scan(columns=90)
    with Bag(path) as bag:
        counts = {t.name: (t.msgtype, t.count) for t in bag.topics()}
        assert counts == {"/imu": ("sensor_msgs/msg/Imu", 100),
                          "/points": ("sensor_msgs/msg/PointCloud2", 9)}
        assert bag.select_topics(SensorConfig()) == ("/points", "/imu")
        stamps = {"/imu": [], "/points": []}
        recv = []
        for topic, t_recv, msg in bag.messages(["/imu", "/points"]):
            stamps[topic].append(stamp_to_ns(msg.header.stamp))
            recv.append(t_recv)
        assert recv == sorted(recv)
        assert stamps["/imu"] == [bf.T0_NS + k * 10_000_000 for k in range(100)]
        assert stamps["/points"] == [bf.T0_NS + k * 100_000_000 for k in range(9)]
        items = list(Sequencer(bag, "/points", "/imu"))
    scans = [i for i in items if isinstance(i, Scan)]
    assert len(scans) == 9
    imu_t = np.concatenate([i.t_ns for i in items if isinstance(i, ImuBatch)])
    np.testing.assert_array_equal(imu_t, [bf.T0_NS + k * 10_000_000 for k in range(100)])
    seen = 0
    for item in items:
        if isinstance(item, ImuBatch):
            seen += len(item)
        else:
            # every sample up to the scan end, and the first one after it (there is one here)
            assert seen == np.count_nonzero(imu_t <= item.t_end_ns) + 1
    np.testing.assert_array_equal(scans[3].points_lidar, pts.astype(np.float32))
    np.testing.assert_array_equal(scans[3].t_ns, bf.T0_NS + 300_000_000 + t_rel.astype(np.int64))


COMPRESSED = [("ros1", "bz2", "rig.bag"), ("ros1", "lz4", "rig.bag"),
              ("sqlite3", "file", "rig"), ("sqlite3", "message", "rig"),
              ("mcap", "file", "rig"), ("mcap", "message", "rig"),
              ("mcap_file", "message", "rig.mcap"), ("sqlite3", "message", "bare.db3")]


@pytest.mark.parametrize("fmt,compression,name", COMPRESSED)
def test_compressed_bags_read_back_the_same_messages(tmp_path, fmt, compression, name):
    """rosbag record --bz2 / --lz4, ros2 bag record --compression-mode file / message (zstd),
    and the bare .mcap or .db3 file of a message-compressed recording, without the
    metadata.yaml that says the messages are compressed."""
    path = bf.write_static_rig(tmp_path / name.removesuffix(".db3"), fmt, duration_s=1.0,
                               imu_rate_hz=100.0, columns=90, compression=compression)
    if name.endswith(".db3"):  # the bag's one file, moved away from its metadata.yaml
        path = next(path.glob("*.db3")).rename(tmp_path / "alone.db3")
    plain = bf.write_static_rig(tmp_path / "plain.bag", "ros1", duration_s=1.0,
                                imu_rate_hz=100.0, columns=90)
    if compression == "message" and path.is_file():  # the messages themselves are zstd frames
        assert bf.ZSTD_MAGIC in path.read_bytes()
    with Bag(path) as bag, Bag(plain) as ref:
        assert {t.name: t.count for t in bag.topics()} == {"/imu": 100, "/points": 9}
        got = list(Sequencer(bag, "/points", "/imu"))
        want = list(Sequencer(ref, "/points", "/imu"))
    assert [type(i) for i in got] == [type(i) for i in want]
    for a, b in zip(got, want, strict=True):
        if isinstance(a, Scan):
            np.testing.assert_array_equal(a.points_lidar, b.points_lidar)
            np.testing.assert_array_equal(a.t_ns, b.t_ns)
        else:
            np.testing.assert_array_equal(a.t_ns, b.t_ns)
            np.testing.assert_array_equal(a.accel_m_s2, b.accel_m_s2)


def test_a_file_compressed_ros2_part_is_named_with_what_to_give(tmp_path):
    folder = bf.write_static_rig(tmp_path / "rig", "sqlite3", duration_s=0.5, imu_rate_hz=50.0,
                                 columns=30, compression="file")
    part = folder / "rig.db3.zstd"
    assert part.is_file()
    with pytest.raises(BagError, match=f"give the bag's folder {folder}"):
        Bag(part)
    alone = tmp_path / "alone.db3.zstd"
    part.rename(alone)
    with pytest.raises(BagError, match="decompress it \\('zstd -d alone.db3.zstd'\\)"):
        Bag(alone)


VELODYNE_PACKET = "time stamp\nuint8[1206] data\n"
VELODYNE_SCAN = "std_msgs/Header header\nvelodyne_msgs/VelodynePacket[] packets\n"


def _packets(w, topic: str, msgtype: str) -> None:
    """Ten messages of a driver's packet type on ``topic`` (registered in the writer's store)."""
    from rosbags.typesys import get_types_from_msg

    if msgtype.startswith("velodyne_msgs"):
        types = get_types_from_msg(VELODYNE_PACKET, "velodyne_msgs/msg/VelodynePacket")
        types.update(get_types_from_msg(VELODYNE_SCAN, msgtype))
    else:
        types = get_types_from_msg("uint8[] buf\n", msgtype)
    w.store.register(types)
    T = w.store.types
    for k in range(10):
        t = bf.T0_NS + k * 100_000_000
        if msgtype.startswith("velodyne_msgs"):
            stamp = T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
            pkt = T["velodyne_msgs/msg/VelodynePacket"](stamp=stamp,
                                                        data=np.zeros(1206, np.uint8))
            msg = T[msgtype](header=w._header(t, "velodyne"), packets=[pkt, pkt])
        else:
            msg = T[msgtype](buf=np.zeros(12609, np.uint8))
        w.write_msg(topic, msgtype, msg, t)


@pytest.mark.parametrize("fmt,name,topic,msgtype", [
    ("ros1", "rig.bag", "/velodyne_packets", "velodyne_msgs/msg/VelodyneScan"),
    ("mcap", "rig", "/ouster/lidar_packets", "ouster_sensor_msgs/msg/PacketMsg"),
    ("sqlite3", "rig", "/hesai/pandar_packets", "hesai_ros_driver/msg/UdpFrame")])
def test_a_lidar_recorded_as_packets_is_named_with_what_to_do(tmp_path, fmt, name, topic,
                                                              msgtype):
    """Drivers' raw packet topics instead of point clouds (Velodyne users often record only
    /velodyne_packets): the error names the topic and says to play it through the driver."""
    with BagWriter(tmp_path / name, fmt) as w:
        for k in range(100):
            w.add_imu("/imu", bf.T0_NS + k * 10_000_000, [0, 0, 0], [0, 0, 9.81])
        _packets(w, topic, msgtype)
    with Bag(tmp_path / name) as bag, pytest.raises(BagError) as err:
        bag.select_topics(SensorConfig())
    text = str(err.value)
    assert "has no sensor_msgs/PointCloud2 or Livox CustomMsg topic" in text
    assert f"{topic} ({msgtype})" in text, text
    assert "raw packets" in text and "play the bag through the LiDAR's ROS driver" in text
    assert text.endswith("and run on that bag"), text
    assert "/imu" not in text


def test_a_2d_laser_scan_is_named_as_such(tmp_path):
    with BagWriter(tmp_path / "rig", "mcap") as w:
        T = w.store.types
        for k in range(10):
            t = bf.T0_NS + k * 100_000_000
            scan = T["sensor_msgs/msg/LaserScan"](
                header=w._header(t, "laser"), angle_min=-3.1, angle_max=3.1, angle_increment=0.01,
                time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=30.0,
                ranges=np.ones(620, np.float32), intensities=np.ones(620, np.float32))
            w.write_msg("/scan", "sensor_msgs/msg/LaserScan", scan, t)
            w.add_imu("/imu", t, [0, 0, 0], [0, 0, 9.81])
    with Bag(tmp_path / "rig") as bag, pytest.raises(
            BagError, match=r"/scan \(sensor_msgs/msg/LaserScan\) is a 2D laser scan, one plane "
                            r"of ranges; adalio needs a 3D LiDAR's point clouds"):
        bag.select_topics(SensorConfig())


def test_folder_of_split_ros1_bags(tmp_path):
    folder = tmp_path / "split"
    folder.mkdir()
    for part in range(2):
        with BagWriter(folder / f"part_{part}.bag", "ros1") as w:
            for k in range(50):
                t = bf.T0_NS + (part * 50 + k) * 5_000_000
                w.add_imu("/imu", t, [0, 0, 0], [0, 0, 9.81])
    with Bag(folder) as bag:
        assert [t.count for t in bag.topics()] == [100]
        got = [stamp_to_ns(m.header.stamp) for _, _, m in bag.messages(["/imu"])]
    assert got == [bf.T0_NS + k * 5_000_000 for k in range(100)]


@pytest.mark.parametrize("fmt,name", FORMATS)
def test_tf_static_chain_gives_T_imu_lidar(tmp_path, fmt, name):
    T_base_imu, T_base_mid, T_mid_lidar = random_T(1), random_T(2), random_T(3)
    tf = [("base_link", "imu_link", T_base_imu), ("base_link", "mid", T_base_mid),
          ("mid", "hesai", T_mid_lidar)]
    path = bf.write_static_rig(tmp_path / name, fmt, duration_s=0.3, tf_static=tf,
                               imu_frame="imu_link", lidar_frame="hesai", columns=30)
    truth = np.linalg.inv(T_base_imu) @ T_base_mid @ T_mid_lidar
    cfg = Config()
    with Bag(path) as bag:
        T, src = resolve_extrinsic(bag, "/points", "/imu", cfg)
        assert "tf_static" in src
        np.testing.assert_allclose(T, truth, atol=1e-9)
        cfg.sensor.extrinsic_source = "config"
        T_cfg, src = resolve_extrinsic(bag, "/points", "/imu", cfg)
        assert src == "config" and np.allclose(T_cfg, np.eye(4))


def test_tf_static_required_but_absent_is_error(tmp_path):
    path = bf.write_static_rig(tmp_path / "a.bag", duration_s=0.3, columns=30)
    cfg = Config()
    cfg.sensor.extrinsic_source = "tf_static"
    with Bag(path) as bag, pytest.raises(BagError, match="has no /tf_static"):
        resolve_extrinsic(bag, "/points", "/imu", cfg)


def test_chain_transform_unconnected_is_none():
    edges = [("a", "b", random_T(4)), ("c", "d", random_T(5))]
    assert chain_transform(edges, "a", "d") is None
    np.testing.assert_allclose(chain_transform(edges, "b", "a"), np.linalg.inv(edges[0][2]))


def test_accel_in_g_is_converted_once(tmp_path):
    path = bf.write_static_rig(tmp_path / "g.bag", duration_s=1.0, accel_scale=1 / 9.81,
                               columns=30)
    with Bag(path) as bag:
        seq = Sequencer(bag, "/points", "/imu")
        with pytest.warns(UserWarning, match="reports in g"):
            items = list(seq)
    acc = np.concatenate([i.accel_m_s2 for i in items if isinstance(i, ImuBatch)])
    assert seq.stats.accel_in_g
    np.testing.assert_allclose(acc[:, 2], 9.80665, rtol=1e-6)
    with Bag(path) as bag:
        seq = Sequencer(bag, "/points", "/imu", SensorConfig(accel_unit="m_s2"))
        acc = np.concatenate([i.accel_m_s2 for i in seq if isinstance(i, ImuBatch)])
    np.testing.assert_allclose(acc[:, 2], 1.0, rtol=1e-6)


@pytest.mark.parametrize("content,match", [(b"hello world" * 10, "not a ROS1 bag"),
                                           (None, "truncated or corrupted")])
def test_damaged_bags_are_bag_errors(tmp_path, content, match):
    path = tmp_path / "bad.bag"
    if content is None:
        good = bf.write_static_rig(tmp_path / "good.bag", duration_s=0.5, columns=30)
        path.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    else:
        path.write_bytes(content)
    with pytest.raises(BagError, match=match), Bag(path) as bag:
        list(bag.messages([t.name for t in bag.topics()]))


def _read_all(bag: Bag, read_ahead: bool) -> tuple[list, str | None]:
    """(topic, receive time, header stamp) of every message read, and the error that stopped
    the reading (None: read to the end)."""
    got = []
    try:
        for topic, t_recv, msg in bag.messages([t.name for t in bag.topics()],
                                               read_ahead=read_ahead):
            got.append((topic, t_recv, stamp_to_ns(msg.header.stamp)))
    except BagError as exc:
        return got, str(exc)
    return got, None


def _read_ahead_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "adalio-bag-read-ahead"]


@pytest.mark.parametrize("fmt,compression", [("sqlite3", None), ("mcap", "message"),
                                             ("ros1", "lz4")])
def test_read_ahead_gives_the_same_messages_and_the_same_error_after_them(tmp_path, fmt,
                                                                        compression):
    """Bag.messages(read_ahead=True), which adalio run reads with: the messages of the bag in
    the same order, and a read that fails mid-bag raises the same error, after the same
    messages, as the plain read."""
    kwargs = {"compression": compression} if compression else {}
    path = bf.write_static_rig(tmp_path / ("rig.bag" if fmt == "ros1" else "rig"), fmt,
                               duration_s=2.0, columns=90, **kwargs)
    for damaged in (False, True):
        if damaged:  # a page of the database overwritten, as in test_cli_io
            db = next(path.glob("*.db3"))
            data = bytearray(db.read_bytes())
            page = int(len(data) * 0.6) // 4096 * 4096
            data[page:page + 4096] = b"\xff" * 4096
            db.write_bytes(bytes(data))
        with Bag(path) as bag:
            plain = _read_all(bag, read_ahead=False)
        with Bag(path) as bag:
            ahead = _read_all(bag, read_ahead=True)
        assert ahead == plain
        assert len(plain[0]) > 20
        assert (plain[1] is not None) == damaged
        if damaged:
            assert "after" in plain[1] and "truncated or corrupted" in plain[1]
        if fmt != "sqlite3":
            break
    assert not _read_ahead_threads()


def test_read_ahead_reads_ahead_and_stops_with_its_reader_or_the_bag(tmp_path):
    path = bf.write_static_rig(tmp_path / "rig.bag", duration_s=2.0, columns=90)
    with Bag(path) as bag:
        topics = [t.name for t in bag.topics()]
        it = bag.messages(topics, read_ahead=True)
        _, t_first, _ = next(it)
        deadline = time.monotonic() + 10.0  # the thread reads on while the caller holds one
        while bag._last_t <= t_first and time.monotonic() < deadline:
            time.sleep(0.01)
        assert bag._last_t > t_first
        it.close()  # the caller stops early (adalio run --max-scans): so does the thread
        assert not _read_ahead_threads()
        bag.messages(topics, read_ahead=True)  # never iterated: closing the bag stops it
        assert _read_ahead_threads()
    assert not _read_ahead_threads()


def test_batch_workers_read_their_bags_without_a_read_ahead_thread(tmp_path, monkeypatch):
    """adalio batch's embedded workers share the cores one bag each: there a read-ahead thread
    only competes, so their processes switch it off (batch._read_without_thread, run in every
    embedded worker whatever NUMBA_NUM_THREADS says)."""
    from adalio import batch

    monkeypatch.setattr(Sequencer, "read_ahead", Sequencer.read_ahead)  # restored after
    path = bf.write_static_rig(tmp_path / "rig.bag", duration_s=1.0, columns=90)

    def reads_ahead() -> bool:  # a read-ahead is registered with its bag while it runs
        with Bag(path) as bag:
            return any(bool(bag._ahead) for _ in Sequencer(bag, "/points", "/imu"))

    assert reads_ahead()
    batch._read_without_thread()
    assert not reads_ahead()


def add_box_clouds(w: BagWriter, n: int, sweep_ns: int) -> None:
    """``n`` sweeps of the factory's box (30 columns) on /points, each received at its end."""
    pts, t_rel, ring = bf.box_scan(columns=30, sweep_ns=sweep_ns)
    cols = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "intensity": np.ones(len(pts)),
            "t": t_rel, "ring": ring}
    for k in range(n):
        w.add_cloud("/points", bf.T0_NS + k * sweep_ns, cols, bf.OUSTER_LAYOUT, bf.OUSTER_STEP,
                    frame_id="lidar", t_recv_ns=bf.T0_NS + (k + 1) * sweep_ns)


@pytest.mark.parametrize("fmt,name", FORMATS)
def test_a_bad_unrelated_transform_and_a_silent_topic_do_not_stop_a_bag(tmp_path, fmt, name):
    """A /tf_static transform to a camera with a zero quaternion is left out with a warning
    naming it (the LiDAR-IMU chain still gives the written extrinsic), and an advertised IMU
    topic that never published is not a second candidate (``ros2 bag record -a``)."""
    T_il = random_T(7)
    path = tmp_path / name
    sweep_ns = 100_000_000
    with BagWriter(path, fmt) as w:
        w.add_tf_static([("imu", "lidar", T_il)], bf.T0_NS)
        T = w._types()
        bad = T["geometry_msgs/msg/TransformStamped"](
            header=w._header(bf.T0_NS, "imu"), child_frame_id="cam0",
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 0.0)))
        w.write_msg("/tf_static", "tf2_msgs/msg/TFMessage",
                    T["tf2_msgs/msg/TFMessage"](transforms=[bad]), bf.T0_NS + 1)
        w._conn("/imu_silent", "sensor_msgs/msg/Imu")
        for k in range(60):
            w.add_imu("/imu", bf.T0_NS + k * 5_000_000, [0.0, 0.0, 0.0], [0.0, 0.0, 9.81],
                      frame_id="imu")
        add_box_clouds(w, 2, sweep_ns)
    with Bag(path) as bag:
        assert {t.name: t.count for t in bag.topics()}.get("/imu_silent", 0) == 0
        assert bag.select_topics(SensorConfig()) == ("/points", "/imu")
        with pytest.warns(UserWarning, match="imu -> cam0: the transform has a zero"):
            edges = bag.static_transforms()
        assert [(p, c) for p, c, _ in edges] == [("imu", "lidar")]
        with pytest.warns(UserWarning, match="cam0"):
            T_found, src = resolve_extrinsic(bag, "/points", "/imu", Config())
        assert "tf_static" in src
        np.testing.assert_allclose(T_found, T_il, atol=1e-9)


@pytest.mark.parametrize("unit,start", [("m_s2", 0.0), ("g", np.nan)])
def test_accel_unit_is_told_by_samples_that_can_tell_it(tmp_path, unit, start):
    """A driver's first samples may be zeros or NaN placeholders; the unit is told by the
    samples after them: an IMU in m/s² with 45 zero samples first is not taken for g (it was:
    every sample x 9.81), and one in g with 60 NaN samples first is (it was not)."""
    scale = 1.0 / 9.80665 if unit == "g" else 1.0
    n_start = 45 if unit == "m_s2" else 60
    path = tmp_path / "a.bag"
    sweep_ns = 100_000_000
    with BagWriter(path, "ros1") as w:
        for k in range(300):
            a = [start] * 3 if k < n_start else [0.0, 0.0, 9.80665 * scale]
            w.add_imu("/imu", bf.T0_NS + k * 5_000_000, [0.0, 0.0, 0.0], a)
        add_box_clouds(w, 12, sweep_ns)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with Bag(path) as bag:
            seq = Sequencer(bag, "/points", "/imu")
            acc = np.concatenate([i.accel_m_s2 for i in seq if isinstance(i, ImuBatch)])
    assert seq.stats.accel_in_g == (unit == "g")
    assert any("reports in g" in str(c.message) for c in caught) == (unit == "g")
    moving = np.any(acc != 0.0, axis=1)
    np.testing.assert_allclose(acc[moving, 2], 9.80665, rtol=1e-6)


def test_an_upper_case_suffix_is_named_with_the_fix(tmp_path):
    """rosbags tells a ROS1 bag by a lower-case '.bag': 'HALL.BAG' is one error that says to
    rename it, and the renamed file reads."""
    path = bf.write_static_rig(tmp_path / "rig.bag", duration_s=0.3, columns=30)
    upper = path.rename(tmp_path / "RIG.BAG")
    with pytest.raises(BagError, match="rename the file to RIG.bag"):
        Bag(upper).__enter__()
    with Bag(upper.rename(tmp_path / "RIG.bag")) as bag:
        assert {t.name for t in bag.topics()} == {"/points", "/imu"}


def _packet_topic_bag(path: Path, rig: Path | None) -> Path:
    """A copy of ``rig`` (or nothing) plus a topic recorded with an empty definition (a driver's
    packet topic, rosserial)."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    _, md5 = store.generate_msgdef("std_msgs/msg/UInt8MultiArray")
    msg = store.types["std_msgs/msg/UInt8MultiArray"](
        layout=store.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0),
        data=np.zeros(4, np.uint8))
    with Writer(path) as w:
        c = w.add_connection("/rslidar_packets", "std_msgs/msg/UInt8MultiArray", msgdef="",
                             md5sum=md5)
        w.write(c, bf.T0_NS, store.serialize_ros1(msg, "std_msgs/msg/UInt8MultiArray"))
        if rig is not None:
            with AnyReader([rig]) as r:
                out = {x.id: w.add_connection(x.topic, x.msgtype, msgdef=x.msgdef.data,
                                              md5sum=x.digest) for x in r.connections}
                for x, t, raw in r.messages():
                    w.write(out[x.id], t, raw)
    return path


def _rosbags_refuses(path: Path) -> bool:
    """Whether rosbags' AnyReader refuses to open the bag (newer releases refuse a topic's empty
    message definition; 0.11.1 does not)."""
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([path])
        reader.open()
    except Exception:  # noqa: BLE001  (whatever rosbags raises for it)
        return True
    reader.close()
    return False


def test_a_topic_with_an_empty_definition_is_left_out_and_the_rest_read(tmp_path):
    """A ROS1 bag with one topic recorded with an empty message definition (a driver's packet
    topic, rosserial): rosbags refuses the whole bag; adalio reads the other topics with its own
    ROS1 types, message for message as in the bag without that topic, and warns naming it
    (rosbags 0.11.1, the lower bound, opens it itself: then the same messages, no warning). A
    bag with nothing else has no LiDAR topic (the usual error); a damaged one is still an
    error. An mcap encoding the reader does not know is named too."""
    from adalio.io.bag import _open_failure

    rig = bf.write_static_rig(tmp_path / "rig.bag", duration_s=0.5, columns=30)
    path = _packet_topic_bag(tmp_path / "p.bag", rig)
    with Bag(rig) as bag:
        want = [(t, s, m.header.stamp.sec, m.header.stamp.nanosec)
                for t, s, m in bag.messages(["/points", "/imu"])]
        clouds = [m.data.tobytes() for _, _, m in bag.messages(["/points"])]
    if _rosbags_refuses(path):  # rosbags 0.11.1 (the lower bound) opens it as it is
        with pytest.warns(UserWarning, match=r"refuses its message definitions "
                                             r"\(/rslidar_packets: empty or not matching the type"):
            bag = Bag(path).open()
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            bag = Bag(path).open()
    with contextlib.closing(bag):
        assert bag.select_topics(SensorConfig()) == ("/points", "/imu")
        got = [(t, s, m.header.stamp.sec, m.header.stamp.nanosec)
               for t, s, m in bag.messages(["/points", "/imu"])]
        assert got == want and len(want) > 100
        assert [m.data.tobytes() for _, _, m in bag.messages(["/points"])] == clouds
        pts_t = [w[1] for w in want if w[0] == "/points"]
        n = min(len(pts_t), 20)  # the rate from the first 20 clouds' receive times
        assert bag.topic_rate_hz("/points", len(pts_t)) == pytest.approx(
            (n - 1) / ((pts_t[n - 1] - pts_t[0]) * 1e-9))
    only = _packet_topic_bag(tmp_path / "only.bag", None)
    with contextlib.ExitStack() as stack:
        if _rosbags_refuses(only):
            stack.enter_context(pytest.warns(UserWarning, match="refuses its message definitions"))
        bag = Bag(only).open()
    with contextlib.closing(bag), pytest.raises(BagError, match="PointCloud2"):
        bag.select_topics(SensorConfig())
    damaged = tmp_path / "damaged.bag"
    damaged.write_bytes(path.read_bytes()[:-200])
    with pytest.raises(BagError, match="cannot read bag"):
        Bag(damaged).open()
    text = _open_failure(Path("x.mcap"), KeyError("ros1msg"))
    assert "ros1msg" in text and "does not read" in text and "truncated" not in text


def test_split_and_unfinished_recordings_are_named(tmp_path):
    """One part of a split recording given alone reads that part with a warning to give the
    folder (ROS1 x_0.bag beside x_1.bag, numbered from 0 as rosbag splits; separate recordings
    numbered _1, _3, _4 are not warned about; a ROS2 file beside its metadata.yaml and other
    parts); a
    folder of ROS2 files without metadata.yaml says to reindex it; an unfinished ROS1 recording
    (.bag.active) says to reindex it, not that it is no bag."""
    import shutil

    (tmp_path / "ros1").mkdir()
    part = bf.write_static_rig(tmp_path / "ros1" / "x_0.bag", duration_s=0.3, columns=30)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # alone in its folder: no warning
        Bag(part).open().close()
    shutil.copy(part, part.with_name("x_1.bag"))
    with pytest.warns(UserWarning, match=r"x_0\.bag looks like one part of a split recording "
                                         r"\(1 more beside it, numbered from _0: x_1\.bag, "
                                         r"\.\.\.\): only this part is read"):
        Bag(part)
    numbered = tmp_path / "hilti2021"  # separate recordings named _1, _3, _4: no warning
    numbered.mkdir()
    for k in (1, 3, 4):
        shutil.copy(part, numbered / f"Basement_{k}.bag")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Bag(numbered / "Basement_3.bag")
    r2 = bf.write_static_rig(tmp_path / "r2", "ros2", duration_s=0.3, columns=30)
    files = sorted(p for p in r2.iterdir() if p.suffix in (".db3", ".mcap"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the bag's one file: no warning
        Bag(files[0])
    shutil.copy(files[0], files[0].with_name("extra_1" + files[0].suffix))
    with pytest.warns(UserWarning, match="is one file of the ROS2 bag .*give the folder"):
        Bag(files[0])
    (r2 / "metadata.yaml").unlink()
    with pytest.raises(BagError, match=r"holds 2 ROS2 bag files .* but no metadata\.yaml: .*"
                                       r"'ros2 bag reindex "):
        Bag(r2)
    active = tmp_path / "y.bag.active"
    active.write_bytes(part.read_bytes())
    with pytest.raises(BagError, match=r"unfinished ROS1 recording .*'rosbag reindex .*rename "
                                       r"it to y\.bag"):
        Bag(active)
