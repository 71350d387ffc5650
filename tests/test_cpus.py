"""adalio.cpus: the CPUs counted are those this process may run on, as numba counts them."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from adalio.cpus import usable_cpus


def test_the_cpus_counted_are_those_this_process_may_run_on(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Held to one CPU (taskset, a batch job's cpuset) on a machine of several, the helper would
    share that CPU with the run: the count is the process's affinity where the platform has
    one, and the machine's count where it has none."""
    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3}, raising=False)
    assert usable_cpus() == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 5}, raising=False)
    assert usable_cpus() == 2
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    assert usable_cpus() == 8


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="no CPU affinity here")
def test_a_process_held_to_one_cpu_counts_one() -> None:
    """The real affinity, set in a child process (as ``taskset -c 0`` sets it)."""
    code = ("import os; os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); "
            "from adalio.cpus import usable_cpus; print(usable_cpus())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    assert out.stdout.split() == ["1"]
