"""The IMU/LiDAR merge: ordering guarantee against brute force, stamp problems, coverage."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from adalio.errors import InputError
from adalio.io.sequencer import SequencerStats, merge
from adalio.types import ImuBatch, Scan


def imu(ts) -> ImuBatch:
    t = np.asarray(ts, dtype=np.int64)
    return ImuBatch(t, np.zeros((t.size, 3)), np.tile([0.0, 0.0, 9.81], (t.size, 1)))


def scan(t0: int, t1: int, n: int = 10) -> Scan:
    t = np.linspace(t0, t1, n).astype(np.int64)
    return Scan(np.ones((n, 3)), t, stamp_ns=t0)


def receive_order(imu_t, scans, latency_ns, chunk=3):
    """Events as a bag would hold them: IMU at its stamp, scans at their end + latency."""
    events = [(int(t), 0, imu([t])) for t in imu_t]
    events += [(s.t_end_ns + latency_ns, 1, s) for s in scans]
    events.sort(key=lambda e: (e[0], e[1]))
    return [e[2] for e in events]


def check_order(out, imu_t):
    seen = []
    for item in out:
        if isinstance(item, ImuBatch):
            seen.extend(item.t_ns.tolist())
        else:
            assert sum(1 for t in seen if t <= item.t_end_ns) == \
                sum(1 for t in imu_t if t <= item.t_end_ns)
            assert all(t <= item.t_end_ns for t in seen)
    return seen


@pytest.mark.parametrize("latency_ms", [0, 5, 40, 300])
def test_every_scan_after_its_imu_random_streams(latency_ms):
    rng = np.random.default_rng(latency_ms)
    imu_t = np.cumsum(rng.integers(2_000_000, 3_000_000, 400)) + 10**15
    scans = [scan(imu_t[0] + k * 100_000_000 + 1, imu_t[0] + (k + 1) * 100_000_000 - 7)
             for k in range(9)]
    st = SequencerStats()
    out = list(merge(receive_order(imu_t, scans, latency_ms * 1_000_000), st))
    seen = check_order(out, imu_t.tolist())
    assert seen == imu_t.tolist()
    out_scans = [o for o in out if isinstance(o, Scan)]
    assert [s.t_end_ns for s in out_scans] == [s.t_end_ns for s in scans]
    assert st.scans_out == 9 and st.imu_samples == 400


def test_small_imu_reordering_is_absorbed():
    imu_t = list(range(10**9, 10**9 + 400 * 2_500_000, 2_500_000))
    shuffled = imu_t.copy()
    shuffled[10], shuffled[11] = shuffled[11], shuffled[10]
    st = SequencerStats()
    out = list(merge([imu(shuffled[:200]), scan(imu_t[5], imu_t[50]), imu(shuffled[200:])], st))
    got = np.concatenate([o.t_ns for o in out if isinstance(o, ImuBatch)]).tolist()
    assert got == imu_t and st.imu_reordered == 1


def test_imu_going_backwards_beyond_window_is_error():
    items = [imu(range(10**9, 12 * 10**8, 5_000_000)), scan(10**9 + 1, 10**9 + 10**8),
             imu(range(12 * 10**8, 5 * 10**9, 5_000_000)), imu([10**9 + 7])]
    with pytest.raises(InputError, match=r"IMU stamps on /imu go backwards: 1\.000000007 s"):
        list(merge(items, imu_topic="/imu"))


def test_scan_end_going_backwards_is_error():
    items = [imu(range(0, 3 * 10**8, 5_000_000)), scan(10**8, 2 * 10**8),
             imu(range(3 * 10**8, 4 * 10**8, 5_000_000)), scan(2 * 10**8 - 10**7, 2 * 10**8 - 10)]
    with pytest.raises(InputError, match="scan end times on /pts go backwards"):
        list(merge(items, lidar_topic="/pts"))


def test_scan_arriving_after_the_imu_window_is_skipped():
    st = SequencerStats()
    items = [imu(range(0, 3 * 10**9, 5_000_000)), scan(10**8, 2 * 10**8),
             scan(29 * 10**8, 2_950_000_000), imu(range(3 * 10**9, 4 * 10**9, 5_000_000))]
    with pytest.warns(UserWarning, match="arrived more than 2.0 s after"):
        out = list(merge(items, st))
    assert [o.t_end_ns for o in out if isinstance(o, Scan)] == [2_950_000_000]
    assert st.scans_late == 1


def test_duplicate_imu_stamps_dropped():
    st = SequencerStats()
    out = list(merge([imu([1, 2, 2, 3]), scan(1, 2), imu([3, 4] + list(range(5, 10**8, 10**6)))],
                     st))
    got = np.concatenate([o.t_ns for o in out if isinstance(o, ImuBatch)])
    assert np.all(np.diff(got) > 0) and st.imu_duplicates == 2


def test_imu_not_covering_scans_is_error():
    items = [imu(range(0, 10**9, 5_000_000)), scan(5 * 10**9, 5 * 10**9 + 10**8)]
    with pytest.raises(InputError, match="does not cover any scan"):
        list(merge(items))


def test_empty_and_uncovered_scans_are_counted():
    st = SequencerStats()
    items = [imu(range(0, 10**9, 5_000_000)), Scan(np.zeros((0, 3)), np.zeros(0, np.int64), 0),
             scan(10**8, 2 * 10**8), scan(2 * 10**9, 2 * 10**9 + 10**8)]
    with pytest.warns(UserWarning, match="empty scan"):
        out = list(merge(items, st))
    assert sum(isinstance(o, Scan) for o in out) == 1
    assert (st.scans_empty, st.scans_after_imu, st.scans_out) == (1, 1, 1)


def test_all_empty_scans_is_error():
    empty = Scan(np.zeros((0, 3)), np.zeros(0, np.int64), 0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the error alone, no 'empty scan skipped' before it
        with pytest.raises(InputError, match="all 2 clouds on lidar"):
            list(merge([imu([1, 2, 3]), empty, empty]))
        with pytest.raises(InputError, match=r"\(3 points are \(0, 0"):
            list(merge([imu([1, 2, 3]), empty, empty],
                       why_empty=lambda: "3 points are (0, 0, 0)"))


def test_nonfinite_imu_samples_dropped_with_one_warning():
    st = SequencerStats()
    batch = imu(range(0, 10**9, 5_000_000))
    batch.gyro_rad_s[[10, 11, 50]] = np.nan
    batch.accel_m_s2[70, 2] = np.inf
    with pytest.warns(UserWarning, match=r"IMU sample on /imu at 0\.050000000 s has a NaN") as w:
        out = list(merge([batch, scan(10**8, 2 * 10**8)], st, imu_topic="/imu"))
    assert len(w) == 1
    kept = np.concatenate([o.t_ns for o in out if isinstance(o, ImuBatch)])
    assert kept.size == 200 - 4 and st.imu_nonfinite == 4
    assert not np.isin([50_000_000, 55_000_000, 250_000_000, 350_000_000], kept).any()
    assert any(m.startswith("skipped 4 IMU samples with NaN/inf") for m in st.messages)


def test_all_nonfinite_imu_is_error():
    batch = imu(range(0, 10**9, 5_000_000))
    batch.accel_m_s2[:] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="all 200 IMU samples on /i"):
            list(merge([batch, scan(10**8, 2 * 10**8)], imu_topic="/i"))


def test_scans_before_first_imu_are_skipped():
    st = SequencerStats()
    out = list(merge([scan(0, 10**8), imu(range(2 * 10**8, 10**9, 5_000_000)),
                      scan(3 * 10**8, 4 * 10**8)], st))
    assert [o.t_end_ns for o in out if isinstance(o, Scan)] == [4 * 10**8]
    assert st.scans_before_imu == 1
