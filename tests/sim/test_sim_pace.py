"""A faster or slower walker (``simulate(pace=...)``, ``adalio simulate --pace``): the same route,
walked ``pace`` times as fast, with the hand and the gait keeping their times. The independent
truth is the walk at pace 1: its path densely sampled, its speed at the same distance along the
route, and the frequency of its steps."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from adalio.errors import InputError
from adalio.sim import cached_sequence, simulate
from adalio.sim.generate import T_IMU_LIDAR_HILTI, build_trajectory
from adalio.sim.scenes import build_scene
from adalio.sim.trajectory import NO_HAND, HandheldMotion

ADALIO = str(Path(sys.executable).with_name("adalio"))
T_IL = np.asarray(T_IMU_LIDAR_HILTI)


def _walk(traj, rate_hz: float):
    """The IMU's positions, distance walked and speed after the still start, at ``rate_hz``."""
    t = np.arange(traj.static_s, traj.duration_s, 1.0 / rate_hz)
    s = traj.sample(t)
    p = s.p_world_imu_m
    dist = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    return t, p, dist, np.linalg.norm(s.v_world_m_s, axis=1)


@pytest.mark.parametrize("scene", ["spiral", "hall"])
def test_a_pace_walks_the_same_route_that_many_times_as_fast(scene):
    scn = build_scene(scene, 0)
    robot = HandheldMotion.load(NO_HAND)  # no hand motion: the path is the route's alone
    walk1 = build_trajectory(scn, T_IL, 0, robot)
    _, p1, d1, v1 = _walk(walk1, 1000.0)
    tree = cKDTree(p1)
    for pace in (0.5, 2.0):
        traj = build_trajectory(scn, T_IL, 0, robot, pace=pace)
        _, p, d, v = _walk(traj, 200.0)
        assert abs(d[-1] - d1[-1]) < 1e-4 * d1[-1], (pace, d[-1], d1[-1])
        off, _ = tree.query(p)
        assert off.max() < 2e-3, (pace, off.max())  # 1.2 mm between the dense samples
        # past the start's ramp (2 s of time, a different distance at each pace) and before the
        # stop: the speed at the same distance along the route is pace times the walk's at 1
        mid = (d > 0.2 * d[-1]) & (d < 0.8 * d[-1])
        want = pace * np.interp(d[mid], d1, v1)
        assert np.max(np.abs(v[mid] - want) / want) < 0.01, pace
        assert (traj.walk_s < walk1.walk_s) == (pace > 1), (pace, traj.walk_s, walk1.walk_s)


def _step_hz(traj) -> float:
    """The frequency (Hz) of the largest peak of the height's spectrum in 1.5-2.5 Hz (the steps'
    bobbing) while the walker moves at full speed."""
    t = np.arange(traj.static_s + 4.0, traj.duration_s - 4.0, 0.01)
    z = traj.sample(t).p_world_imu_m[:, 2]
    z = z - np.polyval(np.polyfit(t, z, 3), t)
    f = np.fft.rfftfreq(8 * len(z), 0.01)
    power = np.abs(np.fft.rfft(z * np.hanning(len(z)), 8 * len(z)))
    band = (f > 1.5) & (f < 2.5)
    return float(f[band][np.argmax(power[band])])


def test_the_gait_keeps_its_time_at_another_pace():
    scn = build_scene("hall", 1)
    f1 = _step_hz(build_trajectory(scn, T_IL, 1))
    assert 1.75 < f1 < 2.05, f1  # the synthetic gait's 1.8-2.0 Hz
    for pace in (0.5, 2.0):
        assert abs(_step_hz(build_trajectory(scn, T_IL, 1, pace=pace)) - f1) < 0.03, pace


def _gt_horizontal_speed(gt: Path, lo_s: float, hi_s: float) -> float:
    """Mean horizontal speed (m/s) of a gt.tum between lo_s and hi_s after its first stamp."""
    a = np.loadtxt(gt)
    t = a[:, 0] - a[0, 0]
    keep = (t >= lo_s) & (t <= hi_s)
    xy = a[keep, 1:3]
    return float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1)) / (t[keep][-1] - t[keep][0]))


def test_a_simulated_sequence_at_twice_the_pace(tmp_path):
    walk = {"duration_s": 6.0, "columns": 64, "seed": 2}
    slow = simulate("corridor", tmp_path / "p1", **walk)
    fast = simulate("corridor", tmp_path / "p2", pace=2.0, **walk)
    assert json.loads(slow.meta_path.read_text())["pace"] == 1.0
    assert json.loads(fast.meta_path.read_text())["pace"] == 2.0
    # after the 2.5 s still start and the 2 s ramp, along the corridor's first straight
    v1 = _gt_horizontal_speed(slow.gt_path, 4.7, 6.0)
    v2 = _gt_horizontal_speed(fast.gt_path, 4.7, 6.0)
    assert 0.5 < v1 < 1.5, v1
    assert abs(v2 / v1 - 2.0) < 0.1, (v1, v2)
    cached = cached_sequence("corridor", pace=2.0, **walk)
    assert "-pace2-" in cached.bag_path.parent.name
    assert cached.gt_path.read_bytes() == fast.gt_path.read_bytes()


def test_a_pace_outside_0_25_to_3_is_refused(tmp_path):
    for pace in (0.2, 3.5, math.nan):
        with pytest.raises(InputError, match=r"^--pace must be 0.25-3 \(got "):
            simulate("hall", tmp_path / "s", duration_s=1.0, columns=64, pace=pace)
        with pytest.raises(InputError, match=r"^--pace must be 0.25-3 \(got "):
            cached_sequence("hall", duration_s=1.0, columns=64, pace=pace)
    assert not (tmp_path / "s").exists()
    proc = subprocess.run([ADALIO, "simulate", "--scene", "hall", "--out", str(tmp_path / "s"),
                           "--pace", "4"], capture_output=True, text=True, timeout=120,
                          check=False)
    both = proc.stdout + proc.stderr
    assert proc.returncode == 2, both
    lines = [ln for ln in both.splitlines() if ln.strip()]
    assert lines == ["error: --pace must be 0.25-3 (got 4)"], both
    assert not (tmp_path / "s").exists()
