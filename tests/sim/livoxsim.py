"""Reading the simulated Livox sequences in the tests (tests/sim/test_sim_livox.py,
test_sim_avia.py): each topic's messages, a frame's points, their directions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from adalio.io.bag import Bag
from adalio.io.livox import LivoxCloud
from adalio.sim import simulate
from adalio.sim.generate import START_NS

PERIOD_NS = 100_000_000
"""The models' 10 Hz frames."""


def messages(bag_path: Path) -> dict[str, list[tuple[int, object]]]:
    """Each topic's (record time ns, message), Livox frames as :class:`LivoxCloud`."""
    out: dict[str, list] = {}
    with Bag(bag_path) as bag:
        for topic, t_ns, msg in bag.messages([t.name for t in bag.topics()]):
            out.setdefault(topic, []).append((t_ns, msg))
    return out


def frame_xyz(cloud: LivoxCloud) -> np.ndarray:
    """(N, 3) float64 points of a frame, LiDAR frame."""
    p = cloud.points
    return np.column_stack([p["x"], p["y"], p["z"]]).astype(np.float64)


def az_el_deg(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth (from x towards y, -180..180) and elevation (towards z) in the points' frame,
    degrees."""
    return (np.degrees(np.arctan2(points[:, 1], points[:, 0])),
            np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))))


def noise_free_walk(tmp_dir: Path, lidar: str) -> tuple[object, dict, dict[str, list]]:
    """4 s in the hall without sensor noise (still for 2.5 s, then walking off), seed 3: the
    sequence, its ``meta.json`` and its messages (:func:`messages`)."""
    import json

    res = simulate("hall", tmp_dir, duration_s=4.0, lidar=lidar, noise_scale=0.0, seed=3)
    return res, json.loads(res.meta_path.read_text()), messages(res.bag_path)


def custommsg_frames(res, meta: dict, msgs: dict[str, list]) -> list[LivoxCloud]:
    """The walk's LiDAR frames, after checking what every Livox model's share: the ROS1 types
    and topics, one frame a period stamped and based at its start and recorded at its end, in
    ``livox_frame``, the points ``meta.json`` counts."""
    with Bag(res.bag_path) as bag:
        types = {t.name: t.msgtype for t in bag.topics()}
    assert types == {"/livox/lidar": "livox_ros_driver/msg/CustomMsg",
                     "/livox/imu": "sensor_msgs/msg/Imu"}
    frames = msgs["/livox/lidar"]
    assert len(frames) == meta["n_scans"] == 40
    assert sum(len(c.points) for _, c in frames) == meta["n_points"]
    for k, (record_ns, cloud) in enumerate(frames):
        start = START_NS + k * PERIOD_NS
        assert cloud.timebase_ns == cloud.stamp_ns == start and record_ns == start + PERIOD_NS
        assert cloud.frame_id == "livox_frame"
    return [c for _, c in frames]
