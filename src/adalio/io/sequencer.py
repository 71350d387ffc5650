"""Time-ordered merge of IMU samples and LiDAR scans read from a bag.

Bags are ordered by receive time: a sweep's message arrives after the IMU samples stamped during
the sweep. The sequencer yields :class:`ImuBatch` chunks and :class:`Scan` objects such that
every scan comes after all IMU samples with ``t_ns <= scan.t_end_ns`` and the first sample after
it, once received (the propagation's last interval takes the mid-point of the two samples around
the scan end; scans are keyed by their end time), and IMU batches never go back in time. IMU
samples are held for a lookahead window to absorb small reordering. Stamp problems are counted
in :class:`SequencerStats`; IMU stamps going backwards beyond the window, scans whose end times
go backwards, IMU that covers none of the scans, a topic whose clouds are all empty (the error says why: no points, NaN, (0, 0, 0)
placeholders, invalid times) or an IMU topic with no finite sample raise
:class:`~adalio.errors.InputError`. IMU samples with a NaN/inf value are dropped with one warning
naming the topic and the first bad stamp. Times are int64 ns; IMU in rad/s and m/s^2.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from adalio.config import SensorConfig
from adalio.errors import BagError, InputError
from adalio.io.bag import IMU_TYPES, LIDAR_TYPES, LIDAR_WHAT, Bag
from adalio.io.imu_range import RangeMonitor
from adalio.io.livox import lidar_decoder
from adalio.io.pointcloud2 import stamp_to_ns
from adalio.types import ImuBatch, Scan

IMU_LOOKAHEAD_NS = 50_000_000
"""A scan is released once an IMU sample this much later than its end has been read: IMU
messages recorded up to this much out of order are sorted in (10 ms before session 75)."""
IMU_DENSITY_PERIODS = 8
IMU_DENSITY_FACTOR = 1.75
"""A re-sorted held batch with ``IMU_DENSITY_FACTOR`` times the samples of the IMU's rate in a
window of ``IMU_DENSITY_PERIODS`` periods holds two stretches laid over each other: the IMU's
clock stepped back (by about 6 periods or more), an error. Bag-order jitter, burst stamps and
stamp noise leave the density as it was."""
IMU_RATE_SAMPLES = 32
"""Samples of a held batch in time order that measure the IMU's rate (samples per second)."""
IMU_GLITCH_SAMPLES = 2
"""IMU samples in a row stamped before samples already used that are dropped as a stamp glitch
(a seconds/nanoseconds roll-over); more in a row are the clock going back, an error."""
IMU_WINDOW_NS = 2_000_000_000
"""IMU samples older than the newest one by more than this are released even without a scan."""
IMU_ENDS_EARLY_NS = 500_000_000
"""Scans left after the IMU's last sample by more than this are warned about (a note below)."""
ACCEL_UNIT_SAMPLES = 50
"""IMU samples averaged to decide whether the accelerometer reports in g."""
G_TO_M_S2 = 9.80665


@dataclass
class SequencerStats:
    """What the sequencer saw and dropped."""

    imu_samples: int = 0
    imu_nonfinite: int = 0
    """IMU samples dropped for a NaN/inf gyro or accel value."""
    imu_first_nonfinite_ns: int | None = None
    imu_duplicates: int = 0
    imu_conflicting: int = 0
    """Of ``imu_duplicates``: samples whose stamp another sample had, with other values (a
    driver that stamps a burst of samples with one read time); only the first is used."""
    imu_reordered: int = 0
    imu_glitches: int = 0
    """IMU samples dropped for a stamp before samples already used, at most
    ``IMU_GLITCH_SAMPLES`` in a row."""
    scans_out_of_order: int = 0
    """Scans skipped for ending at or before a scan already processed (a cloud recorded out of
    order, or twice), within the IMU window."""
    scans_in: int = 0
    scans_out: int = 0
    scans_empty: int = 0
    scans_before_imu: int = 0
    scans_after_imu: int = 0
    scans_late: int = 0
    imu_first_ns: int | None = None
    imu_last_ns: int | None = None
    scan_first_end_ns: int | None = None
    scan_last_end_ns: int | None = None
    accel_in_g: bool = False
    messages: list[str] = field(default_factory=list)

    def warn(self, text: str) -> None:
        self.messages.append(text)
        warnings.warn(text, stacklevel=3)


def _fmt_s(t_ns: int | None, decimals: int = 3) -> str:
    if t_ns is None:
        return "?"
    q, r = divmod(abs(int(t_ns)), 1_000_000_000)
    text = f"{'-' if t_ns < 0 else ''}{q}.{r:09d}"
    return text[: len(text) - 9 + decimals]


def _rate_hz(t: np.ndarray) -> float:
    """Samples per second of sorted stamps ``t``, gaps left out (intervals over 10 times the
    median interval between distinct stamps): a burst-stamping driver's samples count at their
    rate, and an IMU gap in the batch does not lower it (0.0: no interval to tell)."""
    d = np.diff(t)
    pos = d[d > 0]
    if pos.size == 0:
        return 0.0
    inside = d[d <= 10 * np.median(pos)]
    return inside.size / (float(inside.sum()) * 1e-9) if inside.sum() > 0 else 0.0


