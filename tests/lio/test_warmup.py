"""adalio.lio.warmup: the helper compiles what a run needs, with the run's argument types, and a
run never leaves it behind."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from adalio.config import load_config
from adalio.lio import warmup
from adalio.pipeline import run_bag
from adalio.sim import cached_sequence

_RECORD = """
import json, sys
from numba.core import event

compiled = []
shape_error = []  # numba's message for an array slice assignment of the wrong shape


class Record(event.Listener):
    def on_start(self, ev):
        d = ev.data["dispatcher"]
        if d.py_func.__module__.startswith("adalio."):
            compiled.append([d.py_func.__module__ + "." + d.py_func.__qualname__,
                             str(ev.data["args"])])
        elif "raise_with_shape_context" in d.py_func.__qualname__:
            shape_error.append(compiled[-1][0] if compiled else "")

    def on_end(self, ev):
        pass


event.register("numba:compile", Record())
"""

_HELPER = _RECORD + """
from adalio.lio import warmup
cold = warmup.cache_is_cold()
warmup.compile_update_stage()
print(json.dumps({"cold_before": cold, "cold_after": warmup.cache_is_cold(),
                  "compiled": compiled, "shape_error": shape_error}))
"""

_RUN = _RECORD + """
from adalio.config import load_config
from adalio.lio import associate, measurement, map_uncertainty, motion_init
from adalio.pipeline import run_bag
res = run_bag(sys.argv[1], load_config(config_file=sys.argv[2]), sys.argv[3],
              progress=False, parallel_compile=False)
used = {d.__module__ + "." + d.__qualname__: sum(d.stats.cache_hits.values())
        for d in (associate._associate_parallel, measurement.point_to_plane,
                  measurement.residual_weights, map_uncertainty._map_covariance,
                  motion_init.preintegrate)}
print(json.dumps({"compiled": compiled, "loaded": used, "poses": res.n_scans,
                  "shape_error": shape_error}))
