"""The Livox Avia-like LiDAR (``simulate(lidar="avia")``): Livox ``CustomMsg`` frames of 6 lasers
firing in turn, every return inside the 70.4 x 77.2 deg box around the LiDAR's x axis and the
box's edges reached; points that, placed by the ground truth at their own times, lie on the
scene; frames that never repeat and fill the view together; a view along the walk and level;
the ``livox_avia`` preset; and adalio's reader taking the sequence with its own config."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import trimesh
from livoxsim import PERIOD_NS, az_el_deg, custommsg_frames, frame_xyz, noise_free_walk
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp

from adalio.config import load_config
from adalio.io.bag import Bag
from adalio.io.livox import LivoxCloud
from adalio.io.sequencer import Sequencer
from adalio.sim import simulate
from adalio.sim.generate import START_NS, _config_dict, mesh_distance_m
from adalio.sim.lidar import LIDAR_MODELS, RayCaster, lidar_model, rosette_directions
from adalio.types import ImuBatch, Scan

POINTS_PER_FRAME = 24_000
"""240 000 points/s: the i-th firing of a frame at ``i * PERIOD_NS // POINTS_PER_FRAME``."""
LASERS = 6
HALF_H_DEG, HALF_V_DEG = 70.4 / 2.0, 77.2 / 2.0
EPS_DEG = 1e-3
"""float32 coordinates give directions to about 1e-5 deg."""


