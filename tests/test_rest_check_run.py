"""``adalio run`` on a robot already driving when the recording starts (imu.rest_lidar_check):
the IMU's stillness test passes (a constant velocity reads as rest), the LiDAR refutes it, and
the run is a moving start; checked against the simulator's ground truth."""

import warnings
from types import SimpleNamespace

import pytest
import yaml

from adalio.config import load_config
from adalio.eval.metrics import ate
from adalio.lio.motion_init import RestCheck
from adalio.pipeline import _no_pose_reason, run_bag


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    from adalio import simulate

    # a robot's walk (no hand motion): it stands 2 s, then drives the hall at 1.25 m/s
    return simulate("hall", tmp_path_factory.mktemp("robot_hall"), seed=1, duration_s=7,
                    columns=512, motion_from="none")


def test_a_recording_started_while_driving_is_a_moving_start(robot, tmp_path):
    """Cut 3.5 s into the drive: every scan gets a pose, within 2 cm of the truth (first pose
    aligned: a straight drive leaves an SE(3) alignment free), and the summary line says why
    the still window was refused. Measured with the check off (the behaviour before session
    76): a static start at zero velocity, 3.8 m off at the end of 3.5 s."""
    res = {}
    for check in (True, False):
        cfg = load_config(config_file=robot.config_path,
                          overrides={"imu.rest_lidar_check": str(check).lower()})
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res[check] = run_bag(robot.bag_path, cfg, tmp_path / str(check), progress=False,
                                 start_s=3.5)
    on, off = res[True], res[False]
    assert on.init_report.method == "moving" and on.n_scans == on.n_scans_in
    text = on.init_report.describe()
    assert "a still window was refused: the IMU rested by its test while the LiDAR registered" \
        in text
    measured = yaml.safe_load(on.config_path.read_text())["measured"]
    assert measured["init_lidar_rest"].startswith("a still window was refused")
    err_on = ate(on.trajectory_path, robot.gt_path, align="first")["max_m"]
    assert err_on < 0.02, err_on
    assert off.init_report.method == "static"
    assert ate(off.trajectory_path, robot.gt_path, align="first")["max_m"] > 1.0


def test_a_still_start_says_the_lidar_agreed(robot, tmp_path):
    """The same robot from the recording's start, where it stands 2 s: a static start, and the
    LiDAR's registrations over the window agree."""
    cfg = load_config(config_file=robot.config_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run_bag(robot.bag_path, cfg, tmp_path / "still", progress=False, max_scans=20)
    rep = res.init_report
    assert rep.method == "static" and rep.lidar_rest.startswith("the LiDAR agrees: ")
    assert float(rep.lidar_rest.split("LiDAR agrees: ")[1].split(" m/s")[0]) < 0.01


def test_no_pose_after_a_refused_rest_says_to_start_at_rest(tmp_path):
    """A run that never initialized because the LiDAR refused the still windows (and the moving
    start found no geometry to fix the velocity: a robot driving down the simulated stairwell,
    cut at 4 s, measured in session 76) says so and what to do, not to check the IMU."""
    check = RestCheck(0.52, 0.045, 432.8, 66.8, 5, 0.4, 0)
    odom = SimpleNamespace(initialized=False, rest_refuted=check, had_points=True,
                           init_failure=lambda: "the rig moved from the start: "
                           + check.describe())
    text = _no_pose_reason(odom, 80, "/points", "/imu", tmp_path, n_late=0)
    assert text.startswith("no pose from 80 scans: the estimator never initialized: the rig "
                           "moved from the start")
    assert "Start the recording with the rig at rest" in text and "Check /imu" not in text


def test_a_still_start_in_a_view_that_fixes_no_axis_is_not_refused(tmp_path):
    """A LiDAR tilted 30 deg nose down on the handle in the corridor sees its floor and ceiling
    and hardly anything along the axis: standing still, its LiDAR-only registrations slide
    along it (2.2 m/s over 0.4 s, restoring ratios -0.5 to 0.3). They cannot vouch for that motion,
    so they do not refute the rest across it: a static start at once, where before session 81
    the still window was refused and the moving start could not start either (no pose from the
    first 20 scans, nor from the whole walk's first 150)."""
    from adalio.sim import cached_sequence

    sim = cached_sequence("corridor", seed=0, duration_s=3.0, columns=512, lidar_tilt_deg=30.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run_bag(sim.bag_path, load_config(config_file=sim.config_path), tmp_path / "o",
                      progress=False, max_scans=20)
    rep = res.init_report
    assert rep.method == "static", rep.describe()
    assert rep.lidar_rest.startswith("the LiDAR agrees: ")
    assert "not along their weakest translation" in rep.lidar_rest
    assert rep.wait_s < 0.7 and res.n_scans == 20, (rep.wait_s, res.n_scans)
    # still for these 2 s: the filter's own update slides a few cm along the axis (6.5 cm)
    assert ate(res.trajectory_path, sim.gt_path, align="first")["max_m"] < 0.1
