"""An IMU that is noisier in motion than at its still start (a robot's vibration, a motor that
starts after the rest): ``imu.track_noise_ratio`` measures the white noise again over the run
and the filter takes the measured density. The independent truth is the noise added here to a
simulated corridor walk's IMU messages once the rig moves, 30 times the simulated BMI085's
white-noise densities, and the walk's ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_typestore

from adalio.config import load_config
from adalio.eval.metrics import ate
from adalio.lio.odometry import TRACK_NOISE_WINDOW_S
from adalio.pipeline import run_bag
from adalio.sim import cached_sequence
from adalio.sim.imu import ImuNoise

VIBRATION = 30.0
"""The added white noise while the rig moves, times the simulated IMU's densities."""
WALK = {"seed": 0, "duration_s": 20.0, "columns": 512}


def _vibrating_copy(src: Path, dst: Path, meta: dict) -> None:
    """``src`` with white noise of VIBRATION times the simulated densities added to every IMU
    sample from the end of the still start on (each axis, per sample ``density * sqrt(rate)``)."""
    noise = ImuNoise()
    rate = float(meta["imu_rate_hz"])
    moving_ns = int(meta["start_time_ns"]) + round(float(meta["static_s"]) * 1e9)
    rng = np.random.default_rng(7)
    store = get_typestore(Stores.ROS1_NOETIC)
    with AnyReader([src], default_typestore=store) as reader, Writer(dst) as out:
        conns = {c.id: out.add_connection(c.topic, c.msgtype, typestore=store)
                 for c in reader.connections}
        for conn, t_ns, raw in reader.messages():
            if conn.msgtype == "sensor_msgs/msg/Imu":
                msg = reader.deserialize(raw, conn.msgtype)
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                if stamp >= moving_ns:
                    w, a = msg.angular_velocity, msg.linear_acceleration
                    dw = VIBRATION * noise.gyro_noise_rad_s_sqrt_hz * np.sqrt(rate) \
                        * rng.standard_normal(3)
                    da = VIBRATION * noise.accel_noise_m_s2_sqrt_hz * np.sqrt(rate) \
                        * rng.standard_normal(3)
                    w.x, w.y, w.z = w.x + dw[0], w.y + dw[1], w.z + dw[2]
                    a.x, a.y, a.z = a.x + da[0], a.y + da[1], a.z + da[2]
                    raw = store.serialize_ros1(msg, conn.msgtype)
            out.write(conns[conn.id], t_ns, raw)


@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    sim = cached_sequence("corridor", **WALK)
    meta = json.loads(sim.meta_path.read_text())
    bag = tmp_path_factory.mktemp("vibrating") / "corridor.bag"
    _vibrating_copy(sim.bag_path, bag, meta)
    return sim, bag


def _density(cov: float, cfg, rate_hz: float) -> float:
    """A configured white-noise variance as a density, in the config's discretization."""
    return float(np.sqrt(cov / (1.0 if cfg.imu.noise_discretization == "dt" else rate_hz)))


def test_a_clean_imu_keeps_the_density_it_started_with(corridor, tmp_path):
    sim, _ = corridor
    res = run_bag(sim.bag_path, load_config(config_file=sim.config_path), tmp_path / "clean",
                  progress=False)
    assert res.noise_raises == []


def test_an_imu_vibrating_in_motion_has_its_noise_measured_and_used(corridor, tmp_path,
                                                                    summary_text):
    sim, bag = corridor
    cfg = load_config(config_file=sim.config_path)
    res = run_bag(bag, cfg, tmp_path / "tracked", progress=False)
    off = run_bag(bag, load_config(config_file=sim.config_path,
                                   overrides={"imu.track_noise_ratio": "0"}),
                  tmp_path / "off", progress=False)
    assert off.noise_raises == []
    assert res.noise_raises, "no raise"
    # the first raise within a few windows of the motion's start (after the 2.5 s still start)
    assert res.noise_raises[0][0] < 2.5 + 3 * TRACK_NOISE_WINDOW_S, res.noise_raises
    # the densities it reached, against the simulated and the added noise over the filter's
    noise, rate = ImuNoise(), float(cfg.sensor.imu_rate_hz)
    total = np.sqrt(1.0 + VIBRATION**2)
    want_g = total * noise.gyro_noise_rad_s_sqrt_hz / _density(cfg.imu.gyro_cov, cfg, rate)
    want_a = total * noise.accel_noise_m_s2_sqrt_hz / _density(cfg.imu.accel_cov, cfg, rate)
    _, got_g, got_a = res.noise_raises[-1]
    assert abs(got_g / want_g - 1.0) < 0.1, (got_g, want_g)
    assert abs(got_a / want_a - 1.0) < 0.1, (got_a, want_a)
    ate_tracked = float(ate(res.trajectory_path, sim.gt_path)["rmse_m"])
    ate_off = float(ate(off.trajectory_path, sim.gt_path)["rmse_m"])
    print(f"ATE tracked {ate_tracked:.4f} m, off {ate_off:.4f} m; raises {res.noise_raises}")
    assert ate_tracked < 0.05, ate_tracked
    assert ate_tracked < 0.5 * ate_off, (ate_tracked, ate_off)
    text = summary_text(res)
    assert "at risk: the IMU is noisier in motion than at the start" in text
    assert "imu.track_noise_ratio" in text