def _longest_run(mask: np.ndarray) -> int:
    """The most consecutive True values in a boolean array."""
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return int((ends - starts).max()) if starts.size else 0


def merge(items: Iterable[ImuBatch | Scan], stats: SequencerStats | None = None, *,
          imu_topic: str = "imu", lidar_topic: str = "lidar",
          lookahead_ns: int = IMU_LOOKAHEAD_NS, window_ns: int = IMU_WINDOW_NS,
          why_empty: Callable[[], str] | None = None) -> Iterator[ImuBatch | Scan]:
    """Merge IMU batches and scans given in receive order into processing order.

    ``why_empty()`` (e.g. :meth:`DecodeStats.why_empty`) explains the error when every scan is
    empty."""
    st = stats if stats is not None else SequencerStats()
    imu_t: list[np.ndarray] = []
    imu_g: list[np.ndarray] = []
    imu_a: list[np.ndarray] = []
    pending: list[Scan] = []
    released_imu_t: int | None = None
    released_scan_end: int | None = None
    max_imu_t: int | None = None
    held: list[str] = []
    glitch_run = 0
    glitch_note: list[str] = []
    imu_rate_hz = 0.0
    """The IMU's samples per second, from the latest held batch in time order."""

    def note(text: str) -> None:
        """Warn once a scan has gone out; until then hold the text, so that a stream that ends
        in an error (nothing usable) prints that error alone."""
        if st.scans_out:
            st.warn(text)
        else:
            held.append(text)

    def check_overlap(tu: np.ndarray) -> None:
        """InputError if a re-sorted held batch (``tu``, exact copies removed) holds, in some
        window of ``IMU_DENSITY_PERIODS`` periods, ``IMU_DENSITY_FACTOR`` times the samples the
        IMU's rate gives: two stretches laid over each other, the IMU's clock stepped back.
        Messages recorded out of order sort back into the density they had."""
        w_ns = round(IMU_DENSITY_PERIODS / imu_rate_hz * 1e9)
        n_in = np.searchsorted(tu, tu + w_ns, side="left") - np.arange(tu.size)
        dense = np.flatnonzero((tu + w_ns <= tu[-1]) &
                               (n_in >= IMU_DENSITY_FACTOR * IMU_DENSITY_PERIODS))
        if dense.size:
            t0, t1 = int(tu[dense[0]]), int(tu[dense[-1]]) + w_ns
            inside = int(np.count_nonzero((tu >= t0) & (tu < t1)))
            step_s = (inside - (t1 - t0) * 1e-9 * imu_rate_hz) / imu_rate_hz
            raise InputError(f"IMU stamps on {imu_topic} overlap from {_fmt_s(t0)} to "
                             f"{_fmt_s(t1)} s: once sorted, they hold {inside} samples where "
                             f"the IMU's {imu_rate_hz:.0f} Hz gives "
                             f"{(t1 - t0) * 1e-9 * imu_rate_hz:.0f}, two stretches laid over each "
                             f"other: the IMU's clock stepped back by about {step_s:.3f} s "
                             "mid-recording (or two IMUs publish on the topic); re-stamp the bag")

    def take_imu(upto_ns: int, one_past: bool = False) -> ImuBatch | None:
        nonlocal imu_t, imu_g, imu_a, released_imu_t, imu_rate_hz
        if not imu_t:
            return None
        t = np.concatenate(imu_t)
        g = np.concatenate(imu_g)
        a = np.concatenate(imu_a)
        resorted = t.size > 1 and bool(np.any(np.diff(t) < 0))
        if resorted:
            order = np.argsort(t, kind="stable")
            st.imu_reordered += int(np.count_nonzero(np.diff(t) < 0))
            t, g, a = t[order], g[order], a[order]
        if t.size > 1:
            fresh = np.r_[True, (np.diff(t) != 0) | np.any(g[1:] != g[:-1], axis=1) |
                          np.any(a[1:] != a[:-1], axis=1)]  # not an exact copy of the one before
            tu = t[fresh]
            if resorted and imu_rate_hz:
                check_overlap(tu)
            elif not resorted and tu.size >= IMU_RATE_SAMPLES:
                imu_rate_hz = _rate_hz(tu) or imu_rate_hz
        if t.size > 1:
            keep = np.r_[True, np.diff(t) > 0]
            if not keep.all():
                st.imu_duplicates += int(np.count_nonzero(~keep))
                first = np.maximum.accumulate(np.where(keep, np.arange(t.size), 0))
                differ = ~keep & (np.any(g != g[first], axis=1) | np.any(a != a[first], axis=1))
                if differ.any():
                    if not st.imu_conflicting:
                        note(f"IMU samples on {imu_topic} share a stamp with other values (first "
                             f"at {_fmt_s(int(t[differ][0]), 9)} s): the driver stamps several "
                             "samples with one time (a burst read at once?); only the first of "
                             "each stamp is used, the others are dropped and counted (fix the "
                             "driver's stamps to keep them)")
                    st.imu_conflicting += int(np.count_nonzero(differ))
                t, g, a = t[keep], g[keep], a[keep]
        k = int(np.searchsorted(t, upto_ns, side="right"))
        if one_past:
            k = min(k + 1, t.size)
        imu_t, imu_g, imu_a = [t[k:]], [g[k:]], [a[k:]]
        if k == 0:
            return None
        released_imu_t = int(t[k - 1])
        return ImuBatch(t[:k].copy(), g[:k].copy(), a[:k].copy())

    def out_of_order(end: int) -> None:
        """A scan ending at or before one already processed, within the IMU window: skipped."""
        st.scans_out_of_order += 1
        if st.scans_out_of_order == 1:
            again = "again (the cloud recorded twice?)" if end == released_scan_end else \
                f"after the scan ending at {_fmt_s(released_scan_end)} s was processed (a cloud " \
                "recorded out of order?)"
            note(f"scan on {lidar_topic} ending at {_fmt_s(end)} s arrived {again}: skipped; "
                 "further ones are counted")

    def release(final: bool) -> Iterator[ImuBatch | Scan]:
        nonlocal released_scan_end
        pending.sort(key=lambda s: s.t_end_ns)
        while pending and max_imu_t is not None and (
                max_imu_t >= pending[0].t_end_ns + lookahead_ns
                or (final and max_imu_t >= pending[0].t_end_ns)):
            scan = pending.pop(0)
            if released_scan_end is not None and scan.t_end_ns <= released_scan_end:
                out_of_order(scan.t_end_ns)
                continue
            batch = take_imu(scan.t_end_ns, one_past=True)
            if batch is not None:
                yield batch
            if st.imu_first_ns is None or scan.t_start_ns < st.imu_first_ns:
                st.scans_before_imu += 1
                continue
            released_scan_end = scan.t_end_ns
            st.scans_out += 1
            while held:
                st.warn(held.pop(0))
            yield scan
        if max_imu_t is not None and (not pending or final):
            batch = take_imu(max_imu_t if final and not pending else max_imu_t - window_ns)
            if batch is not None:
                yield batch

    for item in items:
        if isinstance(item, ImuBatch):
            if len(item) == 0:
                continue
            t = np.asarray(item.t_ns, dtype=np.int64)
            finite = np.isfinite(item.gyro_rad_s).all(axis=1) & \
                np.isfinite(item.accel_m_s2).all(axis=1)
            if not finite.all():
                if st.imu_first_nonfinite_ns is None:
                    st.imu_first_nonfinite_ns = int(t[~finite][0])
                    note(f"IMU sample on {imu_topic} at {_fmt_s(int(t[~finite][0]), 9)} s has "
                         "a NaN/inf gyro or accel value: dropped (further ones are counted)")
                st.imu_nonfinite += int(np.count_nonzero(~finite))
                t = t[finite]
                item = ImuBatch(t, item.gyro_rad_s[finite], item.accel_m_s2[finite])
                if t.size == 0:
                    continue
            back = t < released_imu_t if released_imu_t is not None else None
            if back is not None and back.any():
                run = max(glitch_run + (back.size if back.all() else int(back.argmin())),
                          _longest_run(back))
                glitch_run = run if back.all() else int(back[::-1].argmin()) if back[-1] else 0
                if run > IMU_GLITCH_SAMPLES:
                    bad = int(t[back][0])
                    raise InputError(f"IMU stamps on {imu_topic} go backwards: {_fmt_s(bad, 9)} "
                                     f"s after {_fmt_s(released_imu_t, 9)} s, over "
                                     f"{run} samples in a row (more "
                                     "than a stamp glitch): the IMU's clock went back, or the "
                                     "bag is not in time order; re-stamp or sort the IMU topic")
                if not st.imu_glitches:  # said once the stream goes on (else it is the error)
                    bad = int(t[back][0])
                    glitch_note.append(f"IMU sample on {imu_topic} stamped {_fmt_s(bad, 9)} s, "
                                       f"{(released_imu_t - bad) * 1e-9:.3f} s before samples "
                                       "already used (a stamp glitch?): dropped; further ones "
                                       "are counted")
                st.imu_glitches += int(back.sum())
                if not back[-1]:
                    while glitch_note:
                        note(glitch_note.pop())
                t = t[~back]
                item = ImuBatch(t, item.gyro_rad_s[~back], item.accel_m_s2[~back])
                if t.size == 0:
                    continue
            elif back is not None:
                glitch_run = 0
                while glitch_note:
                    note(glitch_note.pop())
            if released_imu_t is not None:
                dup = t == released_imu_t
                if dup.any():
                    st.imu_duplicates += int(dup.sum())
                    t = t[~dup]
                    item = ImuBatch(t, item.gyro_rad_s[~dup], item.accel_m_s2[~dup])
                    if t.size == 0:
                        continue
            st.imu_samples += int(t.size)
            tmin, tmax = int(t.min()), int(t.max())
            st.imu_first_ns = tmin if st.imu_first_ns is None else min(st.imu_first_ns, tmin)
            st.imu_last_ns = tmax if st.imu_last_ns is None else max(st.imu_last_ns, tmax)
            max_imu_t = st.imu_last_ns
            imu_t.append(t)
            imu_g.append(np.asarray(item.gyro_rad_s, dtype=np.float64).reshape(-1, 3))
            imu_a.append(np.asarray(item.accel_m_s2, dtype=np.float64).reshape(-1, 3))
        else:
            st.scans_in += 1
            if len(item) == 0:
                st.scans_empty += 1
                if st.scans_empty == 1:
                    note(f"empty scan on {lidar_topic} at {item.stamp_ns * 1e-9:.3f} s skipped "
                         "(no valid points); further ones are counted")
                continue
            end = item.t_end_ns
            st.scan_first_end_ns = end if st.scan_first_end_ns is None else st.scan_first_end_ns
            if released_scan_end is not None and end <= released_scan_end and \
                    released_scan_end - end < window_ns:
                out_of_order(end)
                continue
            if released_scan_end is not None and end <= released_scan_end:
                raise InputError(f"scan end times on {lidar_topic} go backwards: "
                                 f"{_fmt_s(end, 9)} s after {_fmt_s(released_scan_end, 9)} s; "
                                 "check sensor.point_time_* (unit/reference) or re-stamp the "
                                 "bag")
            st.scan_last_end_ns = end if st.scan_last_end_ns is None \
                else max(st.scan_last_end_ns, end)
            if released_imu_t is not None and end < released_imu_t:
                st.scans_late += 1
                if st.scans_late == 1:
                    note(f"scan on {lidar_topic} ending at {_fmt_s(end)} s arrived more than "
                         f"{window_ns * 1e-9:.1f} s after its IMU samples; skipped (further "
                         "ones are counted)")
                continue
            pending.append(item)
        yield from release(final=False)
    yield from release(final=True)
    while glitch_note:
        note(glitch_note.pop())
    if pending:
        st.scans_after_imu += len(pending)
        if st.scans_out and pending[-1].t_end_ns - (max_imu_t or 0) > IMU_ENDS_EARLY_NS:
            st.warn(f"the IMU on {imu_topic} ends at {_fmt_s(max_imu_t)} s, "
                    f"{(pending[-1].t_end_ns - (max_imu_t or 0)) * 1e-9:.2f} s before the last "
                    f"scan on {lidar_topic}: its last {len(pending)} scans are not posed (no "
                    "IMU to predict them)")
        pending.clear()
    batch = take_imu(max_imu_t) if max_imu_t is not None else None
    if batch is not None:
        yield batch
    usable = st.scans_in - st.scans_empty
    if st.scans_in and usable == 0:
        why = why_empty() if why_empty is not None else ""
        raise InputError(f"all {st.scans_in} clouds on {lidar_topic} are empty after dropping "
                         f"invalid points ({why or 'no finite points'}); check the lidar "
                         "topic and its driver")
    if st.imu_nonfinite and st.imu_samples == 0:
        raise InputError(f"all {st.imu_nonfinite} IMU samples on {imu_topic} have NaN/inf "
                         f"values (first at {_fmt_s(st.imu_first_nonfinite_ns, 9)} s); check "
                         "the IMU topic (--imu-topic) and its driver")
    if usable and st.scans_out == 0 and st.scans_late:
        raise InputError(f"{st.scans_late} of {usable} scans on {lidar_topic} arrived more than "
                         f"{window_ns * 1e-9:.1f} s after the IMU samples on {imu_topic} of their "
                         "time, and were skipped: their stamps run behind the IMU's (a LiDAR "
                         "clock behind the IMU's, or clouds recorded that late); set "
                         "sensor.imu_time_offset_s (the IMU's stamps minus the LiDAR's) or "
                         "re-stamp the bag")
    if usable and st.scans_out == 0:
        raise InputError(f"IMU on {imu_topic} ({_fmt_s(st.imu_first_ns)}..{_fmt_s(st.imu_last_ns)}"
                         f" s, {st.imu_samples} samples) does not cover any scan on {lidar_topic} "
                         f"({_fmt_s(st.scan_first_end_ns)}..{_fmt_s(st.scan_last_end_ns)} s); "
                         "check the topics and the bag's time ranges")
    while held:
        st.warn(held.pop(0))
    for n, what in ((st.scans_empty, "empty scans"),
                    (st.scans_before_imu, "scans before the first IMU sample"),
                    (st.scans_after_imu, "scans after the last IMU sample"),
                    (st.scans_late, "scans arriving later than the IMU window"),
                    (st.scans_out_of_order, "scans arriving after later ones (twice?)")):
        if n:
            st.messages.append(f"skipped {n} {what}")
    if st.imu_nonfinite:
        st.messages.append(f"skipped {st.imu_nonfinite} IMU samples with NaN/inf values on "
                           f"{imu_topic} (first at {_fmt_s(st.imu_first_nonfinite_ns, 3)} s)")
    if st.imu_reordered:
        st.messages.append(f"re-sorted {st.imu_reordered} out-of-order IMU samples on {imu_topic}")
    if st.imu_glitches:
        st.messages.append(f"dropped {st.imu_glitches} IMU samples on {imu_topic} stamped before "
                           "samples already used (stamp glitches)")
    if st.imu_conflicting:
        total = st.imu_samples  # counted as read, before duplicates are dropped
        st.messages.append(f"dropped {st.imu_conflicting} of {total} IMU samples on {imu_topic} "
                           f"({100.0 * st.imu_conflicting / max(total, 1):.0f} %): stamped at "
                           "the time of another sample with other values")