"""


def _hall():
    return cached_sequence("hall", seed=1, duration_s=6.0, columns=500)


def _json(script: str, env: dict, *args: str) -> dict:
    out = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True,
                         env=env, timeout=600, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_a_run_after_the_helper_compiles_none_of_the_helper_s_kernels_again(
        tmp_path: Path) -> None:
    """On an empty numba cache the helper compiles the update's kernels; a run then loads every
    one of them from the cache (compiling them again would mean the helper compiled them for
    other argument types than the run passes, and helped nothing)."""
    sim = _hall()
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    helper = _json(_HELPER, env)
    assert helper["cold_before"] and not helper["cold_after"]
    by_helper = {name for name, _ in helper["compiled"]}
    for name in ("adalio.lio.associate._associate_parallel",
                 "adalio.lio.measurement.point_to_plane",
                 "adalio.lio.measurement.residual_weights",
                 "adalio.lio.map_uncertainty._map_covariance",
                 "adalio.lio.motion_init.preintegrate", "adalio.lio.so3.log",
                 "adalio.lio.ivox._gather_points", "adalio.lio.plane._fit_planes_serial",
                 "adalio.lio.dense_map._add_points", "adalio.lio.map_uncertainty._insert"):
        assert name in by_helper
    run = _json(_RUN, env, str(sim.bag_path), str(sim.config_path), str(tmp_path / "run"))
    assert run["poses"] > 10
    again = sorted({name for name, _ in run["compiled"]} & by_helper)
    assert again == [], [c for c in run["compiled"] if c[0] in again]
    assert all(hits >= 1 for hits in run["loaded"].values()), run["loaded"]
    assert len(run["compiled"]) > 10  # the run compiled its own stages (a cold cache indeed)
    # a constant passed from kernel to kernel compiles the callee once more, for the constant's
    # literal type (adalio.jit): a fresh install would pay for it
    literal = [c for c in helper["compiled"] + run["compiled"] if "Literal[" in c[1]]
    assert literal == [], literal
    # an array slice assignment (`a[0:3] = b`) compiles numba's shape-error message, string
    # formatting and all: 4.4 of the IMU propagation's 11.4 s of compilation, which had three
    assert helper["shape_error"] + run["shape_error"] == []


def test_the_helper_is_not_wanted_when_switched_off_or_when_the_cache_is_warm(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(warmup, "cache_is_cold", lambda: True)
    monkeypatch.setattr(warmup, "usable_cpus", lambda: 2)
    monkeypatch.setenv(warmup.ENV_SWITCH, "0")
    assert not warmup.wanted() and not warmup.start().started
    monkeypatch.setenv(warmup.ENV_SWITCH, "1")
    assert warmup.wanted()
    monkeypatch.setattr(warmup, "usable_cpus", lambda: 1)
    assert not warmup.wanted()
    monkeypatch.setattr(warmup, "usable_cpus", lambda: 2)
    assert warmup.wanted()  # two CPUs again: only the warm cache below stops it
    monkeypatch.setattr(warmup, "cache_is_cold", lambda: False)
    assert not warmup.wanted()


@pytest.mark.parametrize("max_scans", [1, 12])
def test_run_bag_stops_the_helper_when_it_ends(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                               max_scans: int) -> None:
    """Whether the run ends with poses (12 scans) or with an error (1 scan: no pose yet), the
    helper process is gone when run_bag returns or raises."""
    sim = _hall()
    started: list[subprocess.Popen] = []

    def start() -> warmup.Warmup:
        proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
        started.append(proc)
        return warmup.Warmup(proc)

    monkeypatch.setattr(warmup, "start", start)
    monkeypatch.setattr(warmup, "cache_is_cold", lambda: True)  # as on a fresh install
    cfg = load_config(config_file=sim.config_path)
    try:
        run_bag(sim.bag_path, cfg, tmp_path / "out", progress=False, max_scans=max_scans)
    except Exception as e:  # noqa: BLE001
        assert max_scans == 1, e
    assert len(started) == 1
    assert started[0].poll() is not None
    started.clear()
    run_bag(sim.bag_path, cfg, tmp_path / "out2", progress=False, max_scans=12,
            parallel_compile=False)
    monkeypatch.setattr(warmup, "cache_is_cold", lambda: False)
    run_bag(sim.bag_path, cfg, tmp_path / "out3", progress=False, max_scans=12)
    assert started == []  # switched off, or a warm cache: no helper


def test_the_helper_imports_this_adalio_with_this_thread_count(tmp_path: Path) -> None:
    """A process that imports adalio from a source tree put on ``sys.path`` by hand (not
    installed, not on ``PYTHONPATH``) gives its helper that same tree, and its numba thread
    count; without that, the helper would compile another adalio's kernels."""
    import shutil

    import adalio

    tree = tmp_path / "tree"
    shutil.copytree(Path(adalio.__file__).parent, tree / "adalio",
                    ignore=shutil.ignore_patterns("__pycache__"))
    script = (
        "import sys, subprocess\n"
        f"sys.path.insert(0, {str(tree)!r})\n"
        "import adalio\n"
        "from adalio.lio import warmup\n"
        "child = ('import adalio, numba; print(adalio.__file__); '\n"
        "         'print(numba.config.NUMBA_NUM_THREADS)')\n"
        "out = subprocess.run([sys.executable, '-c', child], env=warmup.helper_env(),\n"
        "                     capture_output=True, text=True, check=True)\n"
        "print(adalio.__file__)\n"
        "print(out.stdout)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env={**env, "NUMBA_NUM_THREADS": "1"}, cwd=tmp_path, timeout=300,
                         check=False)
    assert out.returncode == 0, out.stderr
    parent_file, child_file, threads = out.stdout.split()
    assert Path(parent_file).is_relative_to(tree)
    assert Path(child_file).resolve() == Path(parent_file).resolve()
    assert threads == "1"
