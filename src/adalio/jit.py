"""The one numba decorator of adalio's kernels, so that every kernel is compiled the same way.

``kernel()`` is ``numba.njit(cache=True)``: compiled once per machine and then loaded from
numba's on-disk cache. It also drops the C-callback (cfunc) wrapper that numba builds and
optimizes for every compiled function unless told not to: adalio never passes a kernel as a
first-class function, and that wrapper was about a sixth of the compilation a fresh install
pays on its first run (issue #15, ``benchmarks/bench_resources.py``). The CPython wrapper stays:
without it a call from Python crashes the interpreter instead of raising.
"""

from __future__ import annotations

from numba import njit


def kernel(*, parallel: bool = False, inline: str = "never"):
    """Decorator: ``@kernel()``, ``@kernel(parallel=True)``, ``@kernel(inline="always")``."""
    return njit(cache=True, no_cfunc_wrapper=True, parallel=parallel, inline=inline)