def imu_msg_arrays(msgs: list[Any]) -> ImuBatch:
    """sensor_msgs/Imu messages → ImuBatch (accel as recorded)."""
    t = np.array([stamp_to_ns(m.header.stamp) for m in msgs], dtype=np.int64)
    g = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z]
                  for m in msgs], dtype=np.float64).reshape(-1, 3)
    a = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
                  for m in msgs], dtype=np.float64).reshape(-1, 3)
    return ImuBatch(t, g, a)


CLOCK_AHEAD_S = 0.25
"""A topic whose stamps run this far ahead of the times the bag received its messages, while
the other topic's do not, is on another clock (:class:`ClockCheck`)."""
CLOCK_AGREE_S = 0.05
"""The other topic's stamps at most this far ahead of their receive times: on the recorder's
clock, so a topic ahead of it by ``CLOCK_AHEAD_S`` is ahead of the other topic too."""
CLOCK_BEHIND_S = 0.5
"""Scans received this much later after their end than IMU samples after their stamps are
warned about: late clouds, or a LiDAR clock behind the IMU's (:class:`ClockCheck`)."""
CLOCK_CHECK_COUNTS = (10, 200)
"""Scans and IMU samples whose stamps are compared with their receive times."""
CLOCK_SPREAD_S = 0.1
"""Receive times whose offsets from the stamps spread more than this (median absolute
deviation; a bag written with one receive time for all) tell nothing: the check is skipped."""
NOT_PROVIDED_S = 2.0
"""Seconds of IMU stamps whose gyro (or accelerometer) says 'not provided' before that is an
error (a driver's start-up samples may say so for a while)."""
INTERLEAVE_SAMPLES = 400
"""The first IMU samples on which :func:`interleaved_sources` judges whether the topic carries
two IMUs' samples in turn."""
INTERLEAVE_RATIO = 16.0
"""Consecutive samples whose mean squared difference exceeds this many times that of samples
two apart alternate between two sources: one IMU's white noise gives about 1, its motion less
(a smooth signal's differences grow with the lag), a drone's propellers up to 4.7 (EuRoC
MH_01's ADIS16448 at 200 Hz, 400-sample windows); two heads mounted apart give thousands."""
INTERLEAVE_FLOOR = 2e-3
"""...and whose RMS difference exceeds this fraction of the mean specific force (about 0.02
m/s² at rest, whatever the unit): far above an accelerometer's quantization."""