class GroundTruth:
    """The sequence's ``gt.tum`` (IMU in the world = IMU at t0) and ``meta.json``'s extrinsic
    and ``T_scene_world``: where a LiDAR-frame point fired at a time lies in the scene frame."""

    def __init__(self, res) -> None:
        meta = json.loads(res.meta_path.read_text())
        rows = np.loadtxt(res.gt_path)
        self.t_s = rows[:, 0] - rows[0, 0]
        self.p_world_m = rows[:, 1:4]
        self._slerp = Slerp(self.t_s, Rotation.from_quat(rows[:, 4:]))
        self.T_il = np.asarray(meta["T_imu_lidar"])
        self.T_sw = np.asarray(meta["T_scene_world"])

    def position_scene_m(self, t_s: np.ndarray) -> np.ndarray:
        p_w = np.column_stack([np.interp(t_s, self.t_s, self.p_world_m[:, i]) for i in range(3)])
        return p_w @ self.T_sw[:3, :3].T + self.T_sw[:3, 3]

    def R_scene_lidar(self, t_s: np.ndarray) -> np.ndarray:
        return self.T_sw[:3, :3] @ self._slerp(t_s).as_matrix() @ self.T_il[:3, :3]

    def points_scene_m(self, xyz_lidar: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        return (np.einsum("nij,nj->ni", self.R_scene_lidar(t_s), xyz_lidar)
                + self.position_scene_m(t_s)
                + np.einsum("nij,j->ni", self.T_sw[:3, :3] @ self._slerp(t_s).as_matrix(),
                            self.T_il[:3, 3]))


def _times_s(cloud: LivoxCloud, keep: np.ndarray | slice = slice(None)) -> np.ndarray:
    """Seconds since the sequence's start of the points' firing, ``timebase + offset_time``."""
    return (cloud.timebase_ns - START_NS
            + cloud.points["offset_time"][keep].astype(np.int64)) * 1e-9


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """4 s in the hall without sensor noise: still for 2.5 s, then walking off (0.6 m by 4 s)."""
    return noise_free_walk(tmp_path_factory.mktemp("avia"), "avia")


def test_frames_are_livox_custom_msgs_of_six_lasers_firing_in_turn(walk):
    res, meta, msgs = walk
    assert {m.header.frame_id for _, m in msgs["/livox/imu"]} == {"livox_frame"}
    frames = custommsg_frames(res, meta, msgs)
    for cloud in frames:
        p = cloud.points
        assert 0.95 * POINTS_PER_FRAME < len(p) <= POINTS_PER_FRAME  # a closed hall
        off = p["offset_time"].astype(np.int64)
        assert off.min() >= 0 and off.max() < PERIOD_NS and np.all(np.diff(off) > 0)
        i = -((-off * POINTS_PER_FRAME) // PERIOD_NS)  # the firing whose slot it is
        assert np.array_equal(i * PERIOD_NS // POINTS_PER_FRAME, off)
        assert np.array_equal(p["line"], i % LASERS)
        assert np.all(p["tag"] == 0) and p["reflectivity"].max() > 100
        r = np.linalg.norm(frame_xyz(cloud), axis=1)
        assert r.min() >= 1.0 - 1e-6 and r.max() <= 100.0  # its 1 m blind zone
    lines = np.bincount(np.concatenate([c.points["line"] for c in frames]))
    assert len(lines) == LASERS and lines.min() > 0.16 * lines.sum()


def test_every_return_lies_in_the_box_around_x_and_reaches_its_edges(walk):
    """70.4 deg of azimuth by 77.2 deg of elevation centred on the LiDAR's x axis, every edge
    reached within 0.2 deg; the returns densest at the centre."""
    _, _, msgs = walk
    az, el = az_el_deg(np.concatenate([frame_xyz(c) for _, c in msgs["/livox/lidar"]]))
    assert np.abs(az).max() <= HALF_H_DEG + EPS_DEG and np.abs(el).max() <= HALF_V_DEG + EPS_DEG
    assert az.max() > HALF_H_DEG - 0.2 and az.min() < -HALF_H_DEG + 0.2
    assert el.max() > HALF_V_DEG - 0.2 and el.min() < -HALF_V_DEG + 0.2
    r = np.hypot(az / HALF_H_DEG, el / HALF_V_DEG)  # 0 at the centre, 1 on the inscribed ellipse

    def per_area(lo: float, hi: float) -> float:
        return np.mean((r >= lo) & (r < hi)) / (hi**2 - lo**2)

    assert per_area(0.0, 0.15) > 3.0 * per_area(0.4, 0.6)


def test_points_lie_on_the_scene_at_their_own_firing_times(walk):
    """Each point through the ground-truth IMU pose at its own time (``timebase +
    offset_time``) and the extrinsic lies on the mesh; through the frame's first pose instead,
    the walking frame's points do not."""
    res, _, msgs = walk
    gt = GroundTruth(res)
    caster = RayCaster(trimesh.load(res.bag_path.parent / "scene.ply"))
    for k in (5, 38):  # still, and walking at about 0.8 m/s
        cloud = msgs["/livox/lidar"][k][1]
        keep = np.arange(0, len(cloud.points), 60)
        xyz, t_s = frame_xyz(cloud)[keep], _times_s(cloud, keep)
        d = mesh_distance_m(caster, gt.points_scene_m(xyz, t_s))
        assert np.median(d) < 1e-3 and np.mean(d > 5e-3) < 0.01, (k, np.median(d))
        if k == 38:
            d_first = mesh_distance_m(caster, gt.points_scene_m(xyz, np.full(len(keep),
                                                                              t_s.min())))
            assert np.median(d_first) > 0.005  # 5x the bound above


def test_frames_never_repeat_and_together_fill_the_view(walk):
    """Still frames (the same pose): consecutive frames' directions differ; one frame hits
    about a fifth of the box's 0.5 deg cells inside its inscribed ellipse (the circular-ish
    field of view), ten frames several times as many, twenty more still."""
    _, _, msgs = walk
    still = [frame_xyz(c) for _, c in msgs["/livox/lidar"][2:22]]  # 0.2-2.2 s: at rest
    dirs = [x / np.linalg.norm(x, axis=1, keepdims=True) for x in still]
    for a, b in itertools.pairwise(dirs):
        near, _ = cKDTree(a).query(b, distance_upper_bound=np.radians(0.01))
        assert np.mean(np.isfinite(near)) < 0.01
    cell = 0.5
    az_c, el_c = np.meshgrid(np.arange(-HALF_H_DEG, HALF_H_DEG, cell) + cell / 2,
                             np.arange(-HALF_V_DEG, HALF_V_DEG, cell) + cell / 2)
    fov_cells = int(np.sum(np.hypot(az_c / HALF_H_DEG, el_c / HALF_V_DEG) < 1.0))

    def cells_hit(xyz: np.ndarray) -> int:
        az, el = az_el_deg(xyz)
        return len(np.unique(np.floor((az + HALF_H_DEG) / cell) * 1000
                             + np.floor((el + HALF_V_DEG) / cell)))

    one, ten, twenty = (cells_hit(np.concatenate(still[:n])) for n in (1, 10, 20))
    assert 0.1 * fov_cells < one < 0.3 * fov_cells
    assert ten > 3.0 * one and ten > 0.85 * fov_cells
    assert twenty > ten


def test_the_view_looks_along_the_walk_and_level(walk):
    """Over the walk's last 1.2 s, each return's direction in the scene (through the ground
    truth at its firing time) against the travel (the ground truth's horizontal displacement)
    and gravity: the median azimuth straight ahead and the median elevation level, within 3
    deg (a rotated pattern, e.g. centred on the LiDAR's -x or y, would be 90-180 deg off)."""
    res, _, msgs = walk
    gt = GroundTruth(res)
    travel = gt.position_scene_m(np.array([4.0]))[0] - gt.position_scene_m(np.array([2.8]))[0]
    assert np.hypot(*travel[:2]) > 0.4
    x = np.array([travel[0], travel[1], 0.0]) / np.hypot(*travel[:2])
    z = np.array([0.0, 0.0, 1.0])  # the scene's up
    y = np.cross(z, x)
    az, el = [], []
    for _, cloud in msgs["/livox/lidar"][28:40]:
        d = frame_xyz(cloud)
        d_scene = np.einsum("nij,nj->ni", gt.R_scene_lidar(_times_s(cloud)), d)
        a, e = az_el_deg(d_scene @ np.column_stack([x, y, z]))
        az.append(a)
        el.append(e)
    assert abs(np.median(np.concatenate(az))) < 3.0
    assert abs(np.median(np.concatenate(el))) < 3.0


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    """0.6 s with sensor noise, in a ROS2 (sqlite3) bag."""
    return simulate("hall", tmp_path_factory.mktemp("avia_ros2"), duration_s=0.6, lidar="avia",
                    fmt="ros2", seed=5)


def test_each_model_s_config_names_its_preset():
    presets = {name: _config_dict(model, np.eye(4), 400.0)["preset"]
               for name, model in LIDAR_MODELS.items()}
    assert presets == {"xt32": "hilti2022", "ouster64": "ouster", "ouster128": "ouster",
                       "vlp16": "velodyne", "mid360": "livox_mid360", "avia": "livox_avia"}


@pytest.mark.parametrize("which", ["walk", "noisy"])
def test_adalio_reads_the_sequence_with_its_own_config(request, which):
    """The sequence's ``config.yaml`` names ``livox_avia`` (its preprocessing: every second
    point), keeps the simulated rig's topics and extrinsic, and through adalio's reader gives
    every frame as a scan of its points at ``timebase + offset_time`` inside the frame, the IMU
    found in g."""
    res = request.getfixturevalue(which)
    if which == "walk":
        res = res[0]
    meta = json.loads(res.meta_path.read_text())
    assert res.config_path.read_text().startswith("preset: livox_avia\n")
    cfg = load_config(config_file=res.config_path)
    np.testing.assert_allclose(cfg.sensor.T_imu_lidar, meta["T_imu_lidar"])
    assert cfg.preprocess.point_filter_num == 2  # the preset's (the defaults': 1)
    assert cfg.sensor.accel_unit == "auto"

    def read() -> tuple[tuple[str, str], list]:
        with Bag(res.bag_path) as bag:
            topics = bag.select_topics(cfg.sensor)
            return topics, list(Sequencer(bag, *topics, cfg.sensor))

    with pytest.warns(UserWarning, match="reports in g"):
        topics, items = read()
    assert topics == ("/livox/lidar", "/livox/imu")
    if which == "noisy":
        with Bag(res.bag_path) as bag:
            assert {t.name: t.msgtype for t in bag.topics()}["/livox/lidar"] == \
                "livox_ros_driver2/msg/CustomMsg"
    scans = [i for i in items if isinstance(i, Scan)]
    acc = np.concatenate([i.accel_m_s2 for i in items if isinstance(i, ImuBatch)])
    assert len(scans) == meta["n_scans"] and len(acc) == meta["n_imu"]
    assert sum(len(s.t_ns) for s in scans) == meta["n_points"]
    for k, s in enumerate(scans):
        start = START_NS + k * PERIOD_NS
        assert s.stamp_ns == start and s.t_ns.min() >= start and s.t_ns.max() < start + PERIOD_NS
        assert s.ring is None
    still = acc[: int(0.5 * meta["imu_rate_hz"])]  # at rest: gravity's reaction, in m/s^2
    assert np.linalg.norm(still.mean(axis=0)) == pytest.approx(9.81, abs=0.1)


@pytest.mark.parametrize(("columns", "rate_hz"), [(4000, 10.0), (600, 20.0), (20000, 5.0)])
def test_the_rosette_stays_in_the_box_at_any_columns_and_rate(columns, rate_hz):
    model = lidar_model("avia", columns, rate_hz)
    n = columns * LASERS
    for first in (0, 7 * n, 123_456 * n):
        d = rosette_directions(model, first)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
        az, el = az_el_deg(d)
        assert np.abs(az).max() <= HALF_H_DEG + 1e-9 and np.abs(el).max() <= HALF_V_DEG + 1e-9
