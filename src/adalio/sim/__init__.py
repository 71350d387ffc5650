"""adalio.sim: realistic handheld LiDAR + IMU sequences of (degenerate) indoor scenes.

``simulate(scene, out_dir, ...)`` writes a ROS1/ROS2 bag in the HILTI 2022 layout plus ground
truth, metadata and a ready-to-run config; ``cached_sequence(...)`` does it once per key under
``$ADALIO_CACHE_DIR/sim``. The simulator never imports the estimator (``adalio.lio``).
"""

from adalio.sim.generate import SCENES, SimResult, cached_sequence, simulate

__all__ = ["SCENES", "SimResult", "cached_sequence", "simulate"]
