"""LiDAR gaps: seconds without a scan are found, warned about once and marked in the scan stats,
and the scan after one re-locks onto the map (``filter.gate_sigmas``) instead of onto the map
where the IMU's dead reckoning put it."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from adalio.sim import cached_sequence

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from bench_lidar_gaps import GapRun, run_with_gap

GAP_S = (12.0, 17.0)
"""Scans ending in this window (s after the bag start) are dropped: 5 s without a scan, the
IMU ten times the BMI085's noise; the run stops 3 s after it."""


def _run(seed: int, gate_sigmas: float) -> GapRun:
    sim = cached_sequence("hall", seed=seed, duration_s=20.0, columns=512, imu_noise_scale=10.0)
    return run_with_gap(sim, GAP_S, GAP_S[1] + 3.0, gate_sigmas)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 2])
def test_a_five_second_lidar_gap_is_reported_and_the_scan_after_it_relocks(seed):
    run = _run(seed, 3.0)
    err, sigma, gap, odom = run.errors_m, run.sigmas_m, run.lidar_gap_s, run.odometry
    # found once, with its length, on the first scan after it
    assert len(run.warnings) == 1 and "no scan for 5.00 s" in run.warnings[0], run.warnings
    assert len(odom.lidar_gaps) == 1
    _, missing_s, sigma_pred_m = odom.lidar_gaps[0]
    assert missing_s == pytest.approx(GAP_S[1] - GAP_S[0], abs=0.05)
    marked = np.flatnonzero(gap > 0)
    assert marked.size == 1 and gap[marked[0]] == pytest.approx(missing_s)
    first = marked[0]
    assert run.t_s[first - 1] < GAP_S[0] < GAP_S[1] < run.t_s[first]
    # the dead reckoning's sigma is decimetres (the warning says so), the scans before the gap
    # track within a centimetre and a half
    assert sigma_pred_m > 0.1
    assert np.linalg.norm(err[:first], axis=1).max() < 0.015
    # the scan after the gap corrects most of the dead reckoning's error at once, and 3 s later
    # the walk is back within the clean run's bound. The first scans after it claim less than
    # their error while the map converges (seed 2: 3 to 7 sigma for four scans; 73 % of the 3 s
    # within 3 sigma on x, 87 % on y)
    after = np.linalg.norm(err[first:], axis=1)
    assert after.max() < 0.2, after[:5]
    assert after[-10:].max() < 0.03, after[-10:]
    assert np.all(np.mean(np.abs(err[first:]) <= 3.0 * sigma[first:], axis=0) >= 0.6)


@pytest.mark.slow
def test_without_the_covariance_gate_the_scan_after_the_gap_locks_where_it_was_predicted():
    """The range gate alone (``gate_sigmas: 0``, FAST-LIO2's) rejects the rows whose residual is
    the dead reckoning's error, and the walk stays decimetres off for good: why the gate is on."""
    err = _run(2, 0.0).errors_m
    assert np.linalg.norm(err[-10:], axis=1).min() > 0.3
