"""benchmarks/bench_lookahead.py: the earlier pass's scans are placed by its own motion from the
previous scan, anchored at this pass's pose there; its command line rejects bad values with one
``error:`` line before any run."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

from bench_lookahead import PassRecord, place_future

from adalio.types import Estimate, ScanStats


def _pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.8, 3)).as_matrix()
    T[:3, 3] = rng.normal(0.0, 3.0, 3)
    return T


def test_future_points_follow_the_earlier_motion_from_this_pass_pose() -> None:
    rng = np.random.default_rng(7)
    T_prev_then, T_scan_then, T_prev_now = _pose(rng), _pose(rng), _pose(rng)
    p_body = rng.normal(0.0, 5.0, (50, 3))  # points in the IMU frame of the later scan
    R_then, t_then = T_scan_then[:3, :3], T_scan_then[:3, 3]
    points_then = p_body @ R_then.T + t_then  # where the earlier pass put them
    # the later scan's pose in this pass: this pass's previous pose, then the earlier pass's
    # relative motion (composed with scipy's rotations, not with the matrices under test)
    r_prev_then = Rotation.from_matrix(T_prev_then[:3, :3])
    r_rel = r_prev_then.inv() * Rotation.from_matrix(R_then)
    t_rel = r_prev_then.inv().apply(t_then - T_prev_then[:3, 3])
    r_now = Rotation.from_matrix(T_prev_now[:3, :3])
    expected = (r_now * r_rel).apply(p_body) + r_now.apply(t_rel) + T_prev_now[:3, 3]
    np.testing.assert_allclose(place_future(T_prev_now, T_prev_then, points_then), expected,
                               atol=1e-9)
    # the same pose in both passes: the points stay where they are
    np.testing.assert_allclose(place_future(T_prev_then, T_prev_then, points_then),
                               points_then, atol=1e-9)


def _estimate(t_ns: int, backfill: bool = False) -> Estimate:
    stats = ScanStats()
    stats.backfill = backfill
    return Estimate(t_ns=t_ns, T_world_imu=np.eye(4), velocity_world_m_s=np.zeros(3),
                    gyro_bias_rad_s=np.zeros(3), accel_bias_m_s2=np.zeros(3),
                    gravity_world_m_s2=np.array([0.0, 0.0, -9.81]), cov_diag=np.zeros(1),
                    stats=stats, points_world=np.full((2, 3), float(t_ns)))


def test_pass_record_gives_the_scans_ahead_and_skips_the_backfill() -> None:
    rec = PassRecord()
    for t in (100_000_000, 200_000_000, 300_000_000, 400_000_000):
        rec.add(_estimate(t))
    rec.add(_estimate(50_000_000, backfill=True))
    assert rec.pose_at(50_000_000) is None and rec.pose_at(200_000_000) is not None
    # after the scan ending at 0.2 s (its own points excluded, also 10 ms off) up to 0.35 s
    assert [a[0, 0] for a in rec.ahead(200_000_000, 350_000_000)] == [3e8]
    assert [a[0, 0] for a in rec.ahead(190_000_000, 400_000_000)] == [3e8, 4e8]


@pytest.mark.parametrize(("args", "flag"), [(["--passes", "0"], "--passes"),
                                            (["--look-ahead-s", "0"], "--look-ahead-s"),
                                            (["--look-ahead-s", "nan"], "--look-ahead-s"),
                                            (["--imu-bias-scale", "-1"], "--imu-bias-scale"),
                                            (["--set", "filter.no_such_key=1"],
                                             "filter.no_such_key")])
def test_bad_arguments_are_one_error_line(args: list[str], flag: str, tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "bench_lookahead.py"), *args,
                           "--out", str(tmp_path / "out")],
                          check=False, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and flag in lines[0], proc.stderr
    assert not any(tmp_path.iterdir())
