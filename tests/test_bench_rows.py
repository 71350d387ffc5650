"""``bench_rows.pull``: the step one update takes on a scan's rows from a given pose. Checked
against a known offset in a box room: at the true pose the rows pull nowhere, from a pose off
by a few centimetres or a fraction of a degree they pull it back by that much. And
``--future-s``: which sweeps a sweep's map holds, and that the later ones sit at their true
poses (a simulated hall, where the rows pull nowhere at the truth)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_rows import census, map_sweeps, nominal_prior, pull

from adalio.config import Config
from adalio.lio import so3
from adalio.lio.ivox import IVox
from adalio.lio.odometry import _Association
from adalio.lio.state import State

ROOM_LO = np.array([-4.0, -3.0, -1.2])
ROOM_HI = np.array([5.0, 2.5, 1.8])


def _room_points(rng: np.random.Generator, n_per_face: int, noise_m: float) -> np.ndarray:
    """Points on the six faces of the box room, with normal noise, plus a box on the floor so
    that the yaw is seen by more than the corners."""
    faces = []
    for axis in range(3):
        for side in (ROOM_LO, ROOM_HI):
            p = rng.uniform(ROOM_LO, ROOM_HI, size=(n_per_face, 3))
            p[:, axis] = side[axis] + rng.normal(scale=noise_m, size=n_per_face)
            faces.append(p)
    lo, hi = np.array([1.0, 0.5, ROOM_LO[2]]), np.array([2.0, 1.5, -0.4])
    for axis in range(2):
        for side in (lo, hi):
            p = rng.uniform(lo, hi, size=(n_per_face // 8, 3))
            p[:, axis] = side[axis] + rng.normal(scale=noise_m, size=n_per_face // 8)
            faces.append(p)
    return np.vstack(faces)


def _pull_from(offset: np.ndarray, seed: int = 0) -> tuple[np.ndarray, State]:
    """The pull at a pose off the true one by ``offset`` ([δp, δθ], world frame)."""
    rng = np.random.default_rng(seed)
    cfg = Config()
    deg = cfg.adaptive.degenerate
    ivox = IVox.from_config(cfg.map)
    ivox.add_points(_room_points(rng, 6000, 0.003), deg.voxel_size_m)
    R_true = so3.exp(np.array([0.02, -0.03, 0.7]))
    p_true = np.array([0.3, -0.2, 0.1])
    scan_world = _room_points(rng, 1500, 0.003)
    scan_world = scan_world[np.linalg.norm(scan_world - p_true, axis=1) > 0.5]
    points_lidar = (scan_world - p_true) @ R_true  # R_LI = I, t_LI = 0
    x = State(R=so3.exp(offset[3:]) @ R_true, p=p_true + offset[:3], R_LI=np.eye(3),
              t_LI=np.zeros(3))
    assoc = _Association(points_lidar, ivox, cfg, deg.search_radius_m, deg.plane_margin_m,
                         deg.voxel_size_m, prior_pose_cov=nominal_prior())
    H, r = assoc.measure(x, True)
    return pull(H, r, x.R, cfg.filter.laser_point_cov), x


def test_rows_on_the_right_planes_pull_nowhere_at_the_truth():
    step, _ = _pull_from(np.zeros(6))
    assert np.all(np.abs(step[:3]) < 1e-3)
    assert np.all(np.abs(np.degrees(step[3:])) < 0.01)


@pytest.mark.parametrize("offset", [
    np.array([0.0, 0.0, 0.02, 0.0, 0.0, 0.0]),
    np.array([-0.015, 0.01, 0.0, 0.0, 0.0, 0.0]),
    np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.radians(0.2)]),
    np.array([0.0, 0.0, 0.0, np.radians(0.2), 0.0, 0.0]),
])
def test_rows_pull_an_offset_pose_back_by_the_offset(offset):
    """The step is the world-frame correction: it undoes a height, a horizontal shift, a yaw or
    a roll about the world's x (the room's pose is turned 40° in yaw, so a rotation left in the
    body frame would be off by a quarter)."""
    step, _ = _pull_from(offset)
    moved = np.flatnonzero(offset)
    assert np.allclose(step[moved], -offset[moved], rtol=0.2)
    rest = np.setdiff1d(np.arange(6), moved)
    scale = np.where(rest < 3, 2e-3, np.radians(0.02))
    assert np.all(np.abs(step[rest]) < scale)


def test_a_sweeps_map_holds_the_earlier_sweeps_and_the_next_seconds_never_itself():
    times = np.arange(2.0, 4.0, 0.1)  # as census builds them, float steps included
    assert map_sweeps(times, 5, 0.0).tolist() == [0, 1, 2, 3, 4]
    assert map_sweeps(times, 5, 0.3).tolist() == [0, 1, 2, 3, 4, 6, 7, 8]
    assert map_sweeps(times, 0, 0.25).tolist() == [1, 2]
    assert map_sweeps(times, 19, 1.0).tolist() == list(range(19))


def test_later_sweeps_join_the_map_at_their_true_poses():
    """In the hall the rows pull nowhere at the truth, with or without the next 0.5 s of sweeps
    in the map. Later sweeps placed 1 cm too high (checked by hand) pull the height by 2.6 mm."""
    for future_s in (0.0, 0.5):
        c = census("hall", 0, "xt32", 256, 6.0, 7.0, 30.0, with_pull=True, warmup_s=1.0,
                   future_s=future_s)
        assert abs(c["pull_z_mm"]) < 0.5
        assert abs(c["pull_along_mm"]) < 0.5
        assert c["rows"] > 10_000


def test_a_20_hz_census_holds_twice_the_sweeps_and_pulls_nowhere_in_the_hall():
    """``lidar_rate_hz``: the window holds the sweeps of the given rate (twice the 10 Hz ones,
    each with the same columns, so about twice the rows), each undistorted at its own true
    poses: in the hall the rows still pull nowhere at the truth."""
    c10 = census("hall", 0, "xt32", 256, 6.0, 7.0, 30.0, with_pull=True, warmup_s=1.0)
    c20 = census("hall", 0, "xt32", 256, 6.0, 7.0, 30.0, with_pull=True, warmup_s=1.0,
                 lidar_rate_hz=20.0)
    assert 1.7 < c20["rows"] / c10["rows"] < 2.3
    assert abs(c20["pull_z_mm"]) < 0.5
    assert abs(c20["pull_along_mm"]) < 0.5
