"""The one numba decorator of adalio's kernels, so that every kernel is compiled the same way.

``kernel()`` is ``numba.njit(cache=True)``: compiled once per machine and then loaded from
numba's on-disk cache. It also drops the C-callback (cfunc) wrapper that numba builds and
optimizes for every compiled function unless told not to: adalio never passes a kernel as a
first-class function, and that wrapper was about a sixth of the compilation a fresh install
pays on its first run (issue #15, ``benchmarks/bench_resources.py``). The CPython wrapper stays:
without it a call from Python crashes the interpreter instead of raising.

Each kernel's save into the cache holds an exclusive lock on a file in its cache folder
(:func:`_locked_save`). numba saves an entry by reading the kernel's index, choosing a data file
name, and writing both back; two processes saving two signatures of one kernel at once (the
workers of ``adalio batch`` on a cold cache, or :mod:`adalio.lio.warmup`'s helper and the run)
could otherwise each pick the same data file name and leave the index pointing at the other's
code. The lock makes that read-modify-write one step (``tests/test_jit.py``).

The cache is keyed on all of adalio's kernel sources, not on the kernel's own file only. numba
stamps each cached kernel with a hash of the file that defines it, so a kernel that calls (or
inlines) a kernel of another file was loaded unchanged after that other file changed: a changed
``plane.within_support``, inlined into ``associate.py``'s search, left 24 benchmark runs identical
to the digit. Here every kernel's stamp is :func:`kernel_sources_stamp`, a hash of every adalio
file that defines kernels (they import this module), so any change to one of them recompiles
them all on the next run.

Two habits keep a fresh install's compilation short (session 72, ``bench_resources.py``):

- A kernel called from another kernel with a constant (``f(0)``, ``f(x, False)``, or a
  counter ``m = 0`` before numba's type inference has widened it in a loop) is compiled for the
  constant's literal type, ``Literal[int](0)``, as well as for the plain type another call
  passes: the same kernel twice. So kernels pass ``np.int64(0)`` / ``np.bool_(False)`` to each
  other, and ``tests/lio/test_warmup.py`` checks that a cold run compiles no kernel for a
  literal argument.
- ``inline="always"`` (numba's IR inlining) types and compiles the callee's body again at every
  call site; a plain call compiles it once and LLVM still inlines it. Only the search row
  (``associate._associate_row``) and its helper keep it: there a plain call compiled no faster
  (the parallel search with its callees 5.6 s either way).
- (Session 92.) An array slice assigned from an array (``a[0:3] = b``) makes numba compile the
  message it would raise on a shape mismatch, string formatting and all: 4.4 of the IMU
  propagation's 11.4 s of compilation when it had three. Kernels on a run's path fill such
  blocks element by element (a scalar fill, ``a[:] = 0.0``, compiles no message), and
  ``tests/lio/test_warmup.py`` checks that neither a cold run nor the helper compiles it.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
from pathlib import Path

from numba import njit

_PACKAGE = Path(__file__).resolve().parent


def sources_stamp(root: Path) -> str:
    """SHA-256 over the ``*.py`` files under ``root`` that import ``adalio.jit`` (the files that
    define kernels), with their relative paths, in sorted order."""
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        text = path.read_bytes()
        if b"adalio.jit" in text:
            h.update(path.relative_to(root).as_posix().encode())
            h.update(b"\0")
            h.update(text)
            h.update(b"\0")
    return h.hexdigest()


@functools.cache
def kernel_sources_stamp() -> str:
    """:func:`sources_stamp` of the installed adalio package (computed once per process)."""
    return sources_stamp(_PACKAGE)


LOCK_NAME = ".adalio-cache.lock"


@contextlib.contextmanager
def _cache_lock(folder: str):
    """Exclusive inter-process lock on ``folder``/:data:`LOCK_NAME` (POSIX ``flock``; where
    there is no ``fcntl``, or the lock file cannot be made or locked, no lock)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover  (Windows)
        yield
        return
    fd = None
    try:
        fd = os.open(os.path.join(folder, LOCK_NAME), os.O_RDWR | os.O_CREAT, 0o666)
        fcntl.flock(fd, fcntl.LOCK_EX)
    except OSError:  # a folder numba can write but not lock in: save as numba would
        if fd is not None:
            os.close(fd)
        fd = None
    try:
        yield
    finally:
        if fd is not None:
            os.close(fd)  # releases the lock


def _locked_save(cache_file):
    """``cache_file.save`` (numba's index-and-data cache file of one kernel) under
    :func:`_cache_lock` of its folder."""
    save = cache_file.save

    def locked(key, data):
        with _cache_lock(cache_file._cache_path):
            save(key, data)

    return locked


def kernel(*, parallel: bool = False, inline: str = "never"):
    """Decorator: ``@kernel()``, ``@kernel(parallel=True)``, ``@kernel(inline="always")``."""
    jit = njit(cache=True, no_cfunc_wrapper=True, parallel=parallel, inline=inline)

    def decorate(fn):
        dispatcher = jit(fn)
        # numba's index file of this kernel compares its stamp with this one on load
        cache_file = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
        if cache_file is not None and hasattr(cache_file, "_source_stamp"):
            cache_file._source_stamp = kernel_sources_stamp()
            if hasattr(cache_file, "_cache_path") and hasattr(cache_file, "save"):
                cache_file.save = _locked_save(cache_file)
        return dispatcher

    return decorate
