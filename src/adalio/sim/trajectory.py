"""Walking-person trajectory of a handheld LiDAR + IMU rig, with analytic derivatives.

Frames: ``world`` = scene frame (z up); ``rig`` = handle frame (x forward, z up) whose orientation
is ``R_world_rig = Rz(yaw) Ry(pitch) Rx(roll)``; ``imu`` = IMU frame, ``R_world_imu =
R_world_rig R_rig_imu`` with ``R_rig_imu = R_rig_lidar R_imu_lidarᵀ``: the LiDAR upright and forward
(``R_rig_lidar = I``), or tilted on the handle (:func:`tilt_rig_lidar`).
Time ``t_s`` is seconds since the sequence start; the rig is exactly still for ``t_s <=
static_s`` and moves along quintic B-splines of ``tau = t_s - static_s`` afterwards (first and
second derivatives vanish at ``tau = 0``, so the motion is C2 everywhere).

The route (filleted waypoints, arc-length quintic spline) is walked with a speed profile limited
by the scene's per-waypoint speed, by a yaw-rate bound on curvature and by an acceleration bound;
step bobbing (~1.9 Hz), lateral sway, slow hand wander and small pitch/roll are added under an
envelope that is zero while still. Position and yaw/pitch/roll are then interpolated at 100 Hz by
quintic splines, which ARE the ground truth: velocity, acceleration, body rate and angular
acceleration are their analytic derivatives.

With a :class:`HandheldMotion` (``handheld=``), the synthetic bobbing, sway, wander and small
attitude motion are replaced by those of a recorded walk (e.g. the dense HILTI 2022 exp04-06
ground truth): its translation away from its own smoothed path, in that path's forward / left /
up frame, and its attitude away from its smoothed attitude, as roll / pitch / yaw about the same
axes. The route and its speed profile stay the scene's, so the recorded operator's hand and gait
are carried through the scene.

``pace`` walks the route that many times as fast: the scene's speed limits and the yaw-rate bound
times ``pace``, the acceleration bound times ``pace²``, so that where those bounds hold the
route's speed profile is the same, run in ``1 / pace`` of the time. The hand and the gait (bobbing
at about 2 Hz, sway, wander, the start's 2 s ramp and the still tail) keep their times.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import BSpline, make_interp_spline
from scipy.ndimage import gaussian_filter1d, minimum_filter1d
from scipy.spatial.transform import Rotation, RotationSpline

from adalio.errors import InputError

SAMPLE_HZ = 100.0
YAW_RATE_MAX_RAD_S = 0.9
ACCEL_MAX_M_S2 = 0.45
PACE_RANGE = (0.25, 3.0)
"""The walking paces :class:`Trajectory` takes (``simulate --pace``): a quarter of the scenes'
speeds (a slow, careful survey) to three times them (a brisk walk down a stair, a robot)."""


def check_pace(pace: float) -> None:
    """InputError unless ``pace`` lies within :data:`PACE_RANGE`."""
    lo, hi = PACE_RANGE
    if not lo <= pace <= hi:
        raise InputError(f"--pace must be {lo:g}-{hi:g} (got {pace:g})")


@dataclass
class TrajectorySample:
    """Trajectory state at an array of times (all world-frame unless named ``_imu``)."""

    p_world_imu_m: np.ndarray
    v_world_m_s: np.ndarray
    a_world_m_s2: np.ndarray
    R_world_imu: np.ndarray
    omega_imu_rad_s: np.ndarray
    alpha_imu_rad_s2: np.ndarray


def _smootherstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _fillet(points: np.ndarray, fillet_m: float, n_arc: int = 24) -> tuple[np.ndarray,
                                                                            np.ndarray]:
    """Round each interior corner with a quadratic Bezier; returns dense points and their
    fractional waypoint index (for interpolating per-waypoint attributes)."""
    out = [points[:1]]
    idx = [np.array([0.0])]
    for i in range(1, len(points) - 1):
        a, b, c = points[i - 1], points[i], points[i + 1]
        la, lc = np.linalg.norm(b - a), np.linalg.norm(c - b)
        d = min(fillet_m, 0.45 * la, 0.45 * lc)
        p0 = b + (a - b) * d / la
        p2 = b + (c - b) * d / lc
        u = np.linspace(0.0, 1.0, n_arc)[:, None]
        arc = (1 - u) ** 2 * p0 + 2 * (1 - u) * u * b + u**2 * p2
        out.append(arc)
        idx.append(i - 0.5 * (1 - u[:, 0]) * d / la + 0.5 * u[:, 0] * d / lc)
    out.append(points[-1:])
    idx.append(np.array([len(points) - 1.0]))
    return np.vstack(out), np.concatenate(idx)


def _resample(points: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    points = points[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    n = max(int(np.ceil(s[-1] / step_m)), 6)
    s_new = np.linspace(0.0, s[-1], n + 1)
    return np.column_stack([np.interp(s_new, s, points[:, k]) for k in range(3)]), s_new


def _wander(rng: np.random.Generator, tau: np.ndarray, amplitude: float) -> np.ndarray:
    freqs = rng.uniform(0.08, 0.45, 3)
    phases = rng.uniform(0, 2 * np.pi, 3)
    w = sum(np.sin(2 * np.pi * f * tau + p) for f, p in zip(freqs, phases, strict=True))
    return amplitude * w / 1.8


NO_HAND = "none"
"""``--motion-from none``: the walk without any hand motion (:meth:`HandheldMotion.none`)."""


def is_no_hand(source) -> bool:
    """Whether a ``motion_from`` names :data:`NO_HAND` (and no file of that name exists)."""
    return source is not None and str(source) == NO_HAND and not Path(str(source)).is_file()


@dataclass
class HandheldMotion:
    """The handheld part of a recorded walk, at ``SAMPLE_HZ`` (see the module docstring).

    ``offset_path_m``: (N, 3) forward / left / up translation away from the smoothed path;
    ``attitude_rad``: (N, 3) yaw / pitch / roll away from the smoothed attitude (small angles,
    about up / left / forward); ``smooth_s``: the Gaussian sigma (s) that defines "smoothed".
    0.5 s (-3 dB at about 0.37 Hz) keeps the gait (~2 Hz) and the hand's wobble and leaves the
    slower motion (where the operator walks and looks) to the scene's route, the band the
    synthetic model's wander (0.08-0.45 Hz) also covers.
    """

    offset_path_m: np.ndarray
    attitude_rad: np.ndarray
    smooth_s: float
    source: str = ""

    @classmethod
    def from_tum(cls, path, smooth_s: float = 0.5) -> HandheldMotion:
        """Extract the handheld motion of a TUM trajectory (``t x y z qx qy qz qw``, >= 10 Hz,
        lines starting with # ignored; read and checked by
        :func:`adalio.eval.files.read_trajectory`)."""
        from adalio.eval.files import read_trajectory

        path = Path(path)
        traj = read_trajectory(path, "motion")
        stamps = np.asarray(traj.timestamps, dtype=np.float64)
        if stamps.size < 20 or not np.all(np.diff(stamps) > 0):
            raise InputError(f"motion file {path}: needs >= 20 poses with increasing times "
                             f"(has {stamps.size})")
        t = stamps - stamps[0]
        if t[-1] / (len(t) - 1) > 0.15:
            raise InputError(f"motion file {path}: poses every {t[-1] / (len(t) - 1):.2f} s; "
                             "the handheld motion needs >= 10 Hz")
        tau = np.arange(0.0, t[-1], 1.0 / SAMPLE_HZ)
        p = make_interp_spline(t, traj.positions_xyz, k=3)(tau)
        quat_xyzw = np.roll(traj.orientations_quat_wxyz, -1, axis=1)
        R = RotationSpline(t, Rotation.from_quat(quat_xyzw))(tau)
        sig = smooth_s * SAMPLE_HZ
        fwd = _hold_heading(np.gradient(gaussian_filter1d(p, 2.0 * sig, axis=0,
                                                          mode="nearest"), axis=0))
        left = np.cross([0.0, 0.0, 1.0], fwd)
        dp = p - gaussian_filter1d(p, sig, axis=0, mode="nearest")
        offset = np.column_stack([np.sum(dp * fwd, 1), np.sum(dp * left, 1), dp[:, 2]])
        # smoothed attitude: the chordal mean of the rotation matrices under the same window
        U, _, Vt = np.linalg.svd(gaussian_filter1d(R.as_matrix(), sig, axis=0, mode="nearest"))
        U[:, :, 2] *= np.sign(np.linalg.det(U @ Vt))[:, None]
        R_s = Rotation.from_matrix(U @ Vt)
        delta_world = R_s.apply((R_s.inv() * R).as_rotvec())
        att = np.column_stack([delta_world[:, 2], np.sum(delta_world * left, 1),
                               np.sum(delta_world * fwd, 1)])
        return cls(offset, att, float(smooth_s), path.name)

    @classmethod
    def none(cls) -> HandheldMotion:
        """No hand: the rig keeps the route's smoothed path and attitude exactly, as a wheeled
        robot does (constant height and attitude on a straight, no gait, no wobble)."""
        return cls(np.zeros((2, 3)), np.zeros((2, 3)), 0.0, NO_HAND)

    @classmethod
    def load(cls, source) -> HandheldMotion:
        """:meth:`none` for the name ``none`` (:data:`NO_HAND`), else :meth:`from_tum`."""
        return cls.none() if is_no_hand(source) else cls.from_tum(source)

    def window(self, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """``n`` consecutive samples from a seed-dependent start, the recording played back
        and forth (time-reversed at its ends) when the walk is longer, so it stays continuous."""
        m = len(self.offset_path_m)
        start = int(np.random.default_rng([seed, 11]).integers(0, m))
        k = (start + np.arange(n)) % (2 * m - 2)
        idx = np.where(k < m, k, 2 * m - 2 - k)
        return self.offset_path_m[idx], self.attitude_rad[idx]


def _hold_heading(d: np.ndarray) -> np.ndarray:
    """Unit horizontal direction of ``d`` per row; rows with almost no horizontal motion keep
    the last defined heading (the first defined one before it; +x if none)."""
    h = np.column_stack([d[:, 0], d[:, 1], np.zeros(len(d))])
    n = np.linalg.norm(h, axis=1)
    ok = n > 1e-3 * max(float(n.max()), 1e-12)
    out = np.zeros_like(h)
    if not ok.any():
        out[:, 0] = 1.0
        return out
    idx = np.where(ok, np.arange(len(d)), 0)
    idx = np.maximum.accumulate(idx)
    first = int(np.argmax(ok))
    idx[:first] = first
    return h[idx] / n[idx][:, None]


class Trajectory:
    """Analytic rig trajectory; evaluate with :meth:`sample` at arrays of times (seconds)."""

    def __init__(self, waypoints_m: np.ndarray, speed_limit_m_s: np.ndarray,
                 R_rig_imu: np.ndarray, *, seed: int = 0, static_s: float = 2.5,
                 fillet_m: float = 1.0, tail_s: float = 1.5, motion: bool = True,
                 handheld: HandheldMotion | None = None, pace: float = 1.0) -> None:
        check_pace(pace)
        rng = np.random.default_rng([seed, 7])
        accel_max = ACCEL_MAX_M_S2 * pace * pace
        self.static_s = float(static_s)
        self.R_rig_imu = np.asarray(R_rig_imu, dtype=np.float64)
        dense, widx = _fillet(np.asarray(waypoints_m, dtype=np.float64), fillet_m)
        speed_dense = np.interp(widx, np.arange(len(speed_limit_m_s)), speed_limit_m_s) * pace
        route, _ = _resample(dense, 0.1)
        route, s_grid = _resample(gaussian_filter1d(route, 2.5, axis=0, mode="nearest"), 0.1)
        dense_s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0),
                                                                  axis=1))])
        dense_s *= s_grid[-1] / max(dense_s[-1], 1e-12)
        route_spl = make_interp_spline(s_grid, route, k=5)
        d1 = route_spl.derivative(1)(s_grid)
        heading = np.unwrap(np.arctan2(d1[:, 1], d1[:, 0]))
        dpsi_ds = np.abs(np.gradient(gaussian_filter1d(heading, 3.0, mode="nearest"), s_grid))
        v_lim = np.minimum(np.interp(s_grid, dense_s, speed_dense),
                           YAW_RATE_MAX_RAD_S * pace / np.maximum(dpsi_ds, 1e-6))
        v_lim = gaussian_filter1d(minimum_filter1d(v_lim, 15, mode="nearest"), 5.0,
                                  mode="nearest")
        ds = np.diff(s_grid)
        for i in range(1, len(v_lim)):
            v_lim[i] = min(v_lim[i], np.sqrt(v_lim[i - 1] ** 2 + 2 * accel_max * ds[i - 1]))
        v_lim[-1] = 0.0
        for i in range(len(v_lim) - 2, -1, -1):
            v_lim[i] = min(v_lim[i], np.sqrt(v_lim[i + 1] ** 2 + 2 * accel_max * ds[i]))
        length = s_grid[-1]
        dt = 1.0 / SAMPLE_HZ
        s_samples = [0.0]
        v_samples = [0.0]
        tau = 0.0
        if motion:
            while s_samples[-1] < length - 1e-5 and tau < 1e4:
                tau += dt
                s_now = s_samples[-1]
                v = _smootherstep(np.array(tau / 2.0))[()] * np.interp(s_now, s_grid, v_lim)
                if tau > 2.0:
                    v = max(min(v, np.sqrt(2 * accel_max * (length - s_now))), 1e-4)
                s_samples.append(min(s_now + v * dt, length))
                v_samples.append(v)
        n_tail = int(tail_s * SAMPLE_HZ)
        s_samples += [s_samples[-1]] * n_tail
        v_samples += [0.0] * n_tail
        s_k = np.array(s_samples)
        v_k = np.array(v_samples)
        tau_k = np.arange(len(s_k)) * dt
        self.walk_s = float(tau_k[-1])
        base = route_spl(s_k)
        d1 = route_spl.derivative(1)(s_k)
        psi = np.unwrap(np.arctan2(d1[:, 1], d1[:, 0]))
        psi = gaussian_filter1d(psi, 0.3 * SAMPLE_HZ, mode="nearest")
        descent = np.arctan2(-d1[:, 2], np.hypot(d1[:, 0], d1[:, 1]))
        descent = gaussian_filter1d(descent, 0.5 * SAMPLE_HZ, mode="nearest")
        moving_until = tau_k[-1] - tail_s
        env = gaussian_filter1d(np.clip(v_k / 0.7, 0.0, 1.0), 0.3 * SAMPLE_HZ, mode="nearest")
        env *= _smootherstep(tau_k / 1.5) * (1.0 - _smootherstep((tau_k - moving_until) / 1.0))
        if not motion:
            env[:] = 0.0
        lat = np.column_stack([-np.sin(psi), np.cos(psi), np.zeros_like(psi)])
        if handheld is None:
            f_step = rng.uniform(1.8, 2.0)
            ph = 2 * np.pi * f_step * tau_k
            bob = (0.012 * np.sin(0.5 * ph + rng.uniform(0, 6.3)))[:, None] * lat
            bob[:, 2] += 0.02 * np.sin(ph)
            wander = np.column_stack([_wander(rng, tau_k, 0.02) for _ in range(3)])
            pos = base + env[:, None] * (bob + wander)
            deg = np.pi / 180.0
            d_yaw = 1.5 * deg * np.sin(0.5 * ph + 1.1) + _wander(rng, tau_k, 3.0 * deg)
            d_pitch = 1.0 * deg * np.sin(ph + 0.3) + _wander(rng, tau_k, 2.0 * deg)
            d_roll = 1.5 * deg * np.sin(0.5 * ph + 0.7) + _wander(rng, tau_k, 1.5 * deg)
        else:
            off, att = handheld.window(len(tau_k), seed)
            d_yaw, d_pitch, d_roll = att.T
            fwd = np.column_stack([np.cos(psi), np.sin(psi), np.zeros_like(psi)])
            shift = off[:, :1] * fwd + off[:, 1:2] * lat
            shift[:, 2] += off[:, 2]
            pos = base + env[:, None] * shift
        yaw = psi + env * d_yaw
        pitch = 0.4 * descent + env * d_pitch
        roll = env * d_roll
        pitch = pitch - pitch[0]
        euler = np.column_stack([yaw, pitch, roll])
        zero = np.zeros(3)
        bc = ([(1, zero), (2, zero)], [(1, zero), (2, zero)])
        self._pos = make_interp_spline(tau_k, pos, k=5, bc_type=bc)
        self._eul = make_interp_spline(tau_k, euler, k=5, bc_type=bc)
        self._pos_d = [self._pos.derivative(k) for k in (1, 2)]
        self._eul_d = [self._eul.derivative(k) for k in (1, 2)]
        self.route_length_m = float(length)

    @property
    def duration_s(self) -> float:
        """Static start + walk + still tail (seconds)."""
        return self.static_s + self.walk_s

    def _eval(self, spl: BSpline, d: list[BSpline], t_s: np.ndarray):
        tau = np.asarray(t_s, dtype=np.float64) - self.static_s
        moving = (tau > 0.0)[:, None]
        tc = np.clip(tau, 0.0, self.walk_s)
        return (spl(tc), np.where(moving, d[0](tc), 0.0), np.where(moving, d[1](tc), 0.0))

    def sample(self, t_s: np.ndarray) -> TrajectorySample:
        """Pose, velocity, acceleration, body rate and angular acceleration at ``t_s``."""
        t_s = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        p, v, a = self._eval(self._pos, self._pos_d, t_s)
        e, ed, edd = self._eval(self._eul, self._eul_d, t_s)
        R_world_rig = euler_zyx_to_matrix(e)
        w_rig, alpha_rig = euler_zyx_body_rates(e, ed, edd)
        Rri = self.R_rig_imu
        return TrajectorySample(p, v, a, R_world_rig @ Rri, w_rig @ Rri, alpha_rig @ Rri)

    def euler_zyx(self, t_s: np.ndarray) -> np.ndarray:
        """(N, 3) yaw, pitch, roll of the rig (radians)."""
        return self._eval(self._eul, self._eul_d, np.atleast_1d(t_s))[0]


def tilt_rig_lidar(tilt_deg: float) -> np.ndarray:
    """``R_rig_lidar`` of a LiDAR pitched ``tilt_deg`` nose down on the handle: about the rig's
    lateral (y) axis, so that its x axis points ``tilt_deg`` below the forward horizontal and its
    spin axis leans forward by as much (negative: nose up)."""
    return euler_zyx_to_matrix(np.array([[0.0, np.radians(tilt_deg), 0.0]]))[0]


def euler_zyx_to_matrix(e: np.ndarray) -> np.ndarray:
    """(N, 3) yaw, pitch, roll -> (N, 3, 3) ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cy, sy = np.cos(e[:, 0]), np.sin(e[:, 0])
    cp, sp = np.cos(e[:, 1]), np.sin(e[:, 1])
    cr, sr = np.cos(e[:, 2]), np.sin(e[:, 2])
    R = np.empty((len(e), 3, 3))
    R[:, 0, 0] = cy * cp
    R[:, 0, 1] = cy * sp * sr - sy * cr
    R[:, 0, 2] = cy * sp * cr + sy * sr
    R[:, 1, 0] = sy * cp
    R[:, 1, 1] = sy * sp * sr + cy * cr
    R[:, 1, 2] = sy * sp * cr - cy * sr
    R[:, 2, 0] = -sp
    R[:, 2, 1] = cp * sr
    R[:, 2, 2] = cp * cr
    return R


def euler_zyx_body_rates(e: np.ndarray, ed: np.ndarray,
                         edd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame angular rate and its time derivative of ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    th, ph = e[:, 1], e[:, 2]
    psid, thd, phd = ed[:, 0], ed[:, 1], ed[:, 2]
    psidd, thdd, phdd = edd[:, 0], edd[:, 1], edd[:, 2]
    st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
    w = np.column_stack([phd - psid * st,
                         thd * cp + psid * sp * ct,
                         -thd * sp + psid * cp * ct])
    wd = np.column_stack([
        phdd - psidd * st - psid * thd * ct,
        thdd * cp - thd * phd * sp + psidd * sp * ct + psid * phd * cp * ct
        - psid * thd * sp * st,
        -thdd * sp - thd * phd * cp + psidd * cp * ct - psid * phd * sp * ct
        - psid * thd * cp * st,
    ])
    return w, wd