def interleaved_sources(t_ns: np.ndarray, accel: np.ndarray) -> float | None:
    """How many times more consecutive accelerometer samples differ than samples two apart
    (RMS, in stamp order), if that says the samples alternate between two IMUs, else None.

    Two IMUs published on one topic under one frame id (livox_ros_driver2 with several LiDARs
    and ``multi_topic: 0``) take turns: each step crosses from one to the other (their biases,
    or gravity in their own axes), while samples two apart come from the same one. So it takes
    all of: consecutive differences above ``sqrt(INTERLEAVE_RATIO)`` times those two apart, and
    above ``INTERLEAVE_FLOOR``; and the even and the odd samples' means apart by at least half
    the consecutive RMS difference, a lasting offset between the two streams. A vibration near
    half the IMU's rate also makes consecutive samples differ most, but its even and odd
    samples share one mean (EuRoC MH_01's at most 0.29 of that difference)."""
    ok = np.isfinite(accel).all(axis=1)
    a = accel[ok][np.argsort(t_ns[ok], kind="stable")]
    if len(a) < 4:
        return None
    d1 = float(np.mean(np.sum(np.diff(a, axis=0) ** 2, axis=1)))
    d2 = float(np.mean(np.sum((a[2:] - a[:-2]) ** 2, axis=1)))
    if not (d1 > INTERLEAVE_RATIO * d2
            and np.sqrt(d1) > INTERLEAVE_FLOOR * float(np.linalg.norm(a.mean(axis=0)))):
        return None
    offset = float(np.linalg.norm(a[0::2].mean(axis=0) - a[1::2].mean(axis=0)))
    return float(np.sqrt(d1 / d2)) if offset >= 0.5 * np.sqrt(d1) else None


