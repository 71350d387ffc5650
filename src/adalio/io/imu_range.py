"""An IMU that reads the end of its range: samples clipped flat at the same extreme value.

An accelerometer set to ±2 g or ±4 g (on a robot's hard landing, a drop, a kick) or a gyro set
to ±125 °/s stops at its range's end: every sample beyond it reads the
same largest value. A real motion's peaks differ from one another, so one value that the
samples reach again and again at an axis's extreme, and never pass, is a clipped range. Where
it clips, the IMU reports less than the motion, and the filter's prediction between those scans
falls short (Point-LIO models the range in its IMU output model; adalio says where it happened).

:class:`RangeMonitor` follows each axis of both sensors, both signs, over a whole recording in
one pass: the most extreme value so far, how many samples (by distinct stamp: a message given
twice is one sample) read exactly it, in how many separate stretches, and from when.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_SAMPLES = 3
"""Samples (distinct stamps) at exactly an axis's extreme that make it a clipped range."""
FLOOR = {"gyro": 0.5, "accelerometer": 11.5}
"""An extreme below this (rad/s; m/s^2, about 1.2 g) is not taken for a range's end: an IMU at
rest repeats its noise's extreme value (its samples are quantized) well inside it, and no IMU's
range is that small (the smallest usual ones: ±125 °/s = 2.2 rad/s, ±2 g)."""
_CHANNELS = [(sensor, axis, sign) for sign in (1.0, -1.0)
             for sensor in ("gyro", "accelerometer") for axis in "xyz"]


@dataclass(frozen=True)
class Saturation:
    """One axis of one sensor that read the end of its range."""

    sensor: str
    """'gyro' or 'accelerometer'."""
    axis: str
    value: float
    """The clipped value (signed; rad/s or m/s^2, after unit conversions)."""
    n_samples: int
    """Samples (distinct stamps) that read it."""
    n_stretches: int
    """Runs of consecutive samples that read it."""
    first_t_ns: int
    """Stamp of the first sample that read it."""

    @property
    def unit(self) -> str:
        return "rad/s" if self.sensor == "gyro" else "m/s^2"


class RangeMonitor:
    """Feed it every IMU batch of a recording in time order (:meth:`add`); :meth:`found`
    lists the axes whose samples stop flat at one extreme value."""

    def __init__(self) -> None:
        k = len(_CHANNELS)
        self._peak = np.full(k, -np.inf)
        self._n = np.zeros(k, np.int64)
        self._runs = np.zeros(k, np.int64)
        self._first = np.full(k, -1, np.int64)
        self._last_t = np.full(k, np.iinfo(np.int64).min, np.int64)
        self._in_run = np.zeros(k, bool)

    def add(self, t_ns: np.ndarray, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray) -> None:
        ok = np.isfinite(gyro_rad_s).all(axis=1) & np.isfinite(accel_m_s2).all(axis=1)
        if not ok.any():
            return
        t = np.asarray(t_ns, np.int64)[ok]
        both = np.hstack([gyro_rad_s[ok], accel_m_s2[ok]])
        values = np.hstack([both, -both])
        for c in range(values.shape[1]):
            col = values[:, c]
            top = float(col.max())
            if top > self._peak[c]:  # a new extreme: what read the old one was no ceiling
                self._peak[c], self._n[c], self._runs[c] = top, 0, 0
                self._first[c], self._in_run[c] = -1, False
                self._last_t[c] = np.iinfo(np.int64).min
            at = col == self._peak[c]
            if at.any():
                ts = t[at]
                before = np.concatenate([[self._last_t[c]], ts[:-1]])
                self._n[c] += int(np.count_nonzero(ts != before))
                self._last_t[c] = ts[-1]
                previous = np.concatenate([[self._in_run[c]], at[:-1]])
                self._runs[c] += int(np.count_nonzero(at & ~previous))
                if self._first[c] < 0:
                    self._first[c] = ts[0]
            self._in_run[c] = bool(at[-1])

    def found(self) -> list[Saturation]:
        """The axes that read the end of their range: at least :data:`MIN_SAMPLES` samples at
        exactly their extreme, which lies beyond :data:`FLOOR`."""
        out = []
        for c, (sensor, axis, sign) in enumerate(_CHANNELS):
            if self._n[c] >= MIN_SAMPLES and self._peak[c] >= FLOOR[sensor]:
                out.append(Saturation(sensor, axis, sign * float(self._peak[c]), int(self._n[c]),
                                      int(self._runs[c]), int(self._first[c])))
        return out
