"""adalio.jit: the row ranges and the threads that run them."""

from __future__ import annotations

import threading

import numba
import numpy as np
import pytest

from adalio.jit import for_rows, row_ranges


@pytest.mark.parametrize("n", [0, 1, 2, 3, 7, 100, 101])
@pytest.mark.parametrize("parts", [1, 2, 3, 8])
def test_row_ranges_cover_every_row_once_in_order_and_balanced(n: int, parts: int) -> None:
    ranges = row_ranges(n, parts)
    rows = [i for lo, hi in ranges for i in range(lo, hi)]
    assert rows == list(range(n))
    assert len(ranges) == max(1, min(parts, n))
    sizes = [hi - lo for lo, hi in ranges]
    assert max(sizes) - min(sizes) <= 1


def _recorder():
    calls: list[tuple[int, int, int]] = []
    lock = threading.Lock()

    def rows(lo: int, hi: int, x: np.ndarray, out: np.ndarray) -> None:
        out[lo:hi] = 2.0 * x[lo:hi]
        with lock:
            calls.append((lo, hi, threading.get_ident()))

    return rows, calls


def test_for_rows_below_the_threshold_is_one_call_on_the_calling_thread() -> None:
    rows, calls = _recorder()
    x = np.arange(50.0)
    out = np.zeros(50)
    for_rows(rows, 50, x, out, min_rows=51)
    np.testing.assert_array_equal(out, 2.0 * x)
    assert calls == [(0, 50, threading.get_ident())]


def test_for_rows_splits_over_numba_threads_and_fills_every_row() -> None:
    threads = numba.get_num_threads()
    if threads < 2:
        pytest.skip("one numba thread on this machine: nothing to split")
    rows, calls = _recorder()
    x = np.arange(1001.0)
    out = np.zeros(1001)
    for_rows(rows, 1001, x, out, min_rows=10)
    np.testing.assert_array_equal(out, 2.0 * x)
    assert sorted((lo, hi) for lo, hi, _ in calls) == row_ranges(1001, threads)
    assert len({ident for *_, ident in calls}) == threads
    # the calling thread takes the first range
    assert (0, row_ranges(1001, threads)[0][1], threading.get_ident()) in calls
    # numba's thread count is the knob: one thread means one call
    rows1, calls1 = _recorder()
    numba.set_num_threads(1)
    try:
        for_rows(rows1, 1001, x, out, min_rows=10)
    finally:
        numba.set_num_threads(threads)
    assert calls1 == [(0, 1001, threading.get_ident())]
