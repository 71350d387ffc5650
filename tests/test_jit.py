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
    "adalio.lio.map_uncertainty", "adalio.lio.measurement", "adalio.lio.motion_init",
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
