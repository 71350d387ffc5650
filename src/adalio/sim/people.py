"""People walking through a simulated scene: the moving objects a survey meets.

Each person is an upright cylinder (``PERSON_RADIUS_M`` wide, ``PERSON_HEIGHT_M`` tall, standing
on the floor) that walks along the scene's route (the rig's waypoints, at floor level), offset
to one side of it, at a walking speed of their own, and turns back at the route's ends. Where
and how each walks is drawn from the sequence's seed (its own stream: the scene, the motion and
the noise do not move). Positions are analytic in time, so every LiDAR column sees each person
where they are at that column's firing time. Frames: scene world, z up, metres, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from adalio.errors import InputError
from adalio.sim.scenes import RIG_HEIGHT_M

PERSON_RADIUS_M = 0.2
"""A walking adult's torso and arms, as one cylinder."""
PERSON_HEIGHT_M = 1.75
MAX_PEOPLE = 20
SPEED_RANGE_M_S = (0.8, 1.5)
"""Walking speeds drawn per person (uniform): a stroll to a brisk walk."""
MAX_OFFSET_M = 0.35
"""Largest sideways offset from the route: people stay inside a 1.6 m corridor and the
spiral's treads (the route runs midway between the column and the shaft's wall)."""


def check_people(n: int) -> None:
    """``simulate``'s number of people must be 0-``MAX_PEOPLE``."""
    if not 0 <= int(n) <= MAX_PEOPLE or int(n) != n:
        raise InputError(f"--people must be an integer 0-{MAX_PEOPLE} (got {n})")


@dataclass(frozen=True)
class People:
    """People walking along a polyline route (floor level, scene world)."""

    route_m: np.ndarray
    """(K, 3) the route at floor level."""
    start_m: np.ndarray
    """(N,) where along the route each person is at time 0 (arc length, m)."""
    velocity_m_s: np.ndarray
    """(N,) signed speed along the route (negative: towards its start)."""
    offset_m: np.ndarray
    """(N,) sideways offset from the route (left of its direction, m)."""
    radius_m: float = PERSON_RADIUS_M
    height_m: float = PERSON_HEIGHT_M

    @classmethod
    def along_route(cls, waypoints_m: np.ndarray, n: int, seed: int) -> People:
        """``n`` people on the route of rig waypoints ``waypoints_m`` (at rig height)."""
        check_people(n)
        route = np.asarray(waypoints_m, dtype=np.float64).copy()
        route[:, 2] -= RIG_HEIGHT_M
        length = float(np.linalg.norm(np.diff(route, axis=0), axis=1).sum())
        rng = np.random.default_rng([seed, 400])
        start = rng.uniform(0.0, length, n)
        speed = rng.uniform(*SPEED_RANGE_M_S, n) * rng.choice([-1.0, 1.0], n)
        offset = rng.uniform(-MAX_OFFSET_M, MAX_OFFSET_M, n)
        return cls(route, start, speed, offset)

    @property
    def count(self) -> int:
        return len(self.start_m)

    def as_dict(self) -> dict:
        """What ``meta.json`` records of them."""
        return {"count": self.count, "radius_m": self.radius_m, "height_m": self.height_m,
                "start_along_route_m": self.start_m.tolist(),
                "velocity_along_route_m_s": self.velocity_m_s.tolist(),
                "offset_m": self.offset_m.tolist()}

    def positions(self, t_s: np.ndarray) -> np.ndarray:
        """(T, N, 3) each person's foot point (the cylinder's bottom centre) at times ``t_s``."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        seg = np.diff(self.route_m, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg_len)])
        length = cum[-1]
        s = self.start_m[None] + self.velocity_m_s[None] * t[:, None]
        s = np.mod(s, 2.0 * length)
        s = np.where(s > length, 2.0 * length - s, s)  # back and forth between the ends
        i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
        frac = (s - cum[i]) / np.maximum(seg_len[i], 1e-12)
        p = self.route_m[i] + frac[..., None] * seg[i]
        d_xy = seg[i][..., :2]
        left = np.stack([-d_xy[..., 1], d_xy[..., 0]], axis=-1)
        left /= np.maximum(np.linalg.norm(left, axis=-1, keepdims=True), 1e-12)
        p[..., :2] += self.offset_m[None, :, None] * left
        return p

    def cast(self, origins: np.ndarray, directions: np.ndarray,
             feet_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance along unit ``directions`` from ``origins`` (R, 3) to the first person hit
        (inf if none) and the cosine of the incidence there, with each ray's people standing at
        ``feet_m`` (R, N, 3). A ray that starts inside a person sees through them."""
        best = np.full(len(origins), np.inf)
        cos_inc = np.zeros(len(origins))
        r2 = self.radius_m ** 2
        d = directions
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        for j in range(feet_m.shape[1]):
            c = feet_m[:, j]
            o = origins - c  # the ray's origin relative to the foot point
            inside_xy = o[:, 0] ** 2 + o[:, 1] ** 2 < r2
            b = 2.0 * (d[:, 0] * o[:, 0] + d[:, 1] * o[:, 1])
            cc = o[:, 0] ** 2 + o[:, 1] ** 2 - r2
            disc = b * b - 4.0 * a * cc
            with np.errstate(invalid="ignore", divide="ignore"):
                t_side = (-b - np.sqrt(disc)) / (2.0 * a)
            z_side = o[:, 2] + t_side * d[:, 2]
            side = ((disc > 0) & ~inside_xy & (t_side > 0) & (z_side >= 0.0)
                    & (z_side <= self.height_m))
            with np.errstate(invalid="ignore", divide="ignore"):
                t_top = (self.height_m - o[:, 2]) / d[:, 2]
                hit_top = o[:, :2] + t_top[:, None] * d[:, :2]
            top = ((o[:, 2] > self.height_m) & (t_top > 0)
                   & ((hit_top ** 2).sum(-1) <= r2))
            t_side = np.where(side, t_side, np.inf)
            t_top = np.where(top, t_top, np.inf)
            t = np.minimum(t_side, t_top)
            nearer = t < best
            if not nearer.any():
                continue
            n_side = (o[:, :2] + np.where(side, t_side, 0.0)[:, None] * d[:, :2]) / self.radius_m
            cos_side = np.abs((n_side * d[:, :2]).sum(-1))
            cos_here = np.where(t_side <= t_top, cos_side, np.abs(d[:, 2]))
            best = np.where(nearer, t, best)
            cos_inc = np.where(nearer, cos_here, cos_inc)
        return best, cos_inc
