"""A recorded walk's handheld motion carried through a scene (``HandheldMotion``), checked
against a recording built here with a known hand motion, and on the real HILTI 2022 exp04
ground truth in the repository's test data."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from adalio.errors import InputError
from adalio.sim.generate import T_IMU_LIDAR_HILTI, build_trajectory, mesh_distance_m
from adalio.sim.lidar import RayCaster
from adalio.sim.scenes import build_scene
from adalio.sim.trajectory import NO_HAND, HandheldMotion

REAL = Path(__file__).parents[1] / "data" / "real" / "hilti2022_gt"
EXP04 = REAL / "exp_04_construction_upper_level_easy_2_2022-03-03-11-48-59_imu.txt"
F_HZ = 2.0
LAT_M, ROLL_RAD, PITCH_RAD = 0.03, np.deg2rad(2.0), np.deg2rad(1.5)


def _recording(path: Path, rate_hz: float = 10.0, span_s: float = 60.0) -> None:
    """A walk along a slow circle (radius 8 m, 0.9 m/s) with a known 2 Hz hand motion: 3 cm
    to the left, 2 degrees of roll about the walking direction, 1.5 degrees of pitch; the IMU
    axes are turned against the walking frame by a fixed mounting rotation."""
    t = np.arange(0.0, span_s, 1.0 / rate_hz)
    ph = 0.9 * t / 8.0
    ring = np.column_stack([8.0 * np.sin(ph), 8.0 * (1.0 - np.cos(ph)), np.full_like(t, 1.5)])
    fwd = np.column_stack([np.cos(ph), np.sin(ph), np.zeros_like(t)])
    left = np.column_stack([-np.sin(ph), np.cos(ph), np.zeros_like(t)])
    wave = np.sin(2 * np.pi * F_HZ * t)
    p = ring + LAT_M * wave[:, None] * left
    R_walk = Rotation.from_euler("z", ph[:, None])
    R_hand = Rotation.from_euler("ZYX", np.column_stack(
        [np.zeros_like(t), PITCH_RAD * np.cos(2 * np.pi * F_HZ * t), ROLL_RAD * wave]))
    mount = Rotation.from_euler("xyz", [0.4, -1.1, 2.0])
    q = (R_walk * R_hand * mount).as_quat()
    assert np.allclose(fwd[:, :2], R_walk.apply([1.0, 0.0, 0.0])[:, :2])
    np.savetxt(path, np.column_stack([1.6e9 + t, p, q]), fmt="%.9f",
               header="t x y z qx qy qz qw")


def _amplitude(x: np.ndarray, rate_hz: float, f_hz: float) -> float:
    """Amplitude of the f_hz sinusoid in x (least squares on sin and cos)."""
    t = np.arange(len(x)) / rate_hz
    A = np.column_stack([np.sin(2 * np.pi * f_hz * t), np.cos(2 * np.pi * f_hz * t),
                         np.ones_like(t)])
    c = np.linalg.lstsq(A, x, rcond=None)[0]
    return float(np.hypot(c[0], c[1]))


def test_the_known_hand_motion_is_recovered_from_a_recording(tmp_path):
    path = tmp_path / "walk.txt"
    _recording(path)
    m = HandheldMotion.from_tum(path)
    inner = slice(500, -500)  # away from the ends, where the smoothing sees the file's edge
    off, att = m.offset_path_m[inner], m.attitude_rad[inner]
    rate = 100.0
    # the hand's 2 Hz motion, recovered on its own axis whatever the IMU's mounting
    assert _amplitude(off[:, 1], rate, F_HZ) == pytest.approx(LAT_M, rel=0.05)
    assert _amplitude(att[:, 2], rate, F_HZ) == pytest.approx(ROLL_RAD, rel=0.05)
    assert _amplitude(att[:, 1], rate, F_HZ) == pytest.approx(PITCH_RAD, rel=0.05)
    # and nothing on the other axes: the circle itself is the route, not the hand
    assert np.abs(off[:, [0, 2]]).max() < 0.1 * LAT_M
    assert np.abs(att[:, 0]).max() < 0.1 * ROLL_RAD


def test_a_scene_walk_carries_the_recorded_hand_motion(tmp_path):
    path = tmp_path / "walk.txt"
    _recording(path)
    hand = HandheldMotion.from_tum(path)
    scn = build_scene("hall", 0)
    T = np.asarray(T_IMU_LIDAR_HILTI)
    plain = build_trajectory(scn, T, 0)
    walk = build_trajectory(scn, T, 0, hand)
    # same route and speed profile; the rig's roll now carries the 2 Hz, 2 degree hand roll
    assert walk.duration_s == plain.duration_s
    t = np.arange(walk.static_s + 5.0, walk.duration_s - 5.0, 0.01)
    roll = walk.euler_zyx(t)[:, 2]
    assert _amplitude(roll, 100.0, F_HZ) == pytest.approx(ROLL_RAD, rel=0.1)
    assert _amplitude(plain.euler_zyx(t)[:, 2], 100.0, F_HZ) < 0.3 * ROLL_RAD
    p_walk, p_plain = walk.sample(t).p_world_imu_m, plain.sample(t).p_world_imu_m
    assert np.abs(p_walk - p_plain).max() < 0.15


def test_no_hand_is_a_recording_that_never_moves_off_its_path(tmp_path):
    """``--motion-from none`` (a robot's walk): the same walk as the hand extracted from a
    recording of a rig standing still (whose smoothed path is itself), and on a straight the
    rig keeps its height and attitude: no roll at all, pitch only where the route descends."""
    still = tmp_path / "still.txt"
    t = np.arange(0.0, 30.0, 0.01)
    np.savetxt(still, np.column_stack([1.6e9 + t, np.zeros((t.size, 3)),
                                       np.tile([0.0, 0.0, 0.0, 1.0], (t.size, 1))]))
    recorded = HandheldMotion.from_tum(still)
    assert np.abs(recorded.offset_path_m).max() < 1e-9
    assert np.abs(recorded.attitude_rad).max() < 1e-9
    scn = build_scene("corridor", 1)
    T = np.asarray(T_IMU_LIDAR_HILTI)
    robot = build_trajectory(scn, T, 1, HandheldMotion.load(NO_HAND))
    from_file = build_trajectory(scn, T, 1, recorded)
    ts = np.arange(0.0, robot.duration_s, 0.01)
    assert np.abs(robot.sample(ts).p_world_imu_m - from_file.sample(ts).p_world_imu_m).max() \
        < 1e-6
    eul = robot.euler_zyx(ts)
    assert np.abs(eul[:, 2]).max() < 1e-9  # roll
    hand = build_trajectory(scn, T, 1)  # the synthetic hand rolls by degrees
    assert np.abs(hand.euler_zyx(ts)[:, 2]).max() > np.deg2rad(1.0)
    p = robot.sample(ts).p_world_imu_m
    assert np.ptp(p[:, 2]) < 1e-6  # the corridor is level: the robot keeps its height


def test_a_robots_sequence_is_cached_under_its_own_key():
    """``cached_sequence(motion_from="none")``: its own cache key, the sequence's meta says so,
    and its ground truth never rolls (the synthetic hand's does)."""
    import json

    from adalio.sim import cached_sequence

    # read before asking for the other: the cache keeps only the sequence handed last from
    # eviction (the robot's went missing in a CI run once the hand's was simulated)
    robot = cached_sequence("hall", seed=0, duration_s=4.0, motion_from=NO_HAND)
    assert "-hhnone-" in robot.bag_path.parent.name
    assert json.loads((robot.bag_path.parent / "meta.json").read_text())["motion_from"] == NO_HAND
    q = np.loadtxt(robot.gt_path)[:, 4:8]
    hand = cached_sequence("hall", seed=0, duration_s=4.0)
    assert robot.bag_path.parent != hand.bag_path.parent
    roll_pitch = Rotation.from_quat(q).as_euler("ZYX")[:, 1:]
    q0 = Rotation.from_quat(q[0]).as_euler("ZYX")[1:]
    assert np.abs(roll_pitch - q0).max() < 1e-6  # the start's rest, then a level walk
    q_hand = np.loadtxt(hand.gt_path)[:, 4:8]
    tilt = Rotation.from_quat(q_hand).as_euler("ZYX")[:, 1:] - q0
    assert np.abs(tilt).max() > np.deg2rad(1.0)  # the synthetic hand tilts the rig by degrees


def test_the_real_exp04_walk_runs_through_every_scene_with_its_rates():
    """The real hand is livelier than the synthetic one (faster turns), and still fits the
    scenes' clearance."""
    hand = HandheldMotion.from_tum(EXP04)
    d_rate = np.degrees(np.gradient(hand.attitude_rad, 0.01, axis=0))
    assert np.sqrt(np.mean(d_rate**2)) > 5.0
    scn = build_scene("spiral", 1)
    traj = build_trajectory(scn, np.asarray(T_IMU_LIDAR_HILTI), 1, hand)
    s = traj.sample(np.arange(0.0, traj.duration_s, 0.1))
    assert mesh_distance_m(RayCaster(scn.mesh), s.p_world_imu_m).min() > 0.25


def test_playback_is_continuous_beyond_the_recording(tmp_path):
    path = tmp_path / "short.txt"
    _recording(path, span_s=8.0)
    m = HandheldMotion.from_tum(path)
    off, att = m.window(5 * len(m.offset_path_m), seed=3)
    step = np.abs(np.diff(np.column_stack([off, att]), axis=0)).max(axis=0)
    src = np.abs(np.diff(np.column_stack([m.offset_path_m, m.attitude_rad]), axis=0)).max(axis=0)
    assert np.all(step <= src + 1e-12)


@pytest.mark.parametrize("text", ["", "1 2 3\n", "0 0 0 0 0 0 0 1\n" * 30,
                                  "".join(f"{i} 0 0 0 0 0 0 1\n" for i in range(30))])
def test_a_file_that_is_no_walk_is_refused_naming_it(tmp_path, text):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(InputError, match="bad.txt"):
        HandheldMotion.from_tum(path)
