"""Importing adalio makes numba's OpenMP threads sleep while they wait (``OMP_WAIT_POLICY``
PASSIVE) unless the user chose how they wait. Checked in fresh interpreters through what GNU
OpenMP itself reports at its start (``OMP_DISPLAY_ENV=VERBOSE``): its spin count is 0 when
passive, 300 000 by default."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

_SCRIPT = """
import adalio  # first, as a user's script would
import numba
import numpy as np

@numba.njit(parallel=True)
def total(a):
    s = 0.0
    for i in numba.prange(a.size):
        s += a[i]
    return s

assert total(np.ones(1000)) == 1000.0
print("layer", numba.threading_layer())
"""


def _started(env_extra: dict[str, str]) -> tuple[str, str | None]:
    """(numba's threading layer, GNU OpenMP's spin count as it started) in a fresh interpreter."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env.update(OMP_DISPLAY_ENV="VERBOSE", NUMBA_NUM_THREADS="2", **env_extra)
    out = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True,
                         env=env, timeout=300, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    layer = out.stdout.split()[-1]
    spin = re.search(r"GOMP_SPINCOUNT = '(\d+)'", out.stderr + out.stdout)
    return layer, spin.group(1) if spin else None


def test_openmp_threads_sleep_while_they_wait_unless_told_otherwise() -> None:
    layer, spin = _started({})
    if layer != "omp":
        pytest.skip(f"numba runs on its {layer} threading layer here, not GNU OpenMP")
    assert spin == "0", spin  # passive: no spinning at all
    # the user's choice stands: a spin count of their own, or a wait policy
    assert _started({"GOMP_SPINCOUNT": "300000"})[1] == "300000"
    assert _started({"OMP_WAIT_POLICY": "ACTIVE"})[1] not in (None, "0")
