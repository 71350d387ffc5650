"""HILTI SLAM Challenge 2022 score of an IMU-frame trajectory against sparse control points.

Official rules (Hilti-Research/hilti-slam-challenge-2022, ``evaluation-2022``; see
``shared/data/real/hilti2022_gt/README.md``):

1. The ground truth is a sparse TUM file of surveyed pole-tip positions (its quaternions are
   meaningless). The estimate is the IMU (Alphasense) pose in its world frame; each estimated pose
   is right-multiplied by ``T_imu_tip = [I | (0.059, -0.00855, 0.1964)]`` so tip positions are
   compared.
2. Each control point is paired with the nearest-in-time estimated pose within 2 s
   (evo ``sync.matching_time_indices``, the routine behind ``associate_trajectories``).
3. The tip positions are SE(3)-aligned to the matched control points only (evo
   ``align(correct_scale=False)``, Umeyama without scale); the error is evo's APE on translation.
4. Points per control point: < 1 cm: 10, < 3 cm: 6, < 6 cm: 3, < 10 cm: 1, else 0; unmatched
   control points get 0. Score = sum / (N_gt / 10), so 100 at most.

Metres and seconds throughout.
"""

from __future__ import annotations

import copy

import numpy as np
from evo.core import metrics as evo_metrics
from evo.core import sync

from adalio.errors import InputError
from adalio.eval.files import TrajectoryLike, read_trajectory
from adalio.eval.metrics import check_max_diff

T_IMU_TIP = np.array([[1.0, 0.0, 0.0, 0.059],
                      [0.0, 1.0, 0.0, -0.00855],
                      [0.0, 0.0, 1.0, 0.1964],
                      [0.0, 0.0, 0.0, 1.0]])
"""Pole tip in the IMU frame (HILTI 2022 scorer)."""
MAX_DIFF_S = 2.0
"""A control point is matched to the nearest estimate within this time (seconds)."""
BAND_LIMITS_M = (0.01, 0.03, 0.06, 0.10)
"""Upper limits (exclusive) of the error bands, metres."""
BAND_POINTS = (10, 6, 3, 1, 0)
"""Points of each band, the last one for errors >= 10 cm."""


def looks_like_control_points(gt_tum: TrajectoryLike) -> bool:
    """True for a HILTI-style control-point file: identity quaternions, >= 1 s apart (median)."""
    gt = read_trajectory(gt_tum, "ground-truth")
    q = np.asarray(gt.orientations_quat_wxyz)
    identity = bool(np.all(np.abs(np.abs(q[:, 0]) - 1.0) < 1e-9))
    spacing = float(np.median(np.diff(gt.timestamps))) if gt.num_poses > 1 else 0.0
    return identity and spacing >= 1.0


def not_control_points_warning(gt_tum: TrajectoryLike, command: str,
                               max_diff_s: float = MAX_DIFF_S) -> str | None:
    """The warning for ``--hilti`` given a ground truth that :func:`looks_like_control_points`
    refuses (``command``: the adalio command to run without --hilti), else None."""
    if looks_like_control_points(gt_tum):
        return None
    return (f"warning: {gt_tum} does not look like HILTI control points (identity orientations "
            "at least 1 s apart): the score pairs each of its poses with an estimate up to "
            f"{max_diff_s:g} s away; for a dense ground truth use {command} without --hilti")


def points_for_error(error_m: float) -> int:
    """Points of one control point with position error ``error_m`` (NaN = unmatched -> 0)."""
    if not np.isfinite(error_m):
        return 0
    for limit, pts in zip(BAND_LIMITS_M, BAND_POINTS, strict=False):
        if error_m < limit:
            return pts
    return BAND_POINTS[-1]


def hilti_score(est_tum: TrajectoryLike, gt_tum: TrajectoryLike, *, tip_offset: bool = True,
                max_diff_s: float = MAX_DIFF_S) -> dict:
    """HILTI 2022 score of an estimate against control points.

    Returns ``dict(score, n_gt, n_matched, points (list per control point), errors_m (list per
    control point, None if unmatched), t_s (control point times), dt_s (time gap to the matched
    estimate, None if unmatched), tip_offset, T_gt_est (4x4 nested list))``.
    Raises InputError when fewer than 3 control points have an estimate within ``max_diff_s``
    (the SE(3) alignment is then undefined).
    """
    check_max_diff(max_diff_s)
    est = read_trajectory(est_tum, "estimate")
    gt = read_trajectory(gt_tum, "control-point")
    if tip_offset:
        est.transform(T_IMU_TIP, right_mul=True)
    idx_gt, idx_est = sync.matching_time_indices(gt.timestamps, est.timestamps,
                                                 max_diff=max_diff_s)
    n_gt = int(gt.num_poses)
    if len(idx_gt) < 3:
        raise InputError(
            f"only {len(idx_gt)} of {n_gt} control points have an estimate within {max_diff_s} s "
            f"(estimate spans [{est.timestamps[0]:.3f}, {est.timestamps[-1]:.3f}] s, control "
            f"points [{gt.timestamps[0]:.3f}, {gt.timestamps[-1]:.3f}] s): need >= 3 to align")
    gt_m = copy.deepcopy(gt)
    gt_m.reduce_to_ids(idx_gt)
    est_m = copy.deepcopy(est)
    est_m.reduce_to_ids(idx_est)
    try:
        r, t, _ = est_m.align(gt_m, correct_scale=False)
    except Exception as exc:  # noqa: BLE001 - evo GeometryException on collinear points
        raise InputError(f"SE(3) alignment to the control points failed ({exc})") from None
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((gt_m, est_m))
    errors = np.full(n_gt, np.nan)
    errors[np.asarray(idx_gt)] = np.asarray(ape.error, dtype=np.float64)
    dt = np.full(n_gt, np.nan)
    dt[np.asarray(idx_gt)] = est.timestamps[np.asarray(idx_est)] - gt.timestamps[np.asarray(idx_gt)]
    points = [points_for_error(e) for e in errors]
    T = np.eye(4)
    T[:3, :3] = r
    T[:3, 3] = t
    return {
        "score": float(sum(points) / (n_gt / 10.0)),
        "n_gt": n_gt,
        "n_matched": len(idx_gt),
        "points": points,
        "errors_m": [None if not np.isfinite(e) else float(e) for e in errors],
        "t_s": [float(x) for x in gt.timestamps],
        "dt_s": [None if not np.isfinite(d) else float(d) for d in dt],
        "tip_offset": bool(tip_offset),
        "T_gt_est": T.tolist(),
    }
