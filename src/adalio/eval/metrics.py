"""Trajectory accuracy: absolute (ATE) and relative (RPE) translation errors, via evo.

Both trajectories are TUM files (or evo ``PoseTrajectory3D``) of the IMU pose in their own world
frame, stamped in seconds on the same clock. Association starts from the estimate: every
estimated pose is paired with the nearest-in-time GT pose if they are within ``max_diff_s``
(evo's ``sync.matching_time_indices`` with the estimate first, which is what evo's
``associate_trajectories`` does when the estimate has no more poses than the GT; evo starts from
the trajectory with fewer poses, so a GT shorter than the run paired one estimate with several
GT poses). The GT pose of a pair is then interpolated at the estimate's time stamp (positions
linearly, rotations by slerp) wherever the GT has a pose within ``max_diff_s`` on either side of
it (:func:`interpolate_gt`); elsewhere (a sparse GT, its ends) it stays the nearest GT pose, and
such a GT pose is paired with one estimate only, the nearest in time (so a 1 Hz GT against a
100 Hz estimate counts each GT pose once, as evo does). Each pose enters the errors once.
Without this a GT at 100 Hz and a LiDAR whose scans end 3.6 ms off its grid (the simulated
OS1-64) add the 4.5 mm the sensor moves in 3.6 ms at a walk to every error: 0.30 instead of
0.19 cm of ATE on the hall. ``interpolate=False`` gives evo's nearest pose.

Alignment of the estimate onto the ground truth before the ATE:

* ``se3``: evo ``align(correct_scale=False)``, the Umeyama least-squares rotation + translation
  over all associated positions (no scale).
* ``first``: evo ``align_origin``: the rigid transform ``T = T_world_gt(t0) T_world_est(t0)^-1``
  that makes the first associated estimated pose coincide with its GT pose (full 6-DoF, so an
  initial heading error shows up as a growing ATE).
* ``none``: raw differences of positions in whatever frames the files are in.

ATE = evo ``APE(translation_part)`` after alignment. RPE = evo ``RPE(translation_part)`` (and
``rotation_angle_deg``) over consecutive pairs whose GT path length is ``delta_m`` (evo
``delta_unit=meters``, ``pairs_from_reference=True``); it is alignment-free. Metres throughout.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from evo.core import metrics as evo_metrics
from evo.core import sync
from evo.core.trajectory import PoseTrajectory3D
from evo.core.units import Unit

from adalio.errors import InputError
from adalio.eval.files import TrajectoryLike, read_trajectory

ALIGNMENTS = ("se3", "first", "none")
SCORE_CONTROL_POINTS = "score them with `adalio eval EST GT --hilti`"
"""The hint of the association's errors for a GT of control points (eval, report, compare and
``run --gt`` share these messages, so the hints name a command, not an option)."""
DEFAULT_MAX_DIFF_S = 0.02
DEFAULT_RPE_DELTAS_M = (1.0, 5.0)


@dataclass
class AlignedPair:
    """Associated GT / estimate pair, the estimate already aligned onto the GT."""

    gt: PoseTrajectory3D
    est: PoseTrajectory3D
    align: str
    T_gt_est: np.ndarray
    """(4, 4) transform applied to the estimate (identity for 'none')."""
    errors_m: np.ndarray
    """(n,) position error of each associated pair after alignment."""
    n_interpolated: int | None = None
    """Of the pairs, those whose GT pose is interpolated at the estimate's stamp (the others
    are the nearest GT pose); None where not known."""

    @property
    def t_s(self) -> np.ndarray:
        return np.asarray(self.gt.timestamps, dtype=np.float64)


def check_max_diff(max_diff_s: float) -> None:
    """InputError unless the association's time gap is a finite number of seconds > 0."""
    if not 0.0 < max_diff_s < float("inf"):
        raise InputError(f"--max-diff must be a finite number of seconds > 0 (got {max_diff_s})")


