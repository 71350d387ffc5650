"""Writing simulated sweeps and IMU samples as ROS1 / ROS2 (sqlite3, mcap) bags with rosbags.

Layouts follow the real drivers. PandarXT-32 (HILTI 2022, ``/hesai/pandar``): unorganized cloud
of valid returns only, column-major; fields x, y, z (f32 @0,4,8), intensity (f32 @16), timestamp
(f64 absolute seconds @24), ring (u16 @32), point_step 48 (Hesai ``PointXYZIT``). Ouster-like
(``/ouster/points``): organized 64 x 1024 cloud (row = beam) with zero points for missing returns;
x, y, z (f32), intensity (f32 @16), t (u32 ns relative to the header stamp @20), reflectivity
(u16 @24), ring (u16 @26), ambient (u16 @28), range (u32 mm @32), point_step 48. Header stamp =
sweep start; the bag record time of a sweep is its end. sensor_msgs/Imu: orientation unknown
(covariance[0] = -1). Velodyne VLP-16 (``/velodyne_points``, the ROS driver's ``PointXYZIRT``):
unorganized cloud of valid returns, packed fields x, y, z, intensity (f32 @0,4,8,12), ring (u16
@16, 0 = the lowest beam as the driver numbers them), time (f32 seconds relative to the header
stamp @18), point_step 22. Livox Mid-360- and Avia-like (``/livox/lidar``): Livox's own
``CustomMsg`` (``livox_ros_driver/msg/CustomMsg`` in ROS1 bags, ``livox_ros_driver2/msg/CustomMsg``
in ROS2 ones, as FAST-LIO users record them; :mod:`adalio.io.livox`): the valid returns in firing
order, ``timebase`` = the frame's first firing (absolute ns) = the header stamp, per point
``offset_time`` (u32 ns after it), x, y, z, ``reflectivity`` (the intensity, 0-255), ``tag`` 0
(first return), ``line`` (the laser: 0-3 on the Mid-360, 0-5 on the Avia); its IMU's accelerometer
in g, as Livox's drivers publish it (:attr:`~adalio.sim.lidar.LidarModel.imu_accel_unit`). mcap bags
are written with zstd-compressed chunks (about 4x smaller for simulated clouds; rosbags, ros2 bag
and Foxglove read them transparently).
"""

from __future__ import annotations

from pathlib import Path
from typing import Self

import numpy as np
from rosbags.typesys import Stores, get_typestore

from adalio.io.livox import (
    LIVOX_TYPES,
    LivoxCloud,
    build_custom_msg,
    livox_points,
    register_livox_types,
)
from adalio.io.pointcloud2 import encode_pointcloud2
from adalio.io.sequencer import G_TO_M_S2
from adalio.sim.lidar import LidarModel, SweepPoints

FORMATS = ("ros1", "ros2", "mcap")

