"""numba's threads change nothing but the time: a run on one thread (the serial search) and on
two (the parallel one) gives the same trajectory, byte for byte. And importing adalio makes
numba's OpenMP threads sleep while they wait (``OMP_WAIT_POLICY`` PASSIVE) unless the user chose
how they wait, checked in fresh interpreters through what GNU OpenMP itself reports at its start
(``OMP_DISPLAY_ENV=VERBOSE``): its spin count is 0 when passive, 300 000 by default."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from adalio.sim import cached_sequence

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


def _rows(scans_csv) -> list[list[str]]:
    """scans.csv without its wall-time column."""
    lines = [ln.split(",") for ln in scans_csv.read_text().splitlines()]
    keep = [i for i, name in enumerate(lines[0]) if name != "wall_ms"]
    return [[row[i] for i in keep] for row in lines]


def test_one_thread_and_two_give_the_same_run(tmp_path) -> None:
    sim = cached_sequence("corridor", seed=0, duration_s=4.0, columns=512)
    outs = []
    for n in (1, 2):
        env = {**os.environ, "NUMBA_NUM_THREADS": str(n)}
        out = subprocess.run([sys.executable, "-m", "adalio.cli", "run", str(sim.bag_path),
                              "--config", str(sim.config_path), "--out", str(tmp_path / str(n)),
                              "--no-progress"], capture_output=True, text=True, env=env,
                             timeout=600, check=False)
        assert out.returncode == 0, out.stderr[-2000:]
        outs.append(tmp_path / str(n))
    one, two = ((o / "trajectory.tum").read_bytes() for o in outs)
    assert len(one.splitlines()) > 20 and one == two
    assert _rows(outs[0] / "scans.csv") == _rows(outs[1] / "scans.csv")
