"""How a LiDAR's view lies against gravity: does it see the horizontal ahead or behind?

A beam at elevation ``e`` in the LiDAR frame (about its spin plane), on a LiDAR whose spin axis
leans ``τ`` from the vertical, points ``e − τ`` above the horizontal on the side the axis leans
towards and ``e + τ`` on the other. So some beam reaches the horizontal on the side the LiDAR
leans towards while ``τ ≤ e_max``, on the other side while ``τ ≤ −e_min``, and on one of them at
least while ``τ ≤ max(e_max, −e_min)``: half the vertical field of view of a symmetric head, the
upper edge of a Livox Mid-360's (−7..+52°).

Along a corridor, what fixes the motion along the axis lies near the horizontal ahead and
behind (the end walls, the door jambs at grazing angles); one end is enough. A LiDAR pitched
beyond that sees the floor, the ceiling and bands of the walls, and nothing fixes the axis: the
XT-32 tilted 30° on the handle loses the simulated corridor, as every peer does, where 15°
keeps it; a simulated Mid-360 tilted 30°, which still sees the horizontal ahead, keeps it
(session 82); in a stairwell the same tilt gives the flights their height (README, Benchmarks,
*A tilted LiDAR*; session 81). The run's summary says so when the LiDAR leans beyond its view
(``adalio run``), from the first scan's points and the filter's gravity at the initialization.
Session 81 asked for the horizontal at every azimuth (``τ ≤ min(e_max, −e_min)``): the same for
a symmetric head, but a Mid-360 tilted 8° was told to keep within 7°.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LidarView:
    """The spin axis's lean from the vertical and the beams' elevations (degrees)."""

    tilt_deg: float
    """Angle between the spin axis (the LiDAR's z, either way) and the vertical, 0-90."""
    up_deg: float
    """The beams' highest elevation in the LiDAR frame."""
    down_deg: float
    """The beams' lowest elevation in the LiDAR frame (negative below the spin plane)."""

    @property
    def horizon_deg(self) -> float:
        """The largest lean at which some beam still reaches the horizontal on one side of the
        lean at least (towards it or away from it)."""
        return max(self.up_deg, -self.down_deg)

    @property
    def sees_horizon(self) -> bool:
        """Some beam reaches the horizontal on one side of the lean at least."""
        return self.tilt_deg <= self.horizon_deg

    def describe(self) -> str:
        """The summary's words (``adalio run``)."""
        view = (f"its spin axis leans {self.tilt_deg:.1f} deg from the vertical, its beams "
                f"reach {self.up_deg:+.1f} / {self.down_deg:+.1f} deg")
        if self.sees_horizon:
            return view + ": they see the horizontal ahead of the lean or behind it"
        return (view + ": no beam sees the horizontal ahead of the lean or behind it, where "
                "along a corridor the walls' far ends fix the motion; keep the tilt within "
                f"{self.horizon_deg:.0f} deg there (README, Benchmarks, A tilted LiDAR)")


def lidar_view(points_lidar: np.ndarray, R_world_lidar: np.ndarray,
               g_world: np.ndarray) -> LidarView | None:
    """The view of a scan's points (LiDAR frame, any order) on a LiDAR at ``R_world_lidar``
    under gravity ``g_world``. None without points or gravity."""
    pts = np.asarray(points_lidar, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(g_world, dtype=np.float64)
    horiz = np.hypot(pts[:, 0], pts[:, 1])
    keep = (horiz > 0) | (pts[:, 2] != 0)
    if not keep.any() or not np.linalg.norm(g) > 0:
        return None
    elev = np.degrees(np.arctan2(pts[keep, 2], horiz[keep]))
    up_lidar = np.asarray(R_world_lidar, dtype=np.float64).T @ (-g / np.linalg.norm(g))
    tilt = float(np.degrees(np.arccos(min(abs(float(up_lidar[2])), 1.0))))
    return LidarView(tilt, float(elev.max()), float(elev.min()))
