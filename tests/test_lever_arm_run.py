"""A LiDAR-IMU lever arm in the config that is off by 3 cm (an extrinsic from a drawing): the
run says so in a summary line with the correction, from the accelerometer against the motion
the LiDAR registers (a hint, not a warning: on short recordings it also flags right lever arms,
README "LiDAR-IMU lever arm"); with the right lever arm it does not flag this walk's."""

from __future__ import annotations

import copy

import numpy as np
import yaml
from typer.testing import CliRunner

from adalio.cli import app
from adalio.config import load_config
from adalio.pipeline import run_bag

OFF_M = 0.03 * np.array([-0.35, 0.62, -0.70]) / np.linalg.norm([-0.35, 0.62, -0.70])


def _shifted(cfg):
    """The config's lever arm 3 cm off: the correction it needs is +OFF_M."""
    out = copy.deepcopy(cfg)
    T = cfg.T_imu_lidar()
    T[:3, 3] -= OFF_M
    out.sensor.T_imu_lidar = T.tolist()
    return out


def test_a_lever_arm_3_cm_off_is_found(tmp_path, hall_walk):
    truth = load_config(config_file=hall_walk.config_path)
    cfg = _shifted(truth)
    res = run_bag(hall_walk.bag_path, cfg, tmp_path / "off", progress=False)
    est = res.extrinsic_translation
    assert est is not None and est.significant, est
    # the correction the warning gives is across the rig's vertical (the IMU's z here)
    across = np.eye(3) - np.outer(est.up_imu, est.up_imu)
    assert abs(abs(est.up_imu[2]) - 1.0) < 0.05, est.up_imu
    corrected = cfg.T_imu_lidar()[:3, 3] + est.horizontal_m
    left = np.linalg.norm(across @ (corrected - truth.T_imu_lidar()[:3, 3]))
    off = np.linalg.norm(across @ OFF_M)
    assert left < 0.6 * off, (est.horizontal_m, OFF_M)  # measured: 0.9 of 2.1 cm
    measured = yaml.safe_load(res.config_path.read_text())["measured"]
    np.testing.assert_allclose(measured["extrinsic_translation_correction_m"], est.horizontal_m,
                               atol=1e-4)


def test_the_right_lever_arm_is_not_flagged(tmp_path, hall_walk):
    cfg = load_config(config_file=hall_walk.config_path)
    res = run_bag(hall_walk.bag_path, cfg, tmp_path / "right", progress=False)
    est = res.extrinsic_translation or res.extrinsic_translation_unsettled.estimate
    assert est is not None and not est.significant, est
    assert est.length_m < 0.015, est.horizontal_m  # measured: 0.8 cm across the vertical


def test_the_command_line_says_it_in_one_line_and_no_warning(tmp_path, hall_walk):
    config_path = tmp_path / "shifted.yaml"
    config_path.write_text(_shifted(load_config(config_file=hall_walk.config_path)).to_yaml())
    res = CliRunner().invoke(app, ["run", str(hall_walk.bag_path), "--config", str(config_path),
                                   "--out", str(tmp_path / "o"), "--no-progress"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert not [ln for ln in lines if ln.startswith("warning:")], lines
    line = [ln for ln in lines if ln.startswith("LiDAR-IMU translation: ")]
    assert len(line) == 1 and ": check sensor.T_imu_lidar's translation" in line[0], lines
