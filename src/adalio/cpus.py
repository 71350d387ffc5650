"""The CPUs this process may run on, as numba counts its threads.

``os.cpu_count()`` is the machine's count. A process held to fewer (``taskset``, a batch job's
cpuset under SLURM, Docker's ``--cpuset-cpus``) runs on its affinity, which numba reads for its
default thread count; the warm-up helper (:mod:`adalio.lio.warmup`) and ``adalio batch``'s
embedded workers count the same CPUs. A CPU quota (Docker's ``--cpus``) shows in neither.
"""

from __future__ import annotations

import os


def usable_cpus() -> int:
    """The CPUs this process may run on: its affinity where the platform gives one, else
    ``os.cpu_count()`` (at least 1)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # no affinity on this platform (macOS, Windows)
        return os.cpu_count() or 1
