"""adalio.jit: every kernel's cache is keyed on all kernel sources, so none is ever stale."""

from __future__ import annotations

import importlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from numba.core.registry import CPUDispatcher

import adalio
from adalio.jit import kernel_sources_stamp, sources_stamp

KERNEL_MODULES = [
    "adalio.io.pointcloud2", "adalio.lio.associate", "adalio.lio.imu", "adalio.lio.ivox",
    "adalio.lio.local_surface", "adalio.lio.map_uncertainty", "adalio.lio.measurement", "adalio.lio.motion_init",
    "adalio.lio.moving", "adalio.lio.stray", "adalio.lio.dense_map",
    "adalio.lio.odometry", "adalio.lio.plane", "adalio.lio.so3", "adalio.lio.voxel",
]


def test_every_kernel_carries_the_stamp_of_all_kernel_sources() -> None:
    root = Path(adalio.__file__).parent
    defining = sorted(p.relative_to(root).with_suffix("").as_posix().replace("/", ".")
                      for p in root.rglob("*.py")
                      if b"adalio.jit" in p.read_bytes() and p.name != "jit.py")
    assert ["adalio." + m for m in defining] == sorted(KERNEL_MODULES)
    n = 0
    for name in KERNEL_MODULES:
        module = importlib.import_module(name)
        for obj in vars(module).values():
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == name:
                assert obj._cache._cache_file._source_stamp == kernel_sources_stamp(), obj
                n += 1
    assert n > 50


def test_the_stamp_follows_the_files_that_define_kernels(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    a = tmp_path / "sub" / "a.py"
    b = tmp_path / "b.py"
    a.write_text("from adalio.jit import kernel\n")
    b.write_text("x = 1\n")
    s0 = sources_stamp(tmp_path)
    b.write_text("x = 2\n")
    assert sources_stamp(tmp_path) == s0
    a.write_text("from adalio.jit import kernel\n# changed\n")
    s1 = sources_stamp(tmp_path)
    assert s1 != s0
    a.rename(tmp_path / "a.py")  # same text, another path
    assert sources_stamp(tmp_path) not in (s0, s1)


_CALL = """
import sys, numpy as np
import adalio
assert adalio.__file__.startswith(sys.argv[1]), adalio.__file__
from adalio.lio.measurement import points_to_world
print(points_to_world(np.array([[1.0, 2.0, 3.0]]), np.eye(3), np.zeros(3), np.eye(3),
                      np.zeros(3))[0].tolist())
"""


def test_a_kernel_is_recompiled_when_a_kernel_it_calls_in_another_file_changes(
        tmp_path: Path) -> None:
    """points_to_world (measurement.py) calls so3.mul (so3.py). After so3.py changes, the next
    process must run the changed product, not the cached kernel (numba alone reloads it)."""
    pkg = tmp_path / "pkg"
    shutil.copytree(Path(adalio.__file__).parent, pkg / "adalio",
                    ignore=shutil.ignore_patterns("__pycache__"))
    env = {**os.environ, "PYTHONPATH": str(pkg), "NUMBA_CACHE_DIR": str(tmp_path / "cache")}

    def run() -> list[float]:
        out = subprocess.run([sys.executable, "-c", _CALL, str(pkg)], capture_output=True,
                             text=True, env=env, timeout=300, check=False)
        assert out.returncode == 0, out.stderr
        return [float(v) for v in out.stdout.strip().strip("[]").split(",")]

    np.testing.assert_allclose(run(), [1.0, 2.0, 3.0])
    so3 = pkg / "adalio" / "lio" / "so3.py"
    text = so3.read_text()
    assert text.count("out[i, c] += a * B[j, c]") == 1
    so3.write_text(text.replace("out[i, c] += a * B[j, c]", "out[i, c] += 2.0 * a * B[j, c]"))
    np.testing.assert_allclose(run(), [2.0, 4.0, 6.0])


_SAVER = """
import sys, time
from numba.core import caching

index_delay_s, data_delay_s, start_at, value = (float(a) for a in sys.argv[2:6])
save_index, save_data = caching.IndexDataCacheFile._save_index, caching.IndexDataCacheFile._save_data


def slow_index(self, overloads):  # numba read the index just before: widen the race window
    time.sleep(index_delay_s)
    save_index(self, overloads)


def slow_data(self, name, data):
    time.sleep(data_delay_s)
    save_data(self, name, data)


caching.IndexDataCacheFile._save_index = slow_index
caching.IndexDataCacheFile._save_data = slow_data
sys.path.insert(0, sys.argv[1])
import twice

while time.time() < start_at:
    time.sleep(0.001)
twice.f(int(value) if value.is_integer() else value)  # compiles, and saves into the cache
"""

_LOADER = """
import sys
sys.path.insert(0, sys.argv[1])
import twice
print(repr(twice.f(3)), repr(twice.f(1.25)), sum(twice.f.stats.cache_hits.values()))
"""


def test_two_processes_saving_signatures_of_one_kernel_leave_a_consistent_cache(
        tmp_path: Path) -> None:
    """Process A saves f(int64) and B f(float64) into one cold cache at the same time, with the
    race numba's cache alone has widened by delays: A picks the data file name, writes the index,
    and writes its data 1 s later; B reads the index before A wrote it, so (unlocked) it picks
    the same name, and writes its index after A's and its data before A's: the index then says
    f(float64) is in a file that holds f(int64). adalio.jit's lock serializes the two saves."""
    import time

    mod = tmp_path / "mod"
    mod.mkdir()
    (mod / "twice.py").write_text(
        "from adalio.jit import kernel\n\n\n@kernel()\ndef f(x):\n    return 2 * x + 1\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    t0 = time.time() + 8.0  # both processes have imported numba and adalio by then

    def saver(index_delay: float, data_delay: float, start: float, value: float):
        return subprocess.Popen([sys.executable, "-c", _SAVER, str(mod), str(index_delay),
                                 str(data_delay), str(start), repr(value)], env=env,
                                stderr=subprocess.PIPE, text=True)

    a = saver(1.0, 1.0, t0, 3.0)
    b = saver(1.0, 0.0, t0 + 0.3, 1.25)
    for p in (a, b):
        assert p.wait(timeout=120) == 0, p.stderr.read()
    out = subprocess.run([sys.executable, "-c", _LOADER, str(mod)], capture_output=True,
                         text=True, env=env, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    f3, f125, hits = out.stdout.split()
    assert (f3, f125) == ("7", "3.5")
    assert int(hits) == 2  # both loaded from the cache, none compiled again


def test_the_cache_lock_gives_way_where_no_lock_file_can_be_made(tmp_path: Path) -> None:
    """A cache folder where the lock file cannot be created (here: the folder does not exist)
    saves unlocked, as numba alone would, instead of failing the compilation."""
    from adalio.jit import _cache_lock

    entered = []
    with _cache_lock(str(tmp_path / "missing")):
        entered.append(True)
    with _cache_lock(str(tmp_path)):
        entered.append(True)
    assert entered == [True, True]
    assert (tmp_path / ".adalio-cache.lock").exists()