def associate(est: TrajectoryLike, gt: TrajectoryLike, max_diff_s: float = DEFAULT_MAX_DIFF_S,
              interpolate: bool = True) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    """Return ``(gt_sync, est_sync)`` with equal length (:func:`associate_counted`)."""
    gt_s, est_s, _ = associate_counted(est, gt, max_diff_s, interpolate)
    return gt_s, est_s


def associate_counted(est: TrajectoryLike, gt: TrajectoryLike,
                      max_diff_s: float = DEFAULT_MAX_DIFF_S, interpolate: bool = True
                      ) -> tuple[PoseTrajectory3D, PoseTrajectory3D, int]:
    """Return ``(gt_sync, est_sync)`` with equal length: each estimated pose with the nearest GT
    pose within ``max_diff_s`` (see the module docstring); with ``interpolate`` the GT poses are
    interpolated at the estimate's stamps where the GT brackets them within ``max_diff_s``
    (:func:`interpolate_gt`). A GT pose kept as it is pairs with its nearest estimate only.
    The third value is how many of the pairs have an interpolated GT pose."""
    check_max_diff(max_diff_s)
    est_t = read_trajectory(est, "estimate")
    gt_t = read_trajectory(gt, "ground-truth")
    t_est = np.asarray(est_t.timestamps, dtype=np.float64)
    t_gt = np.asarray(gt_t.timestamps, dtype=np.float64)
    i_est, i_gt = (np.asarray(i, dtype=np.int64) for i in
                   sync.matching_time_indices(t_est, t_gt, max_diff=max_diff_s))
    exact = (_bracketed(t_gt, t_est[i_est], max_diff_s)[0] if interpolate
             else np.zeros(i_est.size, dtype=bool))
    n_interpolated = int(np.count_nonzero(exact))
    loose = np.nonzero(~exact)[0]
    if loose.size:  # a GT pose not interpolated: only its nearest estimate
        dt = np.abs(t_est[i_est[loose]] - t_gt[i_gt[loose]])
        order = np.lexsort((dt, i_gt[loose]))
        first = order[np.r_[True, np.diff(i_gt[loose][order]) != 0]]
        exact[loose[first]] = True
    i_est, i_gt = i_est[exact], i_gt[exact]
    if i_est.size == 0:
        from adalio.eval.hilti import looks_like_control_points

        hint = (f" (sparse control points? {SCORE_CONTROL_POINTS})"
                if looks_like_control_points(gt_t) else
                "; are both in seconds on the same clock?")
        raise InputError(
            f"no estimate/GT pose pairs within {max_diff_s} s: the estimate spans "
            f"{_span(est_t)} and the GT {_span(gt_t)}{hint}")
    est_s = copy.deepcopy(est_t)
    est_s.reduce_to_ids(i_est)
    gt_s = copy.deepcopy(gt_t)
    gt_s.reduce_to_ids(i_gt)
    if interpolate:
        gt_s = interpolate_gt(gt_t, gt_s, np.asarray(est_s.timestamps, dtype=np.float64),
                              max_diff_s)
    return gt_s, est_s, n_interpolated


def interpolate_gt(gt: PoseTrajectory3D, gt_sync: PoseTrajectory3D, t_s: np.ndarray,
                   max_diff_s: float) -> PoseTrajectory3D:
    """The GT poses at the times ``t_s`` (sorted, one per pose of ``gt_sync``, the GT poses
    associated with them): where ``gt`` has a pose at most ``max_diff_s`` before and one at most
    ``max_diff_s`` after a time, the pose between them at that time (position linear in time,
    rotation by slerp, the shorter way); elsewhere the pose of ``gt_sync``."""
    tg = np.asarray(gt.timestamps, dtype=np.float64)
    t = np.asarray(t_s, dtype=np.float64)
    pos = np.array(gt_sync.positions_xyz, dtype=np.float64)
    quat = np.array(gt_sync.orientations_quat_wxyz, dtype=np.float64)
    ok, lo, hi = _bracketed(tg, t, max_diff_s)
    if not np.any(ok):
        return gt_sync
    from scipy.spatial.transform import Rotation

    a, b = lo[ok], hi[ok]
    s = ((t[ok] - tg[a]) / (tg[b] - tg[a]))[:, None]
    p_all = np.asarray(gt.positions_xyz, dtype=np.float64)
    pos[ok] = (1.0 - s) * p_all[a] + s * p_all[b]
    q_all = np.asarray(gt.orientations_quat_wxyz, dtype=np.float64)
    r_a = Rotation.from_quat(q_all[a][:, [1, 2, 3, 0]])
    r_b = Rotation.from_quat(q_all[b][:, [1, 2, 3, 0]])
    r = r_a * Rotation.from_rotvec(s * (r_a.inv() * r_b).as_rotvec())
    quat[ok] = r.as_quat()[:, [3, 0, 1, 2]]
    return PoseTrajectory3D(positions_xyz=pos, orientations_quat_wxyz=quat, timestamps=t.copy())


