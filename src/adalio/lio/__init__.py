"""adalio.lio: the LiDAR-inertial estimator (Faster-LIO core + AdaLIO switching)."""

from adalio.lio.odometry import Odometry

__all__ = ["Odometry"]
