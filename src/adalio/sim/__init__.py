"""adalio.sim: realistic handheld LiDAR + IMU sequences of (degenerate) indoor scenes.

``simulate(scene, out_dir, ...)`` writes a ROS1/ROS2 bag in the HILTI 2022 layout plus ground
truth, metadata and a ready-to-run config; ``cached_sequence(...)`` does it once per key under
``$ADALIO_CACHE_DIR/sim``. The simulator never imports the estimator (``adalio.lio``).
"""

from __future__ import annotations

import signal
import threading
from typing import Any

_LAZY = {"SCENES", "SimResult", "cached_sequence", "simulate"}


def _import_generate() -> Any:
    """Import ``adalio.sim.generate`` (trimesh, embree) holding Ctrl-C until it is done.

    trimesh wraps its optional imports in ``except BaseException``, which swallows a
    KeyboardInterrupt raised while it is being imported; the signal is delivered afterwards.
    """
    if threading.current_thread() is not threading.main_thread():
        from adalio.sim import generate

        return generate
    received: list[int] = []
    old = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        from adalio.sim import generate
    finally:
        signal.signal(signal.SIGINT, old)
    if received:
        if callable(old):
            old(signal.SIGINT, None)
        elif old != signal.SIG_IGN:
            raise KeyboardInterrupt
    return generate


def __getattr__(name: str) -> Any:
    """The simulator is imported on first use, so that the command line registers ``simulate``
    without loading trimesh."""
    if name in _LAZY:
        module = _import_generate()
        if name == "cached_sequence":
            from adalio.sim import cache as module
        return getattr(module, name)
    raise AttributeError(f"module 'adalio.sim' has no attribute {name!r}")


__all__ = ["SCENES", "SimResult", "cached_sequence", "simulate"]
