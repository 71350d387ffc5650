"""``adalio run`` from a moving start: the scans read before the initialization get their poses
from the backfill, written in time order (trajectory.tum, scans.csv ``backfill``), checked
against the simulator's ground truth."""

import csv

import numpy as np
import pytest

from adalio.config import load_config
from adalio.eval.files import read_scans_csv
from adalio.eval.metrics import ate, sigma_consistency
from adalio.io.writers import read_tum
from adalio.pipeline import run_bag


@pytest.fixture(scope="module")
def hall(tmp_path_factory):
    from adalio import simulate

    return simulate("hall", tmp_path_factory.mktemp("backfill_hall"), seed=3, duration_s=8,
                    columns=512)


@pytest.mark.parametrize("backfill_s", [60.0, 0.0])
def test_moving_start_run_writes_the_backfilled_poses_first(hall, tmp_path, backfill_s):
    """Cut 3 s (the sensor walks by then): a moving start. With the backfill every scan read
    gets a pose (the backfill runs at the end of this 8 s bag, before imu.backfill_after_s);
    the rows are in time order, the backfilled ones first and flagged, the whole trajectory
    within 1 cm (SE(3) ATE) of the ground truth."""
    cfg = load_config(config_file=hall.config_path,
                      overrides={"imu.backfill_s": str(backfill_s)})
    res = run_bag(hall.bag_path, cfg, tmp_path / "out", progress=False, start_s=3.0)
    rep = res.init_report
    assert rep.method == "moving" and rep.scans_without_pose >= 5
    t_ns, _ = read_tum(res.trajectory_path)
    t = t_ns * 1e-9
    rows = list(csv.DictReader(res.scans_csv_path.open()))
    flags = np.array([int(r["backfill"]) for r in rows])
    assert len(rows) == len(t) == res.n_scans
    assert np.all(np.diff(t_ns) > 0)
    assert np.allclose([float(r["t_s"]) for r in rows], t, atol=1e-6)
    if backfill_s:
        assert rep.backfilled == rep.scans_without_pose == int(flags.sum())
        assert np.all(flags[:rep.backfilled] == 1) and np.all(flags[rep.backfilled:] == 0)
        assert res.n_scans == res.n_scans_in
        assert float(ate(res.trajectory_path, hall.gt_path)["rmse_m"]) < 0.01
    else:
        assert rep.backfilled == 0 and not flags.any()
        assert res.n_scans == res.n_scans_in - rep.scans_without_pose
    assert f"init_backfilled: {rep.backfilled}" in res.config_path.read_text()


def test_the_backfilled_map_is_larger(hall, tmp_path):
    """The backfill's scans join the exported map: more points than without it."""
    sizes = {}
    for backfill_s in (60.0, 0.0):
        cfg = load_config(config_file=hall.config_path,
                          overrides={"imu.backfill_s": str(backfill_s), "output.map_voxel_m": "0"})
        res = run_bag(hall.bag_path, cfg, tmp_path / f"o{backfill_s:g}", progress=False,
                      start_s=3.0)
        sizes[backfill_s] = res.map_path.stat().st_size
    assert sizes[60.0] > sizes[0.0]


def test_the_backfill_meets_the_forward_pass_where_it_starts(tmp_path):
    """A robot's still start in the corridor (no hand motion): the reversed pass re-registers the
    first 10 s along the corridor's weak axis before it reaches the scans read at rest before
    the initialization. Held to the anchor's position and yaw where it passes it, those scans'
    poses agree with the ground truth (aligned on the first forward pose) to a centimetre,
    as the forward poses at rest do. (Without the hold: 23 cm along the corridor.)"""
    from adalio import simulate

    seq = simulate("corridor", tmp_path / "seq", seed=0, duration_s=14, columns=512,
                   motion_from="none")
    res = run_bag(seq.bag_path, load_config(config_file=seq.config_path), tmp_path / "out",
                  progress=False)
    rep = res.init_report
    assert rep.method == "static" and rep.backfilled >= 3
    t_ns, _ = read_tum(res.trajectory_path)
    scans = read_scans_csv(res.scans_csv_path)
    first = rep.backfilled
    assert scans["backfill"][:first].all() and not scans["backfill"][first:].any()
    # errors with the ground truth aligned on the filter's first scan (the forward one)
    cons = sigma_consistency(res.trajectory_path, seq.gt_path, scans)
    assert cons.backfill_max_error_m < 0.01
    forward = cons.t_s >= t_ns[first] * 1e-9 - 1e-6
    err_m = np.linalg.norm(cons.errors_world_m[forward][:20], axis=1)
    assert err_m.max() < 0.01  # the forward poses there, as a yardstick