XT32_LAYOUT = [("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("intensity", 16, "f4"),
               ("timestamp", 24, "f8"), ("ring", 32, "u2")]
OUSTER_LAYOUT = [("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("intensity", 16, "f4"),
                 ("t", 20, "u4"), ("reflectivity", 24, "u2"), ("ring", 26, "u2"),
                 ("ambient", 28, "u2"), ("range", 32, "u4")]
VELODYNE_LAYOUT = [("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("intensity", 12, "f4"),
                   ("ring", 16, "u2"), ("time", 18, "f4")]
POINT_STEP = 48
"""Bytes a point of the XT-32 and Ouster layouts; the largest of all layouts."""
VELODYNE_POINT_STEP = 22


def bag_path_for(out_dir: Path, stem: str, fmt: str) -> Path:
    """Where the bag of ``fmt`` goes inside ``out_dir`` (a file for ROS1, a folder for ROS2)."""
    return out_dir / (f"{stem}.bag" if fmt == "ros1" else f"{stem}_{fmt}")


class SimBagWriter:
    """Context manager writing IMU and sweep messages in record-time order."""

    def __init__(self, path: Path, fmt: str, model: LidarModel) -> None:
        self.path = Path(path)
        self.fmt = fmt
        self.model = model
        self.ros1 = fmt == "ros1"
        self.typestore = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        T = self.typestore.types
        self._Header, self._Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
        self._Cloud, self._Field = T["sensor_msgs/msg/PointCloud2"], T["sensor_msgs/msg/PointField"]
        self._Imu, self._Vec = T["sensor_msgs/msg/Imu"], T["geometry_msgs/msg/Vector3"]
        self._Quat = T["geometry_msgs/msg/Quaternion"]
        self._serialize = (self.typestore.serialize_ros1 if self.ros1
                           else self.typestore.serialize_cdr)
        self._seq = {"imu": 0, "lidar": 0}
        self.n_imu = 0
        self.n_scans = 0

    def __enter__(self) -> Self:
        if self.ros1:
            from rosbags.rosbag1 import Writer

            self._writer = Writer(self.path)
        else:
            from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if self.fmt == "mcap" else StoragePlugin.SQLITE3
            self._writer = Writer(self.path, version=8, storage_plugin=plugin)
            if self.fmt == "mcap":
                self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._writer.open()
        self._conn_imu = self._writer.add_connection(self.model.imu_topic, "sensor_msgs/msg/Imu",
                                                     typestore=self.typestore)
        if self.model.driver == "livox":
            register_livox_types(self.typestore)
            lidar_type = LIVOX_TYPES[0 if self.ros1 else 1]
        else:
            lidar_type = "sensor_msgs/msg/PointCloud2"
        self._conn_lidar = self._writer.add_connection(self.model.lidar_topic, lidar_type,
                                                       typestore=self.typestore)
        return self

    def __exit__(self, *exc) -> None:
        self._writer.close()

    def _header(self, kind: str, stamp_ns: int, frame_id: str):
        stamp = self._Time(sec=int(stamp_ns // 1_000_000_000),
                           nanosec=int(stamp_ns % 1_000_000_000))
        if self.ros1:
            seq = self._seq[kind]
            self._seq[kind] += 1
            return self._Header(seq=seq, stamp=stamp, frame_id=frame_id)
        return self._Header(stamp=stamp, frame_id=frame_id)

    def write_imu(self, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                  stamp_offset_ns: int = 0) -> None:
        """Write IMU samples (absolute int64 ns sample times, IMU frame; the accelerometer in
        m/s^2, written in the model's :attr:`~adalio.sim.lidar.LidarModel.imu_accel_unit`),
        recorded at their time and stamped ``stamp_offset_ns`` later (an IMU clock running ahead
        of the LiDAR's)."""
        if self.model.imu_accel_unit == "g":
            accel = np.asarray(accel) / G_TO_M_S2
        ocov = np.zeros(9)
        ocov[0] = -1.0
        zero9 = np.zeros(9)
        quat = self._Quat(x=0.0, y=0.0, z=0.0, w=1.0)
        for t, w, a in zip(t_ns.tolist(), gyro.tolist(), accel.tolist(), strict=True):
            msg = self._Imu(header=self._header("imu", t + stamp_offset_ns, self.model.imu_frame),
                            orientation=quat,
                            orientation_covariance=ocov,
                            angular_velocity=self._Vec(x=w[0], y=w[1], z=w[2]),
                            angular_velocity_covariance=zero9,
                            linear_acceleration=self._Vec(x=a[0], y=a[1], z=a[2]),
                            linear_acceleration_covariance=zero9)
            self._writer.write(self._conn_imu, t, self._serialize(msg, "sensor_msgs/msg/Imu"))
            self.n_imu += 1

    def write_sweep(self, sweep: SweepPoints, stamp_ns: int, record_ns: int) -> int:
        """Write one sweep; returns the number of points in the message."""
        if self.model.driver == "livox":
            return self._write_custom_msg(sweep, stamp_ns, record_ns)
        if self.model.driver == "ouster":
            C, K = self.model.columns, self.model.channels
            order = np.arange(C * K).reshape(C, K).T.ravel()
            v = sweep.valid[order]
            rng_mm = np.where(v, np.round(sweep.range_m[order].astype(np.float64) * 1000.0), 0)
            cols = {"x": sweep.xyz_lidar_m[order, 0], "y": sweep.xyz_lidar_m[order, 1],
                    "z": sweep.xyz_lidar_m[order, 2], "intensity": sweep.intensity[order],
                    "t": (sweep.t_ns[order] - stamp_ns).astype(np.uint32),
                    "reflectivity": np.clip(sweep.intensity[order], 0, 255).astype(np.uint16),
                    "ring": sweep.ring[order],
                    "ambient": np.where(v, 40, 0).astype(np.uint16),
                    "range": rng_mm.astype(np.uint32)}
            layout, height, width, dense = OUSTER_LAYOUT, K, C, False
        else:
            v = sweep.valid
            cols = {"x": sweep.xyz_lidar_m[v, 0], "y": sweep.xyz_lidar_m[v, 1],
                    "z": sweep.xyz_lidar_m[v, 2], "intensity": sweep.intensity[v],
                    "ring": sweep.ring[v]}
            layout, height, width, dense = XT32_LAYOUT, 1, int(v.sum()), True
            if self.model.driver == "velodyne":
                cols["ring"] = (self.model.channels - 1 - sweep.ring[v]).astype(np.uint16)
                cols["time"] = ((sweep.t_ns[v] - stamp_ns) * 1e-9).astype(np.float32)
                layout = VELODYNE_LAYOUT
            else:
                cols["timestamp"] = sweep.t_ns[v] * 1e-9
        step = VELODYNE_POINT_STEP if layout is VELODYNE_LAYOUT else POINT_STEP
        data, fields = encode_pointcloud2(cols, layout, step)
        msg = self._Cloud(
            header=self._header("lidar", stamp_ns, self.model.lidar_frame), height=height,
            width=width,
            fields=[self._Field(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields],
            is_bigendian=False, point_step=step, row_step=step * width,
            data=np.frombuffer(data, dtype=np.uint8), is_dense=dense)
        self._writer.write(self._conn_lidar, record_ns,
                           self._serialize(msg, "sensor_msgs/msg/PointCloud2"))
        self.n_scans += 1
        return height * width

    def _write_custom_msg(self, sweep: SweepPoints, stamp_ns: int, record_ns: int) -> int:
        """Write one frame as a Livox ``CustomMsg``: its valid returns in firing order,
        ``timebase`` and header stamp ``stamp_ns`` (the frame's first firing)."""
        v = sweep.valid
        pts = livox_points((sweep.t_ns[v] - stamp_ns).astype(np.uint32), sweep.xyz_lidar_m[v],
                           np.clip(sweep.intensity[v], 0, 255).astype(np.uint8),
                           np.zeros(int(v.sum()), np.uint8), sweep.ring[v].astype(np.uint8))
        cloud = LivoxCloud(stamp_ns=int(stamp_ns), frame_id=self.model.lidar_frame,
                           timebase_ns=int(stamp_ns), points=pts)
        seq = self._seq["lidar"]
        self._seq["lidar"] += 1
        self._writer.write(self._conn_lidar, record_ns,
                           build_custom_msg(cloud, ros2=not self.ros1, seq=seq))
        self.n_scans += 1
        return len(pts)