def check_imu_messages(msgs: list[Any], batch: ImuBatch, topic: str, seen: dict) -> None:
    """InputError for IMU messages adalio cannot use as one IMU: a gyro or accelerometer the
    messages say they do not provide (ROS REP 145: element 0 of its covariance -1) with all
    values zero, over ``NOT_PROVIDED_S`` of stamps before any real value; or samples
    from more than one (named) frame on the topic: two IMUs publishing on it, which merged would
    read as one at twice the rate; or, over the first ``INTERLEAVE_SAMPLES``, samples that
    alternate between two IMUs under one frame id (:func:`interleaved_sources`). ``seen``
    carries the state between calls."""
    for what, cov, values in (("gyro", "angular_velocity_covariance", batch.gyro_rad_s),
                              ("accelerometer", "linear_acceleration_covariance",
                               batch.accel_m_s2)):
        if seen.get(what) is False:
            continue  # it has given values
        c = getattr(msgs[0], cov, None)
        if c is not None and len(c) and float(c[0]) == -1.0 and not np.any(values):
            since = seen.setdefault(what, int(batch.t_ns[0]))
            if int(batch.t_ns[-1]) - since >= NOT_PROVIDED_S * 1e9:
                raise InputError(f"the IMU on {topic} provides no {what}: its messages set "
                                 f"{cov}[0] = -1 (ROS: not provided) and the values are zero, "
                                 f"for {(int(batch.t_ns[-1]) - since) * 1e-9:.1f} s; adalio "
                                 "needs a 6-axis IMU (gyro and accelerometer): give another IMU "
                                 "topic (--imu-topic)")
        else:
            seen[what] = False
    early = seen.setdefault("early", [])
    if early is not None:
        early.append((batch.t_ns, batch.accel_m_s2))
        if sum(len(t) for t, _ in early) >= INTERLEAVE_SAMPLES:
            seen["early"] = None
            ratio = interleaved_sources(np.concatenate([t for t, _ in early]),
                                        np.concatenate([a for _, a in early]))
            if ratio is not None:
                frame = msgs[0].header.frame_id or "no frame id"
                raise InputError(
                    f"IMU samples on {topic} alternate between two sets of values: consecutive "
                    f"samples differ {ratio:.1f}x as much as samples two apart (one IMU's about "
                    f"as much or less): two IMUs publish on the topic under one frame id "
                    f"('{frame}'), as livox_ros_driver2 does for several LiDARs with "
                    "multi_topic: 0; record with one topic per LiDAR (multi_topic: 1) and give "
                    "one IMU's topic (--imu-topic)")
    frames = seen.setdefault("frames", set())
    new = {m.header.frame_id for m in msgs} - frames - {""}
    if new:
        frames |= new
        if len(frames) > 1:
            names = ", ".join(f"'{f}'" for f in sorted(frames))
            raise InputError(f"IMU messages on {topic} come from more than one frame ({names}): "
                             "two IMUs publish on the topic, and merged they would read as one "
                             "at twice the rate; record one IMU per topic, or copy the bag with "
                             "only one of them")


