"""The one numba decorator of adalio's kernels, and how their row loops use several cores.

``kernel()`` is ``numba.njit(cache=True)``: compiled once per machine and then loaded from
numba's on-disk cache. It also drops the C-callback (cfunc) wrapper that numba builds and
optimizes for every compiled function unless told not to: adalio never passes a kernel as a
first-class function, and that wrapper was about a sixth of the compilation a fresh install
pays on its first run (issue #15, ``benchmarks/bench_resources.py``). The CPython wrapper stays:
without it a call from Python crashes the interpreter instead of raising.

Several cores, two ways:

* ``@kernel(nogil=True)`` on a kernel written as ``rows(lo, hi, ...)`` over a row range, and
  :func:`for_rows` runs contiguous ranges of it on Python threads at once. The result is the
  same whatever the split (every row is computed by the same code). Used for the map search,
  whose ``parallel=True`` twin cost a fresh install's first run 3.5 s of compilation (numba's
  parfor pass, and the row body compiled a second time inside a gufunc) and ran no faster.
* ``@kernel(parallel=True)`` with ``prange``: numba's threading layer, which starts a loop in
  about 10 us against about 140 us for a hand-over to a Python thread on the 2-core dev
  machine. Kept for the undistortion, a loop of 0.3-1 ms per scan, where that hand-over would
  cost 0.15-0.25 ms per scan.

Both use numba's thread count (``NUMBA_NUM_THREADS``, ``numba.set_num_threads``), so the knobs
that set it keep working.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numba
from numba import njit


def kernel(*, inline: str = "never", nogil: bool = False, parallel: bool = False):
    """Decorator: ``@kernel()``, ``@kernel(inline="always")``, ``@kernel(nogil=True)`` for a row
    kernel that :func:`for_rows` may run on several threads, ``@kernel(parallel=True)``."""
    return njit(cache=True, no_cfunc_wrapper=True, inline=inline, nogil=nogil,
                parallel=parallel)


_pools: dict[int, ThreadPoolExecutor] = {}


def _pool(workers: int) -> ThreadPoolExecutor:
    pool = _pools.get(workers)
    if pool is None:
        pool = _pools[workers] = ThreadPoolExecutor(workers, thread_name_prefix="adalio-rows")
    return pool


def row_ranges(n: int, parts: int) -> list[tuple[int, int]]:
    """``[0, n)`` cut into ``min(parts, n)`` contiguous ranges whose sizes differ by at most 1."""
    parts = max(1, min(parts, n))
    q, r = divmod(n, parts)
    out, lo = [], 0
    for j in range(parts):
        hi = lo + q + (1 if j < r else 0)
        out.append((lo, hi))
        lo = hi
    return out


def for_rows(rows: Callable[..., None], n: int, *args, min_rows: int) -> None:
    """``rows(lo, hi, *args)`` over ``[0, n)``: in one call below ``min_rows`` rows or with one
    numba thread, else in one contiguous range per numba thread, the calling thread taking the
    first. ``rows`` must be a ``nogil`` kernel that writes only rows ``lo..hi-1`` of its
    outputs."""
    threads = numba.get_num_threads() if n >= min_rows else 1
    ranges = row_ranges(n, threads)
    if len(ranges) <= 1:
        rows(0, n, *args)
        return
    futures = [_pool(len(ranges) - 1).submit(rows, lo, hi, *args) for lo, hi in ranges[1:]]
    try:
        rows(ranges[0][0], ranges[0][1], *args)
    finally:
        for f in futures:
            f.result()
