"""adalio: adaptive LiDAR-inertial odometry (AdaLIO on a Faster-LIO core), ROS-free.

Public API (see README "Python API"):

* :func:`load_config`, :class:`Config` and its sections: configuration and presets.
* :class:`Odometry`: the streaming estimator (``add_imu`` / ``add_scan`` / ``map_points``).
* Bag reading and the IMU/LiDAR sequencer from :mod:`adalio.io`.
"""

import os as _os

# numba's OpenMP threads (its default threading layer) sleep while they wait for work instead of
# spinning for it, unless you set OMP_WAIT_POLICY or GOMP_SPINCOUNT yourself. GNU OpenMP's default
# spins up to 300 000 rounds at each wait: on a machine whose cores are busy with other work
# (another run, a test worker, a viewer) the parallel kernels then wait for a thread that spins
# on the other core. Measured in session 88 on the 2-core dev machine, a 43 s hall at 512
# columns: a median 10.8-12.1 ms per scan against 21.9-22.0 ms with one core busy, and the same
# 10-11 ms when the machine is idle (README, "Conventions", Threads). It must be set before
# OpenMP starts (numba starts it at the first parallel kernel), hence here.
if "OMP_WAIT_POLICY" not in _os.environ and "GOMP_SPINCOUNT" not in _os.environ:
    _os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

from adalio.config import Config, config_from_dict, load_config
from adalio.errors import AdalioError, BagError, ConfigError, InputError
from adalio.types import Estimate, ImuBatch, Scan, ScanStats

__version__ = "0.1.0"

_LAZY = {
    "Odometry": "adalio.lio",
    "Bag": "adalio.io", "BagWriter": "adalio.io", "Sequencer": "adalio.io",
    "CloudDecoder": "adalio.io", "decode_pointcloud2": "adalio.io",
    "LivoxDecoder": "adalio.io", "LivoxCloud": "adalio.io",
    "run_bag": "adalio.pipeline", "RunResult": "adalio.pipeline",
    "simulate": "adalio.sim", "cached_sequence": "adalio.sim",
}


def __getattr__(name: str):
    """Heavy parts (numba kernels, rosbags) are imported on first use."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'adalio' has no attribute {name!r}")

__all__ = [
    "AdalioError",
    "Bag",
    "BagError",
    "BagWriter",
    "CloudDecoder",
    "Config",
    "ConfigError",
    "Estimate",
    "ImuBatch",
    "InputError",
    "LivoxCloud",
    "LivoxDecoder",
    "Odometry",
    "RunResult",
    "Scan",
    "ScanStats",
    "Sequencer",
    "__version__",
    "cached_sequence",
    "config_from_dict",
    "decode_pointcloud2",
    "load_config",
    "run_bag",
    "simulate",
]