class ClockCheck:
    """Whether the LiDAR's and the IMU's stamps are on one clock, from the bag's receive times.

    A message cannot be received before the instant its stamp names, so stamps that run ahead
    of their receive times by over ``CLOCK_AHEAD_S`` on one topic, while the other topic's are
    not ahead of theirs (within ``CLOCK_AGREE_S``: on the recorder's clock), mean that topic's
    clock runs ahead of the other's (a LiDAR on its own or PTP time, an IMU on the recorder's).
    adalio pairs the two by their stamps, so that would be a silent error (the 8 s hall 12.8 cm
    off at 0.5 s). Both ahead (a recorder whose clock is behind the sensors') says nothing.
    Stamps that run behind their receive times are not told apart from late delivery, which is
    harmless: a warning where they lag the other topic's by over ``CLOCK_BEHIND_S``. The
    LiDAR's offset is its scans' end (the last point's time) minus the receive time; the IMU's
    is its stamp, moved by ``sensor.imu_time_offset_s``, minus the receive time."""

    def __init__(self, lidar_topic: str, imu_topic: str,
                 warn: Callable[[str], None] | None = None) -> None:
        self.lidar_topic, self.imu_topic = lidar_topic, imu_topic
        self.warn = warn or (lambda text: warnings.warn(text, stacklevel=3))
        """Where the warning goes (the sequencer's stats, so the summary has it too)."""
        self.d_lidar: list[int] = []
        self.d_imu: list[int] = []
        self.done = False

    def add_imu(self, recv_ns: int, stamp_ns: int) -> None:
        if len(self.d_imu) < CLOCK_CHECK_COUNTS[1]:
            self.d_imu.append(stamp_ns - recv_ns)

    def add_scan(self, recv_ns: int, end_ns: int) -> None:
        if len(self.d_lidar) < CLOCK_CHECK_COUNTS[0]:
            self.d_lidar.append(end_ns - recv_ns)
        if (len(self.d_lidar), len(self.d_imu)) >= CLOCK_CHECK_COUNTS:
            self.check()

    def check(self) -> None:
        """InputError if one topic's stamps run ahead of the other's (see the class)."""
        if self.done or not self.d_lidar or not self.d_imu:
            return
        self.done = True
        d = {}
        for name, vals in (("lidar", self.d_lidar), ("imu", self.d_imu)):
            v = np.asarray(vals, dtype=np.float64) * 1e-9
            med = float(np.median(v))
            if float(np.median(np.abs(v - med))) > CLOCK_SPREAD_S:
                return
            d[name] = med
        for ahead, other in (("lidar", "imu"), ("imu", "lidar")):
            lead = d[ahead] - d[other]
            if d[ahead] > CLOCK_AHEAD_S and lead > CLOCK_AHEAD_S and d[other] <= CLOCK_AGREE_S:
                topic = {"lidar": self.lidar_topic, "imu": self.imu_topic}
                fix = -lead if ahead == "lidar" else lead
                how = (f"set sensor.imu_time_offset_s: {fix:.3f} (the IMU's stamps minus the "
                       "LiDAR's) or re-stamp the bag" if abs(fix) <= 1.0 else
                       "re-stamp the bag (sensor.imu_time_offset_s reaches 1 s)")
                raise InputError(
                    f"the stamps on {topic[ahead]} run {d[ahead]:.3f} s ahead of the times the "
                    f"bag received them, and those on {topic[other]} "
                    f"{round(d[other], 3) + 0.0:+.3f} s: the "
                    f"{'LiDAR' if ahead == 'lidar' else 'IMU'}'s clock runs about {lead:.2f} s "
                    f"ahead of the {'IMU' if ahead == 'lidar' else 'LiDAR'}'s, and adalio pairs "
                    f"the two by their stamps; {how}")
        lag = d["imu"] - d["lidar"]
        if CLOCK_BEHIND_S < lag <= IMU_WINDOW_NS * 1e-9:  # beyond: the scans are skipped, and
            fix = (f"set sensor.imu_time_offset_s: {lag:.3f}, the IMU's stamps minus the "  # said
                   "LiDAR's, or re-stamp the bag" if lag <= 1.0 else "re-stamp the bag")
            self.warn(
                f"scans on {self.lidar_topic} end {round(-d['lidar'], 2) + 0.0:.2f} s before "
                f"the bag received them, IMU samples on {self.imu_topic} "
                f"{round(-d['imu'], 2) + 0.0:.2f} s: either the clouds came {lag:.2f} s late "
                f"(harmless), or the LiDAR's clock runs {lag:.2f} s behind the IMU's, which "
                "adalio cannot tell from the bag and which would pair each scan with the wrong "
                f"IMU samples (then {fix})")


