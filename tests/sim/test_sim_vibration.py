"""A shaking IMU (``simulate(imu_vibration=...)``): while the rig moves, white noise of X times
the IMU's densities on its samples. The independent truth is the same walk without it (the same
seed), read back from both bags: the clouds and the still start's IMU samples the same, the
difference while moving white with the intended spread."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from adalio.errors import InputError
from adalio.sim import cached_sequence, simulate
from adalio.sim.imu import ImuNoise

WALK = {"seed": 4, "duration_s": 6.0, "columns": 64}
TIMES = 30.0


def _read(bag: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[bytes]]:
    """IMU stamps (ns), gyro, accelerometer, and every cloud's raw message."""
    t, gyro, accel, clouds = [], [], [], []
    with AnyReader([bag]) as reader:
        for conn, _, raw in reader.messages():
            if conn.msgtype.endswith("PointCloud2"):
                clouds.append(bytes(raw))
                continue
            msg = reader.deserialize(raw, conn.msgtype)
            t.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            w, a = msg.angular_velocity, msg.linear_acceleration
            gyro.append((w.x, w.y, w.z))
            accel.append((a.x, a.y, a.z))
    return np.array(t), np.array(gyro), np.array(accel), clouds


def test_the_imu_shakes_while_the_rig_moves_and_only_then(tmp_path):
    quiet = simulate("corridor", tmp_path / "quiet", **WALK)
    shaking = simulate("corridor", tmp_path / "shaking", imu_vibration=TIMES, **WALK)
    meta = json.loads(shaking.meta_path.read_text())
    assert meta["imu_vibration"] == TIMES
    assert json.loads(quiet.meta_path.read_text())["imu_vibration"] == 0.0
    t, g0, a0, c0 = _read(quiet.bag_path)
    t1, g1, a1, c1 = _read(shaking.bag_path)
    assert np.array_equal(t, t1)
    assert c0 == c1  # the clouds are the same, byte for byte
    assert shaking.gt_path.read_bytes() == quiet.gt_path.read_bytes()
    still = t < meta["start_time_ns"] + round(meta["static_s"] * 1e9)
    assert np.array_equal(g0[still], g1[still]) and np.array_equal(a0[still], a1[still])
    # at full strength (from 0.3 m/s: the corridor's walk reaches it about 1 s after setting off)
    full = t > meta["start_time_ns"] + round((meta["static_s"] + 1.5) * 1e9)
    noise, rate = ImuNoise(), float(meta["imu_rate_hz"])
    for got, density in ((g1 - g0, noise.gyro_noise_rad_s_sqrt_hz),
                         (a1 - a0, noise.accel_noise_m_s2_sqrt_hz)):
        d = got[full]
        want = TIMES * density * math.sqrt(rate)
        assert abs(d.std() / want - 1.0) < 0.05, (d.std(), want)
        assert abs(d.mean()) < 4 * want / math.sqrt(d.size)
        # white: consecutive samples uncorrelated
        r = np.corrcoef(d[1:].ravel(), d[:-1].ravel())[0, 1]
        assert abs(r) < 4 / math.sqrt(d.size), r


def test_a_vibration_outside_0_to_300_is_refused(tmp_path):
    for times in (-1.0, 301.0, math.nan):
        with pytest.raises(InputError, match=r"^--imu-vibration must be 0-300 \(got "):
            simulate("hall", tmp_path / "s", duration_s=1.0, columns=64, imu_vibration=times)
        with pytest.raises(InputError, match=r"^--imu-vibration must be 0-300 \(got "):
            cached_sequence("hall", duration_s=1.0, columns=64, imu_vibration=times)
    assert not (tmp_path / "s").exists()
