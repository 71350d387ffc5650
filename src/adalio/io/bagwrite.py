"""Writing small ROS bags (tests, the simulator) with rosbags: ROS1 ``.bag``, ROS2 sqlite3 or
mcap folders, and bare ``.mcap`` files.

Messages: ``sensor_msgs/Imu`` (rad/s, m/s^2, IMU frame), ``sensor_msgs/PointCloud2`` (columns
packed by :func:`~adalio.io.pointcloud2.encode_pointcloud2`), Livox ``CustomMsg``
(:meth:`BagWriter.add_livox`) and ``tf2_msgs/TFMessage`` on
``/tf_static`` (``T_parent_child``). Times are int64 ns; the receive time defaults to the stamp.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any, Self

import numpy as np

from adalio.io.bag import ros1_typestore, ros2_typestore
from adalio.io.pointcloud2 import encode_pointcloud2

FORMATS = ("ros1", "ros2", "sqlite3", "mcap", "mcap_file")
"""'ros2' = 'sqlite3' (ROS2 folder), 'mcap' (ROS2 folder with mcap storage), 'mcap_file'
(a bare .mcap file)."""

COMPRESSIONS = {"ros1": ("bz2", "lz4"), "ros2": ("file", "message")}
"""A ROS1 bag's chunk compression (``rosbag record --bz2`` / ``--lz4``); a ROS2 bag's zstd
compression mode (``ros2 bag record --compression-mode file`` / ``message``)."""

HESAI_LAYOUT = [("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("intensity", 16, "f4"),
                ("timestamp", 24, "f8"), ("ring", 32, "u2")]
HESAI_POINT_STEP = 48
"""Hesai PandarXT (HesaiLidar_General_ROS) layout: PCL-aligned x,y,z,(pad),intensity,timestamp,
ring with padding, absolute float64 seconds."""


class BagWriter:
    """Context manager writing a bag in one of :data:`FORMATS`, compressed as ``compression``
    says (one of :data:`COMPRESSIONS` for the format; None: uncompressed)."""

    def __init__(self, path: str | Path, fmt: str = "ros1", compression: str | None = None
                 ) -> None:
        if fmt not in FORMATS:
            raise ValueError(f"fmt must be one of {FORMATS}")
        allowed = COMPRESSIONS["ros1" if fmt == "ros1" else "ros2"]
        if fmt == "mcap_file":
            allowed = ("message",)  # file mode makes a .mcap.zstd file, not a bare .mcap
        if compression is not None and compression not in allowed:
            raise ValueError(f"compression of a {fmt} bag must be one of {allowed} or None")
        self.path = Path(path)
        self.fmt = fmt
        self._conns: dict[str, Any] = {}
        self._tmp: Path | None = None
        if fmt == "ros1":
            from rosbags.rosbag1 import Writer

            self.store = ros1_typestore()
            self._writer = Writer(self.path)
            if compression is not None:
                self._writer.set_compression(Writer.CompressionFormat[compression.upper()])
        else:
            from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

            self.store = ros2_typestore()
            target = self.path
            if fmt == "mcap_file":
                self._tmp = Path(tempfile.mkdtemp(prefix="adalio_mcap_"))
                target = self._tmp / "bag"
            plugin = StoragePlugin.SQLITE3 if fmt in ("ros2", "sqlite3") else StoragePlugin.MCAP
            self._writer = Writer(target, version=9, storage_plugin=plugin)
            if compression is not None:
                self._writer.set_compression(CompressionMode[compression.upper()],
                                             CompressionFormat.ZSTD)

    def __enter__(self) -> Self:
        self._writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self._writer.close()
        if self._tmp is not None:
            files = list((self._tmp / "bag").glob("*.mcap"))
            shutil.move(str(files[0]), self.path)
            shutil.rmtree(self._tmp, ignore_errors=True)

    # ------------------------------------------------------------------ helpers
    def _types(self) -> Any:
        return self.store.types

    def _conn(self, topic: str, msgtype: str) -> Any:
        if topic not in self._conns:
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self.store)
        return self._conns[topic]

    def _header(self, stamp_ns: int, frame_id: str) -> Any:
        T = self._types()
        stamp = T["builtin_interfaces/msg/Time"](sec=int(stamp_ns // 1_000_000_000),
                                                  nanosec=int(stamp_ns % 1_000_000_000))
        if self.fmt == "ros1":
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def write_msg(self, topic: str, msgtype: str, msg: Any, t_recv_ns: int) -> None:
        data = self.store.serialize_ros1(msg, msgtype) if self.fmt == "ros1" \
            else self.store.serialize_cdr(msg, msgtype)
        self._writer.write(self._conn(topic, msgtype), int(t_recv_ns), data)

    # ------------------------------------------------------------------ messages
    def add_imu(self, topic: str, t_ns: int, gyro_rad_s: Any, accel_m_s2: Any,
                frame_id: str = "imu", t_recv_ns: int | None = None) -> None:
        T = self._types()
        v3 = T["geometry_msgs/msg/Vector3"]
        cov = np.zeros(9)
        msg = T["sensor_msgs/msg/Imu"](
            header=self._header(t_ns, frame_id),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.r_[-1.0, np.zeros(8)],
            angular_velocity=v3(*map(float, gyro_rad_s)), angular_velocity_covariance=cov,
            linear_acceleration=v3(*map(float, accel_m_s2)), linear_acceleration_covariance=cov)
        self.write_msg(topic, "sensor_msgs/msg/Imu", msg, t_ns if t_recv_ns is None else t_recv_ns)

    def add_cloud_bytes(self, topic: str, stamp_ns: int, data: bytes,
                        fields: list[tuple[str, int, int, int]], point_step: int, width: int,
                        height: int = 1, big_endian: bool = False, frame_id: str = "lidar",
                        row_step: int | None = None, t_recv_ns: int | None = None) -> None:
        T = self._types()
        pf = T["sensor_msgs/msg/PointField"]
        msg = T["sensor_msgs/msg/PointCloud2"](
            header=self._header(stamp_ns, frame_id), height=int(height), width=int(width),
            fields=[pf(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields],
            is_bigendian=bool(big_endian), point_step=int(point_step),
            row_step=int(row_step if row_step is not None else point_step * width),
            data=np.frombuffer(bytes(data), dtype=np.uint8), is_dense=False)
        self.write_msg(topic, "sensor_msgs/msg/PointCloud2", msg,
                       stamp_ns if t_recv_ns is None else t_recv_ns)

    def add_cloud(self, topic: str, stamp_ns: int, columns: dict[str, np.ndarray],
                  layout: list[tuple[str, int, str]], point_step: int, *,
                  big_endian: bool = False, frame_id: str = "lidar", height: int = 1,
                  t_recv_ns: int | None = None) -> None:
        """Pack ``columns`` with ``layout`` (see encode_pointcloud2) and write one cloud."""
        data, fields = encode_pointcloud2(columns, layout, point_step, big_endian)
        n = len(next(iter(columns.values())))
        width = n // height if height > 0 else 0
        self.add_cloud_bytes(topic, stamp_ns, data, fields, point_step, width, height,
                             big_endian, frame_id, t_recv_ns=t_recv_ns)

    def add_livox(self, topic: str, cloud: Any, t_recv_ns: int | None = None,
                  msgtype: str | None = None) -> None:
        """Write one Livox ``CustomMsg`` (:class:`~adalio.io.livox.LivoxCloud`), serialized
        with numpy; the type is ``livox_ros_driver/msg/CustomMsg`` in a ROS1 bag and
        ``livox_ros_driver2/msg/CustomMsg`` in a ROS2 one unless ``msgtype`` says."""
        from adalio.io.livox import LIVOX_TYPES, build_custom_msg

        msgtype = msgtype or LIVOX_TYPES[0 if self.fmt == "ros1" else 1]
        data = build_custom_msg(cloud, ros2=self.fmt != "ros1")
        self._writer.write(self._conn(topic, msgtype),
                           int(cloud.stamp_ns if t_recv_ns is None else t_recv_ns), data)

    def add_tf_static(self, transforms: list[tuple[str, str, np.ndarray]], t_ns: int,
                      topic: str = "/tf_static") -> None:
        """Write one TFMessage with ``(parent, child, T_parent_child)`` transforms."""
        from scipy.spatial.transform import Rotation

        T = self._types()
        out = []
        for parent, child, M in transforms:
            M = np.asarray(M, dtype=float)
            q = Rotation.from_matrix(M[:3, :3]).as_quat()
            out.append(T["geometry_msgs/msg/TransformStamped"](
                header=self._header(t_ns, parent), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](*map(float, M[:3, 3])),
                    rotation=T["geometry_msgs/msg/Quaternion"](*map(float, q)))))
        self.write_msg(topic, "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](
            transforms=out), t_ns)
