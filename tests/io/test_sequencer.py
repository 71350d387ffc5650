"""The IMU/LiDAR merge: ordering guarantee against brute force, stamp problems, coverage."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from adalio.errors import InputError
from adalio.io.sequencer import IMU_LOOKAHEAD_NS, SequencerStats, merge
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


def check_order(out, imu_t, lookahead_ns=IMU_LOOKAHEAD_NS):
    """Brute force: before each scan, every sample up to its end and the first one after it
    (the propagation's last interval needs it), once the lookahead has it; nothing later."""
    seen = []
    for item in out:
        if isinstance(item, ImuBatch):
            seen.extend(item.t_ns.tolist())
        else:
            assert sum(1 for t in seen if t <= item.t_end_ns) == \
                sum(1 for t in imu_t if t <= item.t_end_ns)
            after = [t for t in imu_t if t > item.t_end_ns]
            received = bool(after) and after[-1] >= item.t_end_ns + lookahead_ns
            assert [t for t in seen if t > item.t_end_ns] == (after[:1] if received else [])
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
    """IMU samples stamped before samples already used: up to two in a row are a stamp glitch
    (dropped, a warning once the stream goes on, counted), also split over chunks; three in a
    row, in one chunk or over several, are the clock going back: an error, and no warning."""
    head = [imu(range(10**9, 12 * 10**8, 5_000_000)), scan(10**9 + 1, 10**9 + 10**8),
            imu(range(12 * 10**8, 5 * 10**9, 5_000_000))]
    with pytest.raises(InputError, match=r"IMU stamps on /imu go backwards: 1\.000000007 s .*"
                                         r"over 3 samples in a row"):
        list(merge([*head, imu([10**9 + 7, 10**9 + 8, 10**9 + 9])], imu_topic="/imu"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no glitch warning before the error: it was none
        with pytest.raises(InputError, match=r"over 3 samples in a row"):
            list(merge([*head, imu([10**9 + 7, 10**9 + 8]), imu([10**9 + 9, 5 * 10**9])],
                       imu_topic="/imu"))
    st = SequencerStats()
    tail = [imu([10**9 + 7, 5 * 10**9 + 1]), imu([5 * 10**9 + 2, 10**9 + 8]),
            imu([5 * 10**9 + 3, 5 * 10**9 + 4])]
    with pytest.warns(UserWarning, match=r"IMU sample on /imu stamped 1\.000000007 s, 1\.995 s "
                                         r"before samples already used \(a stamp glitch\?\)"):
        out = list(merge([*head, *tail], st, imu_topic="/imu"))
    got = np.concatenate([o.t_ns for o in out if isinstance(o, ImuBatch)])
    assert np.all(np.diff(got) > 0) and st.imu_glitches == 2
    assert 10**9 + 7 not in got and 5 * 10**9 + 4 in got


def test_scan_end_going_backwards_is_error():
    """A scan ending at or before one already processed: within the IMU window a cloud recorded
    out of order or twice, skipped with a warning and counted; beyond it an error that points
    at the time settings."""
    items = [imu(range(0, 3 * 10**8, 5_000_000)), scan(10**8, 2 * 10**8),
             imu(range(3 * 10**8, 4 * 10**8, 5_000_000)), scan(2 * 10**8 - 10**7, 2 * 10**8 - 10),
             scan(10**8, 2 * 10**8), imu(range(4 * 10**8, 6 * 10**8, 5_000_000)),
             scan(2 * 10**8 + 1, 3 * 10**8)]
    st = SequencerStats()
    with pytest.warns(UserWarning, match=r"scan on /pts ending at 0\.199 s arrived after the "
                                         r"scan ending at 0\.200 s was processed"):
        out = list(merge(items, st, lidar_topic="/pts"))
    assert [o.t_end_ns for o in out if isinstance(o, Scan)] == [2 * 10**8, 3 * 10**8]
    assert st.scans_out_of_order == 2
    assert "skipped 2 scans arriving after later ones" in " ".join(st.messages)
    items = [imu(range(0, 3 * 10**9, 5_000_000)), scan(27 * 10**8, 28 * 10**8),
             imu(range(3 * 10**9, 4 * 10**9, 5_000_000)), scan(5 * 10**8, 6 * 10**8)]
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
    with pytest.warns(UserWarning, match="empty scan"), \
            pytest.warns(UserWarning, match="1.10 s before the last scan"):
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


def test_imu_samples_stamped_alike_with_other_values_are_warned_and_counted():
    """A driver that stamps a burst of 4 samples with one read time: the first of each stamp is
    kept (as for exact duplicates, which stay silent), and a warning plus the summary say how
    many samples with their own values were dropped."""
    t = np.repeat(np.arange(10**9, 10**9 + 200 * 10_000_000, 10_000_000), 4)  # 800 samples
    rng = np.random.default_rng(0)
    burst = ImuBatch(t, rng.normal(size=(t.size, 3)), rng.normal(size=(t.size, 3)))
    st = SequencerStats()
    with pytest.warns(UserWarning, match=r"share a stamp with other values \(first at "
                                         r"1\.000000000 s\)"):
        out = list(merge([burst, scan(10**9 + 1, 10**9 + 10**8)], st, imu_topic="/imu"))
    got = np.concatenate([o.t_ns for o in out if isinstance(o, ImuBatch)])
    assert got.tolist() == np.unique(t).tolist()
    assert st.imu_conflicting == 600 and st.imu_duplicates == 600
    assert "dropped 600 of 800 IMU samples on /imu (75 %)" in " ".join(st.messages)
    st = SequencerStats()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # exact copies are dropped without a word
        list(merge([imu(t), scan(10**9 + 1, 10**9 + 10**8)], st))
    assert st.imu_duplicates == 600 and st.imu_conflicting == 0


def test_an_imu_ending_long_before_the_lidar_is_a_warning():
    """Scans past the IMU's last sample are not posed: a note when it is the usual last scan, a
    warning naming the span when the IMU stopped more than half a second early."""
    items = [imu(range(0, 10**9, 5_000_000))]
    items += [scan(k * 10**8 + 1, (k + 1) * 10**8) for k in range(30)]
    st = SequencerStats()
    with pytest.warns(UserWarning, match=r"the IMU on /imu ends at 0\.995 s, 2\.01 s before "
                                         r"the last scan on /pts: its last 21 scans are not posed"):
        out = list(merge(items, st, imu_topic="/imu", lidar_topic="/pts"))
    assert sum(isinstance(o, Scan) for o in out) == 9 and st.scans_after_imu == 21
    st = SequencerStats()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        list(merge([imu(range(0, 10**9, 5_000_000)), scan(1, 10**8),
                    scan(9 * 10**8, 10**9 + 10**7)], st))
    assert st.scans_after_imu == 1


def _imu_msgs(n, frame="imu", gyro=(0.01, -0.02, 0.03), gyro_cov0=0.0, accel_cov0=0.0,
              accel=(0.0, 0.0, 9.81), t0_ns=10**9, period_ns=10_000_000):
    from types import SimpleNamespace as NS

    def vec(v):
        return NS(x=v[0], y=v[1], z=v[2])

    stamps = [t0_ns + k * period_ns for k in range(n)]
    return [NS(header=NS(stamp=NS(sec=t // 10**9, nanosec=t % 10**9), frame_id=frame),
               angular_velocity=vec(gyro), linear_acceleration=vec(accel),
               angular_velocity_covariance=np.r_[gyro_cov0, np.zeros(8)],
               linear_acceleration_covariance=np.r_[accel_cov0, np.zeros(8)])
            for t in stamps]


def test_an_imu_that_says_it_has_no_gyro_or_two_frames_is_an_error():
    """ROS REP 145's 'not provided' (covariance element 0 = -1) with zero values over 2 s of
    stamps is an error naming the field, whatever the chunks (a 100 Hz IMU beside a 20 Hz
    LiDAR gives chunks of 5); start-up samples that say so for 1.5 s and then real values
    pass, as does -1 with real values. Two frames on one topic (two IMUs) is an error naming
    them; an empty frame id beside one named frame is not."""
    from adalio.io.sequencer import check_imu_messages, imu_msg_arrays

    def feed(chunks, topic="/imu"):
        seen: dict = {}
        for msgs in chunks:
            check_imu_messages(msgs, imu_msg_arrays(msgs), topic, seen)

    def chunks(n_chunks, **kw):  # chunks of 5 samples at 100 Hz, in time order
        return [_imu_msgs(5, t0_ns=10**9 + 50_000_000 * c, **kw) for c in range(n_chunks)]

    no_gyro = {"gyro": (0.0, 0.0, 0.0), "gyro_cov0": -1.0}
    with pytest.raises(InputError, match=r"the IMU on /imu provides no gyro: its messages set "
                                         r"angular_velocity_covariance\[0\] = -1 .* for 2\.0 s"):
        feed(chunks(41, **no_gyro))
    feed(chunks(30, **no_gyro) + [_imu_msgs(5, t0_ns=3 * 10**9)] +
         [_imu_msgs(5, t0_ns=4 * 10**9 + 50_000_000 * c, **no_gyro) for c in range(60)])
    feed(chunks(60, gyro_cov0=-1.0))  # -1 beside real values: read
    with pytest.raises(InputError, match=r"provides no accelerometer: its messages set "
                                         r"linear_acceleration_covariance\[0\] = -1"):
        feed(chunks(41, accel=(0.0, 0.0, 0.0), accel_cov0=-1.0))
    with pytest.raises(InputError, match=r"IMU messages on /imu come from more than one frame "
                                         r"\('cam_imu', 'imu'\): two IMUs publish on the topic"):
        feed([_imu_msgs(64), _imu_msgs(32) + _imu_msgs(32, frame="cam_imu")])
    feed([_imu_msgs(64, frame=""), _imu_msgs(64), _imu_msgs(64, frame="")])


def _imu_series(t_ns, accel, frame="livox_frame"):
    """sensor_msgs/Imu-like messages with one accelerometer sample each (zero gyro)."""
    from types import SimpleNamespace as NS

    def vec(v):
        return NS(x=float(v[0]), y=float(v[1]), z=float(v[2]))

    return [NS(header=NS(stamp=NS(sec=int(t) // 10**9, nanosec=int(t) % 10**9), frame_id=frame),
               angular_velocity=vec((0.0, 0.0, 0.0)), linear_acceleration=vec(a),
               angular_velocity_covariance=np.zeros(9),
               linear_acceleration_covariance=np.zeros(9)) for t, a in zip(t_ns, accel)]


def test_two_imus_taking_turns_under_one_frame_id_are_an_error():
    """livox_ros_driver2 with two Mid-360s and multi_topic: 0 publishes both built-in IMUs on
    /livox/imu with frame id livox_frame, 200 Hz each, in turn. Two heads mounted differently
    (one rolled 90 degrees: gravity on another axis), or alike with 0.3 m/s^2 between their
    biases, are an error naming the topic and the frame; one IMU is not, with white noise, with
    a smooth motion, or shaken at 97 % of half its rate (its consecutive samples then differ
    over 5 times as much as samples two apart, measured below, but its even and odd samples
    share one mean)."""
    from adalio.io.sequencer import check_imu_messages, imu_msg_arrays

    rng = np.random.default_rng(7)
    n = 240  # each IMU's, 1.2 s at 200 Hz
    t = 10**9 + np.arange(n) * 5_000_000

    def feed(t_ns, accel):
        seen: dict = {}
        msgs = _imu_series(t_ns, accel)
        for k in range(0, len(msgs), 20):  # the sequencer's chunks
            check_imu_messages(msgs[k:k + 20], imu_msg_arrays(msgs[k:k + 20]), "/livox/imu",
                               seen)

    def noise(m):
        return rng.normal(0.0, 0.02, (m, 3))

    up = np.array([0.0, 0.0, 9.81])
    for second in (np.array([0.0, 9.81, 0.0]), up + 0.3 / np.sqrt(3)):
        t2 = np.concatenate([t, t + 2_300_000])  # the other IMU 2.3 ms later
        a2 = np.concatenate([up + noise(n), second + noise(n)])
        order = np.argsort(t2)  # in the bag in turn
        t2, a2 = t2[order], a2[order]
        with pytest.raises(InputError, match=r"IMU samples on /livox/imu alternate between two "
                                             r"sets of values: .* two IMUs publish on the topic "
                                             r"under one frame id \('livox_frame'\).*"
                                             r"multi_topic: 1"):
            feed(t2, a2)
    # one IMU at 400 Hz
    t1 = 10**9 + np.arange(2 * n) * 2_500_000
    feed(t1, up + noise(2 * n))
    s = t1 * 1e-9
    feed(t1, up + np.column_stack([np.sin(2 * np.pi * 1.3 * s), np.cos(2 * np.pi * 0.7 * s),
                                   0.5 * np.sin(2 * np.pi * 2.1 * s)]) + noise(2 * n))
    shake = up + np.outer(np.sin(2 * np.pi * 0.97 * 200.0 * s + 0.3), [0.3, 0.0, 0.5])
    d1 = np.mean(np.sum(np.diff(shake, axis=0) ** 2, axis=1))
    d2 = np.mean(np.sum((shake[2:] - shake[:-2]) ** 2, axis=1))
    assert d1 > 25 * d2  # it would pass the first two tests
    feed(t1, shake + noise(2 * n))


def _clock(d_lidar_s, d_imu_s, n=(10, 200), spread_s=0.0):
    """A ClockCheck fed stamps minus receive times (seconds), receive times spread as given."""
    from adalio.io.sequencer import ClockCheck

    c = ClockCheck("/pts", "/imu")
    rng = np.random.default_rng(1)
    for k in range(n[1]):
        t = 10**18 + k * 2_500_000
        c.add_imu(t + int(rng.uniform(0, spread_s) * 1e9), t + int(d_imu_s * 1e9))
    for k in range(n[0]):
        t = 10**18 + k * 100_000_000
        c.add_scan(t + int(rng.uniform(0, spread_s) * 1e9), t + int(d_lidar_s * 1e9))
    c.check()
    return c


def test_clock_check_tells_a_clock_ahead_from_its_receive_times():
    """Stamps ahead of their receive times on one topic only: that clock runs ahead (an error
    with the setting that moves the IMU onto the LiDAR's clock, or a re-stamp beyond 1 s). Both
    ahead of the recorder's clock (the other not within 50 ms of it), ordinary latencies, or
    receive times that spread (one time for the whole bag) say nothing. Scans received long
    after their end while the IMU is not: a warning, as late delivery cannot be told from a
    LiDAR clock behind; beyond the IMU window none (the scans are skipped, and that is said)."""
    with pytest.raises(InputError, match=r"the stamps on /pts run 0\.500 s ahead of the times "
                                         r"the bag received them, and those on /imu -0\.002 s: "
                                         r"the LiDAR's clock runs about 0\.50 s ahead of the "
                                         r"IMU's.*sensor\.imu_time_offset_s: -0\.502"):
        _clock(0.5, -0.002)
    with pytest.raises(InputError, match=r"the IMU's clock runs about 0\.33 s ahead of the "
                                         r"LiDAR's.*sensor\.imu_time_offset_s: 0\.330"):
        _clock(-0.03, 0.3)
    with pytest.raises(InputError, match=r"re-stamp the bag \(sensor\.imu_time_offset_s "
                                         r"reaches 1 s\)"):
        _clock(1.5, 0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _clock(0.7, 0.7)  # both clocks ahead of the recorder's alike
        _clock(0.7, 0.4)  # a recorder behind both, the IMU delivered 0.3 s later
        _clock(-5.0, 0.0)  # beyond the IMU window: the scans are skipped, and that is said
        _clock(-0.08, -0.004)  # a driver's latency
        _clock(0.8, 0.0, spread_s=5.0)  # receive times that tell nothing
        _clock(0.2, 0.0)  # within the margin
    with pytest.warns(UserWarning, match=r"scans on /pts end 1\.00 s before the bag received "
                                         r"them, IMU samples on /imu 0\.00 s: either the clouds "
                                         r"came 1\.00 s late \(harmless\), or the LiDAR's clock "
                                         r"runs 1\.00 s behind.*imu_time_offset_s: 1\.000"):
        _clock(-1.0, 0.0)
    with pytest.warns(UserWarning, match=r"behind the IMU's.*\(then re-stamp the bag\)"):
        _clock(-1.5, 0.0)


def test_a_lidar_clock_ahead_stops_the_sequencer_reading_a_bag(tmp_path):
    """The receive times reach the check through a real bag: the static rig with its clouds'
    header stamps moved 0.5 s ahead (their per-point times are relative) is an error naming
    both topics; the rig as written reads without one."""
    import bagfactory as bf
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer

    from adalio.config import SensorConfig
    from adalio.io.bag import Bag, ros1_typestore
    from adalio.io.sequencer import Sequencer

    rig = bf.write_static_rig(tmp_path / "rig.bag", duration_s=3.0, columns=60)
    ahead = tmp_path / "ahead.bag"
    store = ros1_typestore()
    with AnyReader([rig], default_typestore=store) as r, Writer(ahead) as w:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data,
                                        md5sum=c.digest) for c in r.connections}
        for c, t, raw in r.messages():
            if c.topic == "/points":
                msg = r.deserialize(raw, c.msgtype)
                ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec + 500_000_000
                msg.header.stamp = type(msg.header.stamp)(sec=ns // 10**9, nanosec=ns % 10**9)
                raw = store.serialize_ros1(msg, c.msgtype)
            w.write(conns[c.id], t, raw)
    with Bag(rig) as b, warnings.catch_warnings():
        warnings.simplefilter("error")
        assert sum(isinstance(i, Scan) for i in Sequencer(b, "/points", "/imu", SensorConfig()))
    with Bag(ahead) as b, pytest.raises(InputError, match=r"the stamps on /points run 0\.4\d\d s "
                                                          r"ahead .* those on /imu \+0\.000 s"):
        list(Sequencer(b, "/points", "/imu", SensorConfig()))


@pytest.mark.parametrize("step_ms", [21.25, 37.0, 38.75, 48.75, 61.25, 98.75])
def test_an_imu_clock_stepping_back_is_told_from_reordered_messages(step_ms):
    """An IMU clock that steps back mid-recording (by a whole number of periods or between
    them) lays two stretches over each other: once sorted, a window holds about twice the
    samples of the IMU's rate, an error that says so and about how far the clock went back.
    Messages recorded out of order sort into the density they had: bridged, every sample kept,
    also with a burst-stamping driver, host stamps with noise, after a rate change, and after
    an IMU gap (which must not lower the rate the density is held to)."""
    period = 2_500_000
    t = np.arange(10**9, 10**9 + 1200 * period, period)
    stepped = np.r_[t[:600], t[600:] - int(step_ms * 1e6)]
    scans = [scan(int(t[0]) + k * 10**8 + 1, int(t[0]) + (k + 1) * 10**8) for k in range(28)]

    values = np.random.default_rng(0).normal(size=(t.size, 3))  # every sample its own

    def recorded(recv, stamps, scan_latency_ns):
        events = sorted([(int(r), 0, ImuBatch(np.array([int(s)]), values[k:k + 1],
                                              values[k:k + 1] + [0.0, 0.0, 9.81]))
                         for k, (r, s) in enumerate(zip(recv, stamps, strict=True))] +
                        [(s.t_end_ns + scan_latency_ns, 1, s) for s in scans],
                        key=lambda e: e[:2])
        return [e[2] for e in events]

    with pytest.raises(InputError, match=r"IMU stamps on /imu overlap from .* where the IMU's "
                                         r"400 Hz gives .* stepped back by about "
                                         r"(\d\.\d+) s") as info, warnings.catch_warnings():
        # a step's first sample can fall before the sample after a released scan's end (passed
        # on with the scan): a stamp glitch warning may come before the error
        warnings.simplefilter("ignore")
        list(merge(recorded(t, stepped, 5_000_000), imu_topic="/imu"))
    found = float(str(info.value).split("stepped back by about ")[1].split(" s")[0])
    assert found == pytest.approx(step_ms * 1e-3, abs=0.006)
    rng = np.random.default_rng(int(step_ms * 100))
    late = t + 5_000_000
    late[700] += 14_000_000  # one message recorded 14 ms late, after the next burst
    late_gap = t + 5_000_000
    late_gap[440] += 14_000_000  # and in the batch after a 0.3 s IMU gap
    for stamps, recv in ((t, t + rng.integers(0, 30_000_000, t.size)),  # bag-order jitter
                         (t - (t - t[0]) % 10_000_000, late),  # bursts of 4 stamped alike
                         (t + rng.integers(-1_200_000, 1_200_000, t.size), late),  # stamp noise
                         (np.r_[t[:600:2], t[600:]], np.r_[late[:600:2], late[600:]]),  # rate
                         (np.r_[t[:300], t[420:]], np.r_[late[:300], late_gap[420:]])):  # gap
        st = SequencerStats()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the burst stamps' own warning
            out = list(merge(recorded(recv, stamps, 40_000_000), st))
        got = np.concatenate([o.t_ns for o in out if isinstance(o, ImuBatch)])
        assert got.tolist() == np.unique(stamps).tolist() and st.imu_reordered > 0


def test_a_sequencer_on_a_topic_the_bag_lacks_says_so(tmp_path):
    """The README's Python loop with a misspelt topic: an error naming it and the topics of
    that kind the bag has (it yielded IMU alone, and the run blamed the IMU)."""
    import bagfactory as bf

    from adalio.errors import BagError
    from adalio.io.bag import Bag
    from adalio.io.sequencer import Sequencer

    rig = bf.write_static_rig(tmp_path / "rig.bag", duration_s=0.5, columns=30)
    with Bag(rig) as b:
        with pytest.raises(BagError, match=r"topic /point is not in .*rig\.bag; "
                                           r"sensor_msgs/PointCloud2 or Livox CustomMsg topics in the bag: /points "
                                           r"\(Sequencer's lidar_topic\)"):
            Sequencer(b, "/point", "/imu")
        with pytest.raises(BagError, match=r"topic /points in .*rig\.bag is "
                                           r"sensor_msgs/msg/PointCloud2, not sensor_msgs/Imu; "
                                           r"sensor_msgs/Imu topics in the bag: /imu "
                                           r"\(Sequencer's imu_topic\)"):
            Sequencer(b, "/points", "/points")
        assert any(isinstance(i, Scan) for i in Sequencer(b, "/points", "/imu"))
