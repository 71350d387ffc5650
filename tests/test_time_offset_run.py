"""IMU stamps that run late against the LiDAR's (an IMU stamped on arrival): the simulator writes
them, ``sensor.imu_time_offset_s`` takes them back, and without it ``run_bag`` finds the offset
from the data and restarts with it; a sequence on time is left alone."""

from __future__ import annotations

import copy

import pytest
import yaml
from typer.testing import CliRunner

from adalio.cli import app
from adalio.config import load_config
from adalio.eval.metrics import ate
from adalio.io.bag import Bag
from adalio.pipeline import run_bag

LATE_S = 0.03


@pytest.fixture
def late(hall_walk_of):
    return hall_walk_of(imu_time_offset_s=LATE_S)


@pytest.fixture(scope="module")
def on_time_ate(hall_walk_of, tmp_path_factory) -> float:
    on_time = hall_walk_of()
    res = run_bag(on_time.bag_path, load_config(config_file=on_time.config_path),
                  tmp_path_factory.mktemp("on_time"), progress=False)
    assert res.time_offset_found is None  # on time: no restart
    assert res.time_offset is not None and abs(res.time_offset.offset_s) < 2e-3, res.time_offset
    return float(ate(res.trajectory_path, on_time.gt_path, align="se3")["rmse_m"])


def _ate(sim, cfg, out) -> tuple[float, object]:
    res = run_bag(sim.bag_path, cfg, out, progress=False)
    return float(ate(res.trajectory_path, sim.gt_path, align="se3")["rmse_m"]), res


def test_the_simulator_stamps_the_imu_late_and_says_so_only_in_meta(late):
    import json

    assert json.loads(late.meta_path.read_text())["imu_time_offset_s"] == pytest.approx(LATE_S)
    assert load_config(config_file=late.config_path).sensor.imu_time_offset_s == 0.0
    with Bag(late.bag_path) as bag:
        topic = next(t.name for t in bag.topics() if t.msgtype.endswith("Imu"))
        _, t_rec, msg = next(iter(bag.messages([topic])))
    stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
    assert stamp_ns - t_rec == round(LATE_S * 1e9)


def test_the_configured_offset_takes_the_late_stamps_back(tmp_path, late, on_time_ate):
    cfg = load_config(config_file=late.config_path)
    cfg.sensor.imu_time_offset_check = False
    late_ate, _ = _ate(late, copy.deepcopy(cfg), tmp_path / "late")
    cfg.sensor.imu_time_offset_s = LATE_S
    fixed_ate, res = _ate(late, cfg, tmp_path / "fixed")
    assert res.time_offset is None  # the check is off
    # measured: 30 ms late costs the hall walk several times its error on time (1.2 vs 0.2 cm)
    assert late_ate > 2.5 * on_time_ate, (late_ate, on_time_ate)
    assert fixed_ate < on_time_ate + 0.001, (fixed_ate, on_time_ate)


def test_run_bag_finds_the_offset_and_restarts_with_it(tmp_path, late, on_time_ate):
    cfg = load_config(config_file=late.config_path)
    with pytest.warns(UserWarning, match=r"restarted with sensor\.imu_time_offset_s"):
        found_ate, res = _ate(late, cfg, tmp_path / "found")
    found = res.time_offset_found
    assert found is not None and abs(found.offset_s - LATE_S) < 2e-3, found
    assert found.configured_s == 0.0 and 1 <= len(found.passes) <= 6
    # the first estimate sees only part of the offset; the passes find the rest
    assert 0.0 < found.detected_s < LATE_S
    assert not res.stopped_for_time_offset and res.n_scans >= 135
    saved = load_config(config_file=res.config_path)  # a re-run from config.yaml starts right
    assert saved.sensor.imu_time_offset_s == pytest.approx(found.offset_s)
    measured = yaml.safe_load(res.config_path.read_text())["measured"]  # and what was left
    assert abs(measured["imu_time_offset_left_s"]) < 2e-3, measured
    assert found_ate < on_time_ate + 0.001, (found_ate, on_time_ate)


def test_the_restart_is_one_warning_line_on_the_command_line(tmp_path, late):
    res = CliRunner().invoke(app, ["run", str(late.bag_path), "--config", str(late.config_path),
                                   "--out", str(tmp_path / "o"), "--no-progress"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    warned = [ln for ln in lines if ln.startswith("warning:")]
    assert len(warned) == 1 and "sensor.imu_time_offset_s: 0.0" in warned[0], warned
    timing = [ln for ln in lines if ln.startswith("IMU timing: ")]
    assert len(timing) == 1 and "the run restarted with it" in timing[0], lines


def test_an_offset_beyond_the_configs_range_is_refused(late):
    cfg = load_config(config_file=late.config_path)
    cfg.sensor.imu_time_offset_s = 2.0
    with pytest.raises(Exception, match=r"sensor\.imu_time_offset_s must be"):
        cfg.validate()