def test_the_forward_run_is_the_same_with_or_without_the_backfill(tmp_path):
    """The backfill's reversed pass runs on a copy of the filter. With people walking by it
    judges moving things on its own sweeps (in mirrored time), so the forward run after it
    keeps every pose it has without the backfill (before session 69 the two shared that state,
    and the forward poses after the backfill moved: 5 m on a corridor walk). The backfill
    runs 3 s after the initialization here, with walkers in view."""
    from adalio.sim import cached_sequence

    sim = cached_sequence("corridor", seed=0, duration_s=12.0, columns=512, people=4)
    poses, rows = {}, {}
    for backfill_s in ("60", "0"):
        cfg = load_config(config_file=sim.config_path,
                          overrides={"imu.backfill_s": backfill_s, "imu.backfill_after_s": "3"})
        res = run_bag(sim.bag_path, cfg, tmp_path / backfill_s, progress=False)
        t_ns, T = read_tum(res.trajectory_path)
        scans = read_scans_csv(res.scans_csv_path)
        keep = ~scans["backfill"].astype(bool)
        poses[backfill_s], rows[backfill_s] = (t_ns[keep], T[keep]), scans
        # the run's counts are what its scans.csv sums to, the backfilled rows included
        assert res.moving_points == (scans["n_moving"].sum(), scans["n_seen_through"].sum(),
                                     (scans["n_moving"] > 0).sum()), res.moving_points
        assert res.stray_points == (scans["n_stray"].sum(), scans["n_raw"].sum())
        assert 0 < res.stray_points[0] < 0.01 * res.stray_points[1]  # counted, not dropped
        assert not res.stray_dropped and not scans["n_stray_dropped"].any()
        assert res.stray_drops == (0, 0, res.stray_points[0])
        assert res.stray_dropped_ranges_s == []
        # a backfilled row counts the points read, as a forward row does (before session 86
        # it gave those held, about a third, and no stray return)
        bf = scans["backfill"].astype(bool)
        if bf.any():
            assert scans["n_raw"][bf].min() > 0.9 * np.median(scans["n_raw"][~bf])
            assert scans["n_stray"][bf].sum() > 0
    assert rows["60"]["backfill"].sum() >= 3 and not rows["0"]["backfill"].any()
    assert rows["0"]["n_moving"].sum() > 1000  # walkers were kept out after the backfill too
    np.testing.assert_array_equal(poses["60"][0], poses["0"][0])
    np.testing.assert_array_equal(poses["60"][1], poses["0"][1])


def test_a_run_stopped_by_its_input_keeps_the_backfilled_poses(hall, tmp_path):
    """A moving start, then an IMU gap longer than imu.max_gap_s: the run stops with its error,
    and the scans held for the backfill still get their poses (from the state before the gap),
    written in time order before the forward ones, as in the run of the same bag cut before
    the gap. (Before session 75 the error skipped the backfill: the trajectory began 2 s late.)"""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer

    from adalio.errors import InputError

    with AnyReader([hall.bag_path]) as r:
        t0 = r.start_time
        gap = (t0 + int(6.0e9), t0 + int(7.6e9))
        cut = tmp_path / "gap.bag"
        with Writer(cut) as w:
            conns = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data,
                                            md5sum=c.digest) for c in r.connections}
            for c, t, raw in r.messages():
                if not (c.msgtype.endswith("Imu") and gap[0] <= t < gap[1]):
                    w.write(conns[c.id], t, raw)
    cfg = load_config(config_file=hall.config_path, overrides={"imu.max_gap_s": "1"})
    with pytest.raises(InputError, match="longer than imu.max_gap_s"):
        run_bag(cut, cfg, tmp_path / "out", progress=False, start_s=3.0)
    rows = read_scans_csv(tmp_path / "out" / "scans.csv")
    t_ns, _ = read_tum(tmp_path / "out" / "trajectory.tum")
    assert np.all(np.diff(t_ns) > 0) and len(t_ns) == len(rows["t_s"])
    assert rows["backfill"].sum() >= 5 and np.all(np.diff(rows["backfill"]) <= 0)
    ok = run_bag(hall.bag_path, cfg, tmp_path / "ok", progress=False, start_s=3.0)
    t_ok, _ = read_tum(ok.trajectory_path)
    assert t_ns[0] == t_ok[0] and t_ns[-1] > hall_t(6.0, t0)
    assert float(ate(tmp_path / "out" / "trajectory.tum", hall.gt_path)["rmse_m"]) < 0.03


def hall_t(s: float, t0_ns: int) -> int:
    return t0_ns + int(s * 1e9)