def _bracketed(tg: np.ndarray, t: np.ndarray,
               max_diff_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(ok, lo, hi)``: ``ok`` where the GT stamps ``tg`` have one at most ``max_diff_s`` before
    and one at most ``max_diff_s`` after a time of ``t``, ``tg[lo] < t <= tg[hi]``."""
    hi = np.searchsorted(tg, t, side="left")  # tg[hi - 1] < t <= tg[hi]
    inside = (hi > 0) & (hi < len(tg))
    lo = np.clip(hi - 1, 0, len(tg) - 1)
    hi = np.clip(hi, 0, len(tg) - 1)
    ok = inside & (t - tg[lo] <= max_diff_s) & (tg[hi] - t <= max_diff_s) & (tg[hi] > tg[lo])
    return ok, lo, hi


def _span(traj: PoseTrajectory3D) -> str:
    t = traj.timestamps
    return f"[{t[0]:.3f}, {t[-1]:.3f}] s"


def _eval_command(est: TrajectoryLike, gt: TrajectoryLike) -> str:
    """``adalio eval EST GT`` with the files' paths where they are files."""
    import shlex

    def arg(x: TrajectoryLike, name: str) -> str:
        return shlex.quote(str(x)) if isinstance(x, str | Path) else name

    return f"adalio eval {arg(est, 'EST')} {arg(gt, 'GT')}"


def align_pair(est: TrajectoryLike, gt: TrajectoryLike, align: str = "se3",
               max_diff_s: float = DEFAULT_MAX_DIFF_S, interpolate: bool = True) -> AlignedPair:
    """Associate, align the estimate onto the GT (see module docstring) and compute errors."""
    if align not in ALIGNMENTS:
        raise InputError(f"--align must be one of {', '.join(ALIGNMENTS)} (got {align!r})")
    gt_s, est_s, n_interpolated = associate_counted(est, gt, max_diff_s, interpolate)
    est_a = copy.deepcopy(est_s)
    T = np.eye(4)
    if align == "se3":
        if gt_s.num_poses < 3:
            from adalio.eval.hilti import looks_like_control_points

            hint = (f"sparse control points? {SCORE_CONTROL_POINTS}"
                    if looks_like_control_points(gt) else
                    "the ground truth covers too little of the run; "
                    f"`{_eval_command(est, gt)} --align first` scores it on the first pose, and "
                    "`--max-diff S` there pairs poses further apart")
            raise InputError(f"only {gt_s.num_poses} associated poses: se3 alignment needs >= 3 "
                             f"({hint})")
        try:
            r, t, _ = est_a.align(gt_s, correct_scale=False)
        except Exception as exc:  # noqa: BLE001 - evo GeometryException on degenerate input
            pos = gt_s.positions_xyz
            spread = float(np.max(np.linalg.norm(pos - pos.mean(axis=0), axis=1)))
            what = (f"the ground truth does not move over the {gt_s.num_poses} associated poses "
                    f"(within {spread:.3g} m: a stretch at rest)" if spread < 0.01 else
                    "the associated ground-truth positions lie on a line")
            raise InputError(f"se3 alignment failed ({exc}): {what}; evaluate a longer "
                             "stretch, or score it on the first pose with "
                             f"`{_eval_command(est, gt)} --align first`") from None
        T[:3, :3] = r
        T[:3, 3] = t
    elif align == "first":
        T = est_a.align_origin(gt_s)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((gt_s, est_a))
    return AlignedPair(gt=gt_s, est=est_a, align=align, T_gt_est=np.asarray(T),
                       errors_m=np.asarray(ape.error, dtype=np.float64),
                       n_interpolated=n_interpolated)


def ate(est_tum: TrajectoryLike, gt_tum: TrajectoryLike, align: str = "se3",
        max_diff_s: float = DEFAULT_MAX_DIFF_S, interpolate: bool = True) -> dict:
    """Absolute trajectory error (translation) after alignment.

    Returns ``dict(rmse_m, mean_m, median_m, std_m, max_m, n, align, max_diff_s,
    duration_s, n_interpolated)`` where ``n`` is the number of associated pose pairs and
    ``n_interpolated`` how many of them have the GT interpolated at the estimate's stamp.
    """
    pair = align_pair(est_tum, gt_tum, align, max_diff_s, interpolate)
    return ate_from_pair(pair, max_diff_s)


def ate_from_pair(pair: AlignedPair, max_diff_s: float = DEFAULT_MAX_DIFF_S) -> dict:
    """The statistics of :func:`ate` for an already aligned pair."""
    e = pair.errors_m
    t = pair.t_s
    return {
        "rmse_m": float(np.sqrt(np.mean(e**2))),
        "mean_m": float(np.mean(e)),
        "median_m": float(np.median(e)),
        "std_m": float(np.std(e)),
        "max_m": float(np.max(e)),
        "n": int(e.size),
        "align": pair.align,
        "max_diff_s": float(max_diff_s),
        "duration_s": float(t[-1] - t[0]),
        "n_interpolated": pair.n_interpolated,
    }


def rpe(est_tum: TrajectoryLike, gt_tum: TrajectoryLike,
        deltas_m: tuple[float, ...] | list[float] = DEFAULT_RPE_DELTAS_M,
        max_diff_s: float = DEFAULT_MAX_DIFF_S, interpolate: bool = True) -> list[dict]:
    """Relative pose error over GT path segments of each length in ``deltas_m``.

    One dict per delta: ``delta_m, n, rmse_m, mean_m, median_m, max_m, drift_pct`` (mean / delta
    x 100) and ``rot_rmse_deg``; the statistics are None when the GT path is shorter than delta.
    """
    gt_s, est_s = associate(est_tum, gt_tum, max_diff_s, interpolate)
    out = []
    for delta in deltas_m:
        if not delta > 0:
            raise InputError(f"--rpe-delta values must be > 0 m (got {delta})")
        row: dict = {"delta_m": float(delta), "n": 0, "rmse_m": None, "mean_m": None,
                     "median_m": None, "max_m": None, "drift_pct": None, "rot_rmse_deg": None}
        errors = {}
        for rel in (evo_metrics.PoseRelation.translation_part,
                    evo_metrics.PoseRelation.rotation_angle_deg):
            metric = evo_metrics.RPE(rel, delta=float(delta), delta_unit=Unit.meters,
                                     all_pairs=False, pairs_from_reference=True)
            try:
                metric.process_data((gt_s, est_s))
            except Exception:  # noqa: BLE001 - evo raises when no pair spans delta
                break
            errors[rel] = np.asarray(metric.error, dtype=np.float64)
        e = errors.get(evo_metrics.PoseRelation.translation_part)
        if e is not None and e.size:
            row.update(n=int(e.size), rmse_m=float(np.sqrt(np.mean(e**2))),
                       mean_m=float(np.mean(e)), median_m=float(np.median(e)),
                       max_m=float(np.max(e)), drift_pct=float(np.mean(e) / delta * 100.0))
            r = errors.get(evo_metrics.PoseRelation.rotation_angle_deg)
            if r is not None and r.size:
                row["rot_rmse_deg"] = float(np.sqrt(np.mean(r**2)))
        out.append(row)
    return out


def path_length_m(traj: TrajectoryLike) -> float:
    """Total travelled distance of a trajectory (metres)."""
    t = read_trajectory(traj)
    return float(np.sum(np.linalg.norm(np.diff(t.positions_xyz, axis=0), axis=1)))


SIGMA_COLUMNS = ("sigma_x_m", "sigma_y_m", "sigma_z_m")


@dataclass
class SigmaConsistency:
    """How honest the filter's position standard deviations are against a ground truth."""

    t_s: np.ndarray
    """(n,) associated times (s)."""
    errors_world_m: np.ndarray
    """(n, 3) estimate minus ground truth in the estimate's world frame, the ground truth aligned
    on the pose of the filter's first scan, which defines the world and has sigma 0 (the
    first associated pose whose ``scans.csv`` row has ``backfill`` 0; the first associated pose
    if the file has no ``backfill`` column). Poses given by the backfill come before it in
    time and have sigmas that grow backwards from it."""
    sigma_world_m: np.ndarray
    """(n, 3) the filter's sigma_x/y/z_m at those scans."""
    within_3sigma: np.ndarray
    """(3,) share of scans with ``|error| <= 3 sigma`` on x, y, z."""
    mean_nees: float
    """Mean of ``Σ_axis (error / sigma)²`` (3 for a consistent filter; the covariance's
    off-diagonal terms are not in scans.csv, so this is the diagonal NEES)."""
    increment_correlation: np.ndarray
    """(3,) per axis, the correlation of consecutive ``INCREMENT_S`` increments of the error
    (lag 1): about 0 when the error grows as a random walk, towards +1 when it drifts the same
    way for a long time (a bias), negative when it swings back. NaN for fewer than 3 increments."""
    median_abs_z: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    """(3,) per axis, the median over the scans of ``|error| / sigma``: ``MEDIAN_ABS_Z``
    (0.674) for honest Gaussian sigmas, far below it for sigmas much larger than the errors
    (which the within-3σ share and the mean NEES alone do not show), above it for sigmas
    too small."""
    backfill_max_error_m: float = float("nan")
    """The largest position error (m, the same alignment) of the poses the backfill gave
    (``scans.csv`` ``backfill`` 1): how far the scans read before the filter's start lie from
    where the truth, seen from the first forward pose, puts them. NaN without such poses."""
    anchor_t_s: float = float("nan")
    """Time (s) of the pose the ground truth is aligned on (see ``errors_world_m``)."""
    first_scan_t_s: float = float("nan")
    """Time (s) of the filter's first scan (the first ``scans.csv`` row with ``backfill`` 0, or
    the first row): the anchor when the ground truth covers the run's start. A later anchor (a
    GT that starts later) has a sigma above 0 there, and its errors, measured from it, are too
    small against those sigmas: the three figures come out optimistic."""
    anchor_sigma_m: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    """(3,) the sigma_x/y/z_m of the anchor's scan (0 at the filter's first scan)."""

    @property
    def anchor_is_first_scan(self) -> bool:
        return bool(abs(self.anchor_t_s - self.first_scan_t_s) <= 1e-6)


MEDIAN_ABS_Z = 0.6744897501960817
"""The median of ``|z|`` for a standard normal ``z``."""


def sigma_consistency(est_tum: TrajectoryLike, gt_tum: TrajectoryLike,
                      scans: dict[str, np.ndarray],
                      max_diff_s: float = DEFAULT_MAX_DIFF_S,
                      interpolate: bool = True) -> SigmaConsistency:
    """Compare the errors of a run with the sigma columns of its ``scans.csv`` (as read by
    :func:`adalio.eval.files.read_scans_csv`)."""
    missing = [c for c in SIGMA_COLUMNS if c not in scans]
    if missing:
        raise InputError(f"scans.csv has no {', '.join(missing)} column: it was written by an "
                         "adalio without sigma columns; re-run the bag")
    gt_s, est_s = associate(est_tum, gt_tum, max_diff_s, interpolate)
    t_est = np.asarray(est_s.timestamps, dtype=np.float64)
    t_csv = np.asarray(scans["t_s"], dtype=np.float64)
    order = np.argsort(t_csv, kind="stable")  # the backfill's rows are written after later ones
    t_sorted = t_csv[order]
    pos = np.clip(np.searchsorted(t_sorted, t_est), 0, max(len(t_csv) - 1, 0))
    prev = np.clip(pos - 1, 0, None)
    pos = np.where(np.abs(t_sorted[prev] - t_est) < np.abs(t_sorted[pos] - t_est), prev, pos)
    idx = order[pos]
    ok = np.abs(t_csv[idx] - t_est) <= 1e-6
    anchor = 0
    backfilled = np.zeros(len(t_est), dtype=bool)
    forward_csv = np.ones(len(t_csv), dtype=bool)
    if "backfill" in scans:
        forward_csv = np.asarray(scans["backfill"], dtype=np.float64) == 0
        flags = np.asarray(scans["backfill"], dtype=np.float64)[idx]
        forward = ok & (flags == 0)
        backfilled = ok & (flags == 1)
        if forward.any():
            anchor = int(np.argmax(forward))
    T = est_s.poses_se3[anchor] @ np.linalg.inv(gt_s.poses_se3[anchor])
    p_gt = gt_s.positions_xyz @ T[:3, :3].T + T[:3, 3]
    err = est_s.positions_xyz - p_gt
    bf_max = (float(np.max(np.linalg.norm(err[backfilled], axis=1))) if backfilled.any()
              else float("nan"))
    sig = np.column_stack([np.asarray(scans[c], dtype=np.float64)[idx] for c in SIGMA_COLUMNS])
    anchor_sigma = sig[anchor].copy() if ok[anchor] else np.full(3, np.nan)
    first_scan_t = float(np.min(t_csv[forward_csv])) if forward_csv.any() else float("nan")
    ok &= np.all(np.isfinite(sig) & (sig > 0), axis=1)
    if not np.any(ok):
        raise InputError("no trajectory pose has a scans.csv row with finite sigma columns at "
                         "the same time: are the two files from the same run?")
    err, sig = err[ok], sig[ok]
    z = err / sig
    return SigmaConsistency(t_s=t_est[ok], errors_world_m=err, sigma_world_m=sig,
                            within_3sigma=np.mean(np.abs(z) <= 3.0, axis=0),
                            mean_nees=float(np.mean(np.sum(z * z, axis=1))),
                            increment_correlation=increment_correlation(t_est[ok], err),
                            median_abs_z=np.median(np.abs(z), axis=0),
                            backfill_max_error_m=bf_max, anchor_t_s=float(t_est[anchor]),
                            first_scan_t_s=first_scan_t, anchor_sigma_m=anchor_sigma)


INCREMENT_S = 1.0
"""Step (s) of the error increments whose correlation :func:`increment_correlation` reports."""


def increment_correlation(t_s: np.ndarray, errors: np.ndarray,
                          step_s: float = INCREMENT_S) -> np.ndarray:
    """Per column of ``errors`` (n, d) at times ``t_s`` (n,): the lag-1 correlation of the
    error's increments over consecutive ``step_s`` intervals (the error sampled at the first
    time at or after each multiple of ``step_s`` from the start). NaN where fewer than 3
    increments exist or an increment series is constant."""
    t = np.asarray(t_s, dtype=np.float64)
    e = np.asarray(errors, dtype=np.float64).reshape(len(t), -1)
    out = np.full(e.shape[1], np.nan)
    if len(t) < 2:
        return out
    marks = t[0] + step_s * np.arange(int(np.floor((t[-1] - t[0]) / step_s)) + 1)
    idx = np.unique(np.searchsorted(t, marks - 1e-9))  # marks <= t[-1]: every index is valid
    d = np.diff(e[idx], axis=0)
    if d.shape[0] < 3:
        return out
    for a in range(e.shape[1]):
        x, y = d[:-1, a], d[1:, a]
        if np.std(x) > 0 and np.std(y) > 0:
            out[a] = float(np.corrcoef(x, y)[0, 1])
    return out