def _inverse_unless_identity(S: list[list[float]]) -> np.ndarray | None:
    """The inverse of a sensitivity matrix (``sensor.gyro_sensitivity``), None for the identity
    (the samples are then read as they are, bit for bit)."""
    M = np.asarray(S, dtype=np.float64)
    return None if np.array_equal(M, np.eye(3)) else np.linalg.inv(M)


def usable_accel(accel: np.ndarray) -> np.ndarray:
    """The samples that can tell the accelerometer's unit: finite and not all zero (a driver's
    start-up placeholders, as NaN samples are)."""
    return accel[np.isfinite(accel).all(axis=1) & np.any(accel != 0.0, axis=1)]


def accel_is_in_g(accel: np.ndarray) -> bool:
    """True if the mean accelerometer norm of (static-ish) samples is near 1 (units of g);
    non-finite and all-zero samples do not count (:func:`usable_accel`)."""
    accel = usable_accel(accel) if accel.ndim == 2 else accel
    if accel.shape[0] == 0:
        return False
    norm = float(np.linalg.norm(np.mean(accel, axis=0)))
    return 0.5 < norm < 2.0


class Sequencer:
    """Decode and merge the LiDAR and IMU topics of an opened :class:`Bag`.

    Iterating yields ``ImuBatch`` and ``Scan`` objects in processing order; ``stats`` and
    ``decoder.time_spec`` describe what was seen. The bag is read ahead in a thread
    (:meth:`Bag.messages`' ``read_ahead``) unless :attr:`read_ahead` is False; the decoding
    stays in the caller's thread, where its warnings are caught.
    """

    read_ahead: bool = True
    """Read the bag ahead in a thread, whose decompression overlaps the estimator on a spare
    core. ``adalio batch``'s embedded workers switch it off for their process: they already
    share the cores, one bag each, and there the thread only competes (two 2000-column mcap
    bags on two workers and two cores: 28.7-30.4 s with it, 26.7-27.3 s without)."""

    def __init__(self, bag: Bag, lidar_topic: str, imu_topic: str,
                 sensor: SensorConfig | None = None, *, imu_chunk: int = 64,
                 lookahead_ns: int = IMU_LOOKAHEAD_NS, start_ns: int | None = None,
                 read_ahead: bool | None = None) -> None:
        bag.select_topic(lidar_topic, LIDAR_TYPES, LIDAR_WHAT, "Sequencer's lidar_topic")
        bag.select_topic(imu_topic, IMU_TYPES, "sensor_msgs/Imu", "Sequencer's imu_topic")
        self.bag = bag
        self.start_ns = start_ns
        """Messages received before this time (bag clock, int64 ns) are not read."""
        self.lidar_topic = lidar_topic
        self.imu_topic = imu_topic
        self.sensor = sensor or SensorConfig()
        self.decoder = lidar_decoder(bag.msgtype(lidar_topic), self.sensor, lidar_topic)
        self.stats = SequencerStats()
        self.imu_chunk = imu_chunk
        self.lookahead_ns = lookahead_ns
        self._accel_scale: float | None = {"m_s2": 1.0, "g": G_TO_M_S2}.get(
            self.sensor.accel_unit)
        self.range_monitor = RangeMonitor()
        """Every IMU sample read, in the sensor's own axes and in rad/s and m/s^2: where it
        reads the end of its range (``range_monitor.found()``, once the iteration is done)."""
        if read_ahead is not None:
            self.read_ahead = read_ahead

    def _raw(self) -> Iterator[ImuBatch | Scan]:
        """Decoded scans and IMU batches in receive order; IMU stamps moved onto the LiDAR's
        clock by ``sensor.imu_time_offset_s``."""
        imu_msgs: list[Any] = []
        imu_seen: dict = {}
        held: list[ImuBatch | Scan] = []
        offset_ns = round(self.sensor.imu_time_offset_s * 1e9)

        def flush_imu() -> ImuBatch | None:
            if not imu_msgs:
                return None
            try:
                batch = imu_msg_arrays(imu_msgs)
            except (AttributeError, TypeError, ValueError):
                raise BagError(f"messages on {self.imu_topic} are not sensor_msgs/Imu") from None
            check_imu_messages(imu_msgs, batch, self.imu_topic, imu_seen)
            imu_msgs.clear()
            if offset_ns:
                batch.t_ns = batch.t_ns - offset_ns
            return batch

        gyro_scale = np.pi / 180.0 if self.sensor.gyro_unit == "deg_s" else 1.0
        gyro_inv = _inverse_unless_identity(self.sensor.gyro_sensitivity)
        accel_inv = _inverse_unless_identity(self.sensor.accel_sensitivity)

        def scaled(item: ImuBatch | Scan) -> ImuBatch | Scan:
            if isinstance(item, ImuBatch) and self._accel_scale != 1.0:
                item.accel_m_s2 = item.accel_m_s2 * self._accel_scale
            if isinstance(item, ImuBatch) and gyro_scale != 1.0:
                item.gyro_rad_s = item.gyro_rad_s * gyro_scale
            if isinstance(item, ImuBatch):  # as read: a sensitivity correction mixes the axes
                self.range_monitor.add(item.t_ns, item.gyro_rad_s, item.accel_m_s2)
            if isinstance(item, ImuBatch) and gyro_inv is not None:
                item.gyro_rad_s = item.gyro_rad_s @ gyro_inv.T
            if isinstance(item, ImuBatch) and accel_inv is not None:
                item.accel_m_s2 = item.accel_m_s2 @ accel_inv.T
            return item

        def decide(force: bool) -> Iterator[ImuBatch | Scan]:
            if self._accel_scale is None:  # the samples that can tell the unit, until decided
                acc = [usable_accel(h.accel_m_s2) for h in held if isinstance(h, ImuBatch)]
                n = sum(len(a) for a in acc)
            if self._accel_scale is None and (n >= ACCEL_UNIT_SAMPLES or force):
                in_g = accel_is_in_g(np.concatenate(acc)[:ACCEL_UNIT_SAMPLES]) if acc else False
                self._accel_scale = G_TO_M_S2 if in_g else 1.0
                self.stats.accel_in_g = in_g
                if in_g:
                    self.stats.warn(f"accelerometer on {self.imu_topic} reports in g (mean norm "
                                    f"~1); converting to m/s^2 (set sensor.accel_unit to "
                                    "silence)")
            if self._accel_scale is not None:
                for h in held:
                    yield scaled(h)
                held.clear()

        clock = ClockCheck(self.lidar_topic, self.imu_topic, self.stats.warn)
        for topic, t_recv, msg in self.bag.messages([self.lidar_topic, self.imu_topic],
                                                    start_ns=self.start_ns,
                                                    read_ahead=self.read_ahead):
            if topic == self.imu_topic:
                imu_msgs.append(msg)
                if not clock.done:
                    with contextlib.suppress(AttributeError, TypeError, ValueError):
                        clock.add_imu(t_recv, stamp_to_ns(msg.header.stamp) - offset_ns)
                if len(imu_msgs) >= self.imu_chunk:
                    held.append(flush_imu())
                    yield from decide(False)
            else:
                batch = flush_imu()
                if batch is not None:
                    held.append(batch)
                try:
                    scan = self.decoder.decode(msg)
                except (AttributeError, TypeError):
                    raise BagError(f"messages on {self.lidar_topic} are not "
                                   f"{LIDAR_WHAT}") from None
                held.append(scan)
                if not clock.done and len(scan):
                    clock.add_scan(t_recv, scan.t_end_ns)
                yield from decide(False)
        clock.check()
        batch = flush_imu()
        if batch is not None:
            held.append(batch)
        yield from decide(True)

    def __iter__(self) -> Iterator[ImuBatch | Scan]:
        return merge(self._raw(), self.stats, imu_topic=self.imu_topic,
                     lidar_topic=self.lidar_topic, lookahead_ns=self.lookahead_ns,
                     why_empty=self.decoder.stats.why_empty)
