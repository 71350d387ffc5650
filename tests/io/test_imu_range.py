"""An IMU reading the end of its range (``adalio.io.imu_range``): samples clipped flat at one
extreme value are found per axis and sign, with their count and stretches, against a
brute-force count; a motion whose peaks differ, an IMU at rest and duplicated messages are
not taken for a clipped range."""

from __future__ import annotations

import numpy as np
import pytest

from adalio.io.imu_range import FLOOR, MIN_SAMPLES, RangeMonitor


def _walk(n: int, rate_hz: float = 400.0, seed: int = 0):
    """A hand-held walk's IMU: footsteps at 1.9 Hz on the vertical accelerometer with peaks of
    different heights, a turning gyro, white noise."""
    rng = np.random.default_rng(seed)
    t_s = np.arange(n) / rate_hz
    steps = 1.0 + 0.3 * np.sin(2 * np.pi * 0.13 * t_s)  # each step's peak its own
    accel = np.stack([0.8 * np.sin(2 * np.pi * 0.7 * t_s), 0.5 * np.cos(2 * np.pi * 0.4 * t_s),
                      -9.81 - 4.0 * steps * np.maximum(np.sin(2 * np.pi * 1.9 * t_s), 0) ** 4],
                     axis=1) + 0.01 * rng.standard_normal((n, 3))
    gyro = np.stack([0.3 * np.sin(2 * np.pi * 0.5 * t_s), 0.2 * np.sin(2 * np.pi * 0.3 * t_s),
                     1.5 * np.sin(2 * np.pi * 0.1 * t_s)], axis=1) + 0.002 * rng.standard_normal((n, 3))
    return (np.round(t_s * 1e9).astype(np.int64), gyro, accel)


def _feed(t_ns, gyro, accel, chunk: int = 64) -> RangeMonitor:
    mon = RangeMonitor()
    for k in range(0, len(t_ns), chunk):
        mon.add(t_ns[k:k + chunk], gyro[k:k + chunk], accel[k:k + chunk])
    return mon


def _brute_force(t_ns, x):
    """Samples and stretches at exactly the lowest value of ``x``, and the first one's stamp."""
    at = x == x.min()
    starts = at & ~np.concatenate([[False], at[:-1]])
    return int(at.sum()), int(starts.sum()), int(t_ns[np.flatnonzero(at)[0]])


def test_an_unclipped_walk_reads_no_range_end():
    assert _feed(*_walk(24_000)).found() == []


@pytest.mark.parametrize("chunk", [1, 7, 64, 24_000])
def test_a_clipped_accelerometer_is_found_with_its_count_stretches_and_first_sample(chunk):
    t_ns, gyro, accel = _walk(24_000)
    accel[:, 2] = np.maximum(accel[:, 2], -12.5)  # the footsteps reach -12.6 to -15.0 m/s^2
    found = _feed(t_ns, gyro, accel, chunk).found()
    assert len(found) == 1
    sat = found[0]
    n, runs, first = _brute_force(t_ns, accel[:, 2])
    assert (sat.sensor, sat.axis, sat.value, sat.unit) == ("accelerometer", "z", -12.5, "m/s^2")
    assert (sat.n_samples, sat.n_stretches, sat.first_t_ns) == (n, runs, first)
    assert runs > 50 and n > runs  # one flat top per footstep over the 60 s


def test_a_clipped_gyro_and_both_signs_are_found():
    t_ns, gyro, accel = _walk(24_000)
    gyro[:, 2] = np.clip(gyro[:, 2], -1.2, 1.2)
    found = {(s.sensor, s.axis, s.value) for s in _feed(t_ns, gyro, accel).found()}
    assert found == {("gyro", "z", 1.2), ("gyro", "z", -1.2)}


def test_messages_given_twice_count_once():
    """A recorder that wrote every IMU message twice repeats each extreme: that is one sample,
    so a natural peak read twice is no ceiling, and a clipped one counts its stamps."""
    t_ns, gyro, accel = _walk(24_000)
    twice = (np.repeat(t_ns, 2), np.repeat(gyro, 2, axis=0), np.repeat(accel, 2, axis=0))
    assert _feed(*twice).found() == []
    accel[:, 2] = np.maximum(accel[:, 2], -12.5)
    once = _feed(t_ns, gyro, accel).found()[0]
    doubled = _feed(np.repeat(t_ns, 2), np.repeat(gyro, 2, axis=0),
                    np.repeat(accel, 2, axis=0)).found()[0]
    assert doubled.n_samples == once.n_samples and doubled.n_stretches == once.n_stretches


def test_a_quantized_imu_at_rest_is_not_clipped():
    """At rest a quantized IMU repeats its noise's extreme value many times: below the floor,
    so no range's end (the accelerometer's z sits at gravity, 9.81 < 11.5 m/s^2)."""
    rng = np.random.default_rng(4)
    n = 40_000
    t_ns = np.arange(n, dtype=np.int64) * 2_500_000
    lsb_a, lsb_g = 16 * 9.81 / 32768, np.deg2rad(2000) / 32768  # ±16 g, ±2000 deg/s, 16 bit
    accel = np.round((np.array([0.05, -0.1, -9.81]) + 0.02 * rng.standard_normal((n, 3))) / lsb_a)
    gyro = np.round(0.003 * rng.standard_normal((n, 3)) / lsb_g)
    accel, gyro = accel * lsb_a, gyro * lsb_g
    assert (accel[:, 2] == accel[:, 2].min()).sum() >= MIN_SAMPLES  # repeated: the floor decides
    assert np.abs(accel).max() < FLOOR["accelerometer"] and np.abs(gyro).max() < FLOOR["gyro"]
    assert _feed(t_ns, gyro, accel).found() == []


def test_non_finite_samples_are_passed_over():
    t_ns, gyro, accel = _walk(4_000)
    accel[:, 2] = np.maximum(accel[:, 2], -12.5)
    expected = _feed(t_ns, gyro, accel).found()
    gyro[::50, 0] = np.nan
    accel[3::97] = np.inf
    assert {(s.sensor, s.axis, s.value) for s in _feed(t_ns, gyro, accel).found()} == \
        {(s.sensor, s.axis, s.value) for s in expected}
