"""The scan's own local surface (``lio/local_surface.py``) against the simulator's true faces."""

from __future__ import annotations

import numpy as np
import pytest

from adalio.config import Config
from adalio.lio.ivox import IVox
from adalio.lio.local_surface import LocalSurface, disagrees
from adalio.lio.odometry import _Association
from adalio.lio.state import State
from adalio.lio.voxel import voxel_downsample, voxel_downsample_with_index
from adalio.sim.generate import START_NS, T_IMU_LIDAR_HILTI, build_trajectory
from adalio.sim.lidar import RayCaster, SweepSimulator, lidar_model
from adalio.sim.scenes import build_scene
from adalio.types import ScanStats

T_IL = np.asarray(T_IMU_LIDAR_HILTI, dtype=np.float64)


def _simulator(scene: str, seed: int, model: str, columns: int | None = None):
    scn = build_scene(scene, seed)
    caster = RayCaster(scn.mesh, seed)
    traj = build_trajectory(scn, T_IL, seed)
    return SweepSimulator(caster, traj, lidar_model(model, columns), T_IL, START_NS), traj, caster


def _lidar_pose(traj, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s = traj.sample((np.asarray(t_ns, dtype=np.int64) - START_NS) * 1e-9)
    return s.R_world_imu @ T_IL[:3, :3], s.p_world_imu_m + s.R_world_imu @ T_IL[:3, 3]


def _sweep_at_end(sim, traj, t_start_ns: int, seed: int):
    """One sweep: raw points, the same points undistorted to the sweep end with the true poses,
    rings, true face normals (world) and the end pose (R, p of the LiDAR in the world)."""
    sw = sim.sweep(t_start_ns, np.random.default_rng(seed))
    v = sw.valid
    raw = sw.xyz_lidar_m[v].astype(np.float64)
    R, p = _lidar_pose(traj, sw.t_ns[v])
    world = np.einsum("nij,nj->ni", R, raw) + p
    R_e, p_e = _lidar_pose(traj, np.array([sw.t_ns[v].max()]))
    end = (world - p_e[0]) @ R_e[0]
    face_n = np.where((sw.face[v] >= 0)[:, None], sim.caster.face_normals[sw.face[v]], np.nan)
    return raw, end, sw.ring[v], face_n, world, (R_e[0], p_e[0])


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c = np.abs(np.sum(a * b, axis=1)) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


@pytest.mark.parametrize(("scene", "model", "columns"), [
    ("stairs_garage", "xt32", 2000), ("stairs_garage", "xt32", 512),
    ("spiral", "xt32", 2000), ("corridor", "ouster64", 1024)])
def test_local_planes_match_the_true_faces(scene: str, model: str, columns: int) -> None:
    """Every judged patch's normal is the true face's normal of the point it stands for (the
    simulator's ray-cast face), on XT-32 and OS1-64 sweeps at 512-2000 columns, and the window
    keeps its angular size (1.5 ring spacings) at every column count."""
    sim, traj, _ = _simulator(scene, 0, model, columns)
    raw, end, ring, face_n, _, (R_e, _) = _sweep_at_end(sim, traj, START_NS + 4_000_000_000, 0)
    rows = np.arange(0, raw.shape[0], 2)  # decimated as preprocess.point_filter_num 2
    surf = LocalSurface(raw, end, ring, rows, 1.5)
    elev = np.radians(np.asarray(sim.model.elevations_deg))
    assert surf.ring_step_rad == pytest.approx(np.median(np.abs(np.diff(elev))), rel=0.01)
    assert surf.col_step_rad == pytest.approx(2 * np.pi / columns, rel=0.01)
    assert abs(surf.half_width * surf.col_step_rad - 1.5 * surf.ring_step_rad) \
        <= 0.5 * surf.col_step_rad + 1e-9

    down, vop = voxel_downsample_with_index(end[rows], 0.1)
    member = surf.members(down, vop)
    normals, judged = surf.normals(down, vop, 10.0)  # at every range, for the accuracy
    assert judged.sum() >= 0.3 * len(judged)  # measured: 45-57 %
    near_normals, near = surf.normals(down, vop, 0.1)  # the default limit
    rng = np.linalg.norm(end[member], axis=1)
    assert near.any() and not np.any(near & (rng > surf.max_range_m(0.1)))
    np.testing.assert_array_equal(near_normals[near], normals[near])
    err = _angle_deg(normals[judged] @ R_e.T, face_n[member[judged]])
    # measured: 99th percentile 7-14 degrees, 0.1-0.2 % beyond 30 degrees
    assert np.percentile(err, 90) < 10.0, np.percentile(err, [50, 90, 99])
    assert np.mean(err > 30.0) < 0.01, np.percentile(err, [50, 90, 99])


def test_ring_labels_are_only_labels() -> None:
    """Renumbering the rings (drivers count top-first, bottom-first or interleaved) changes
    nothing: neighbours come from measured elevations."""
    sim, traj, _ = _simulator("stairs_garage", 1, "xt32", 1024)
    raw, end, ring, _, _, _ = _sweep_at_end(sim, traj, START_NS + 5_000_000_000, 1)
    rows = np.arange(raw.shape[0])
    down, vop = voxel_downsample_with_index(end, 0.1)
    n1, j1 = LocalSurface(raw, end, ring, rows, 1.5).normals(down, vop, 0.1)
    relabel = np.random.default_rng(3).permutation(1000)[:32].astype(np.uint16) + 7
    n2, j2 = LocalSurface(raw, end, relabel[ring], rows, 1.5).normals(down, vop, 0.1)
    assert j1.sum() > 100
    np.testing.assert_array_equal(j1, j2)
    np.testing.assert_allclose(np.abs(np.sum(n1 * n2, axis=1))[j1], 1.0, atol=1e-9)


def test_dropped_rows_are_the_rows_whose_map_plane_is_wrong() -> None:
    """What the check is for: in the stairwell, against a map built from true poses, the rows
    it drops are mostly rows whose fitted map plane is more than 30° off the true face of their
    point, and it drops few of the rest."""
    cfg = Config()
    sim, traj, _ = _simulator("stairs_garage", 1, "xt32", 2000)
    ivox = IVox.from_config(cfg.map)
    dropped_wrong = dropped = wrong = right = dropped_right = 0
    for k, t_s in enumerate(np.arange(8.0, 14.01, 0.5)):
        raw, end, ring, face_n, world, (R_e, p_e) = _sweep_at_end(
            sim, traj, START_NS + int(t_s * 1e9), k)
        rows = np.arange(0, raw.shape[0], 2)
        if k:
            down, vop = voxel_downsample_with_index(end[rows], 0.1)
            surf = LocalSurface(raw, end, ring, rows, 1.5)
            member = surf.members(down, vop)
            R_wi = R_e @ T_IL[:3, :3].T
            x = State(R=R_wi, p=p_e - R_wi @ T_IL[:3, 3], R_LI=T_IL[:3, :3].copy(),
                      t_LI=T_IL[:3, 3].copy())
            assoc = _Association(down, ivox, cfg, 2.0, 0.025, 0.1)
            assoc.measure(x, True)
            sel = assoc.selected
            normals, judged = surf.normals(down, vop, 10.0)
            bad = disagrees(assoc.normals, normals, judged, R_e, 30.0) & sel
            off = (_angle_deg(assoc.normals, face_n[member]) > 30.0) & sel
            dropped += bad.sum()
            dropped_wrong += (bad & off).sum()
            wrong += off.sum()
            right += (sel & ~off).sum()
            dropped_right += (sel & ~off & bad).sum()
        ivox.add_points(voxel_downsample(world[::2], 0.1), 0.1)
    assert wrong > 50 and dropped > 50
    precision = dropped_wrong / dropped
    recall = dropped_wrong / wrong
    # measured: 1.9 % of the rows are wrong; the check drops 0.33 %, 83 % of them wrong (15 %
    # of the wrong rows), and 0.06 % of the right ones
    assert precision > 0.6, (precision, recall)
    assert recall > 0.1, (precision, recall)
    assert dropped_right / right < 0.005, dropped_right / right


def _odometry_run(overrides: dict, rings: bool = True):
    """8 s of the stairwell (seed 1) at 512 columns through the sequencer and the odometry: poses (t_ns, p)
    and the odometry."""
    from adalio.config import load_config
    from adalio.io.bag import Bag
    from adalio.io.sequencer import Sequencer
    from adalio.lio.odometry import Odometry
    from adalio.pipeline import resolve_extrinsic
    from adalio.sim import cached_sequence
    from adalio.types import Scan

    sim = cached_sequence("stairs_garage", seed=1, duration_s=8.0, columns=512)
    cfg = load_config(config_file=sim.config_path, overrides=overrides)
    poses = []
    with Bag(sim.bag_path) as bag:
        lt, it = bag.select_topics(cfg.sensor)
        T, _ = resolve_extrinsic(bag, lt, it, cfg)
        cfg.sensor.T_imu_lidar = T.tolist()
        odom = Odometry(cfg)
        for item in Sequencer(bag, lt, it, cfg.sensor):
            if isinstance(item, Scan):
                assert item.ring is not None
                est = odom.add_scan(item.points_lidar, item.t_ns, item.ring if rings else None)
                if est is not None:
                    poses.append(np.r_[est.t_ns, est.T_world_imu[:3, 3]])
            else:
                odom.add_imu(item.t_ns, item.gyro_rad_s, item.accel_m_s2)
    return np.array(poses), odom


def test_the_odometry_drops_rows_only_through_the_check() -> None:
    """The check's own path (every point in range undistorted, then decimated) changes nothing
    else: with an angle no plane can exceed, and without rings (a warning, once), the poses are
    the check-off poses to the bit; with the default angle it drops a few rows, which moves the
    poses by centimetres at most."""
    base, _ = _odometry_run({})
    assert len(base) > 20
    never, odom = _odometry_run({"filter.local_surface_check": True,
                                 "filter.local_surface_max_angle_deg": 90.0})
    np.testing.assert_array_equal(never, base)
    assert odom.local_surface_rows[0] == 0 and odom.local_surface_rows[1] > 1000
    with pytest.warns(UserWarning, match="no ring") as caught:
        blind, odom = _odometry_run({"filter.local_surface_check": True}, rings=False)
    assert len([w for w in caught if "no ring" in str(w.message)]) == 1
    np.testing.assert_array_equal(blind, base)
    assert odom.local_surface_rows == [0, 0]
    checked, odom = _odometry_run({"filter.local_surface_check": True})
    dropped, rows = odom.local_surface_rows
    assert 0 < dropped < 0.05 * rows
    assert np.max(np.abs(checked[:, 1:] - base[:, 1:])) < 0.05


def test_rings_that_do_not_match_the_points_are_refused() -> None:
    from adalio.errors import InputError
    from adalio.lio.odometry import Odometry

    odom = Odometry(Config())
    odom.initialized = True
    odom.cfg.filter.local_surface_check = True
    pts = np.ones((10, 3))
    with pytest.raises(InputError, match="ring must be"):
        odom._preprocess(pts, np.arange(10, dtype=np.int64), np.zeros(9, np.int64), ScanStats())


def test_livox_lines_that_do_not_match_the_points_are_refused_by_their_own_name() -> None:
    from adalio.errors import InputError
    from adalio.lio.odometry import Odometry

    odom = Odometry(Config())
    pts = np.ones((10, 3))
    t = np.arange(10, dtype=np.int64)
    for bad in (np.zeros(9, np.int64), np.zeros(10)):  # short; not integers
        with pytest.raises(InputError, match=r"add_scan: line must be \(N,\) integer Livox"):
            odom.add_scan(pts, t, line=bad)
    with pytest.raises(InputError, match="add_scan: ring must be"):
        Odometry(Config()).add_scan(pts, t, ring=np.zeros(9, np.int64))
