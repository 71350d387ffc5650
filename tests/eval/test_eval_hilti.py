"""HILTI 2022 score: synthetic threshold bands and the real exp04-06 ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from adalio.errors import InputError
from adalio.eval.hilti import hilti_score, points_for_error

REAL_GT = Path(__file__).resolve().parents[1] / "data" / "real" / "hilti2022_gt"
REAL = {
    "exp04": ("exp04_construction_upper_level.txt", "exp_04_*_imu.txt"),
    "exp05": ("exp05_construction_upper_level_2.txt", "exp_05_*_imu.txt"),
    "exp06": ("exp06_construction_upper_level_3.txt", "exp_06_*_imu.txt"),
}
TIP_M = np.array([0.059, -0.00855, 0.1964])


def write_tum(path: Path, t_s, xyz, quat_xyzw) -> Path:
    np.savetxt(path, np.column_stack([t_s, xyz, quat_xyzw]), fmt="%.12f")
    return path


def test_band_edges():
    expected = {0.0: 10, 0.0099: 10, 0.01: 6, 0.0299: 6, 0.03: 3, 0.0599: 3, 0.06: 1,
                0.0999: 1, 0.1: 0, 0.5: 0, float("nan"): 0}
    for err, pts in expected.items():
        assert points_for_error(err) == pts, err


# error magnitudes just below / above each threshold, each used by a +/- pair of control points
BAND_ERRORS_M = (0.0099, 0.0101, 0.0299, 0.0301, 0.0599, 0.0601, 0.0999, 0.1001, 0.004, 0.15)
BAND_POINTS = (10, 6, 6, 3, 3, 1, 1, 0, 10, 0)


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """Control points in +/- pairs around a centre, radial tip errors of known size.

    Radial errors of equal size on symmetric pairs have zero mean and a symmetric
    cross-covariance, so the optimal SE(3) alignment is the identity and each point's error
    after alignment is exactly the injected one. The IMU poses have random orientations, so the
    tip offset must be applied through the rotation to recover the tip.
    """
    d = tmp_path_factory.mktemp("hilti")
    rng = np.random.default_rng(3)
    centre = np.array([4.0, -2.0, 1.5])
    dirs = rng.normal(size=(len(BAND_ERRORS_M), 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = rng.uniform(3.0, 8.0, len(BAND_ERRORS_M))
    gt_xyz, err_vec, pts = [], [], []
    for u, r, e, p in zip(dirs, radii, BAND_ERRORS_M, BAND_POINTS, strict=True):
        for sign in (1.0, -1.0):
            gt_xyz.append(centre + sign * r * u)
            err_vec.append(sign * e * u)
            pts.append(p)
    gt_xyz = np.array(gt_xyz)
    n = len(gt_xyz)
    t_gt = 5000.0 + 10.0 * np.arange(n)
    # estimate: a pose 0.3 s after each control point (the nearest), decoys 1.5 s away
    tip_est = gt_xyz + np.array(err_vec)
    rot = Rotation.random(n, random_state=4)
    imu_xyz = tip_est - rot.apply(TIP_M)
    decoy_t = np.concatenate([t_gt - 1.5, t_gt + 1.6])
    t_all = np.concatenate([t_gt + 0.3, decoy_t])
    xyz_all = np.concatenate([imu_xyz, rng.normal(0, 50, (decoy_t.size, 3))])
    q_all = np.concatenate([rot.as_quat(), Rotation.random(decoy_t.size, 5).as_quat()])
    order = np.argsort(t_all)
    est = write_tum(d / "est.tum", t_all[order], xyz_all[order], q_all[order])
    ident = np.tile([0, 0, 0, 1.0], (n, 1))
    gt = write_tum(d / "gt.txt", t_gt, gt_xyz, ident)
    # one more control point whose nearest estimate is 2.1 s away (unmatched)
    t_extra = t_gt[-1] + 0.3 + 1.6 + 2.1
    gt_extra = write_tum(d / "gt_extra.txt", np.append(t_gt, t_extra),
                         np.vstack([gt_xyz, centre]), np.vstack([ident, [0, 0, 0, 1.0]]))
    return {"est": est, "gt": gt, "gt_extra": gt_extra, "points": pts, "n": n,
            "errors": np.abs(np.repeat(BAND_ERRORS_M, 2))}


def test_synthetic_bands(synthetic):
    res = hilti_score(synthetic["est"], synthetic["gt"])
    assert res["n_gt"] == res["n_matched"] == synthetic["n"]
    assert np.allclose(res["errors_m"], synthetic["errors"], atol=1e-7)
    assert res["points"] == synthetic["points"]
    assert res["score"] == pytest.approx(sum(synthetic["points"]) / (synthetic["n"] / 10))
    assert np.allclose(res["dt_s"], 0.3, atol=1e-6)  # the nearest pose, not a decoy
    assert np.allclose(res["T_gt_est"], np.eye(4), atol=1e-6)


def test_unmatched_control_point_scores_zero(synthetic):
    res = hilti_score(synthetic["est"], synthetic["gt_extra"])
    assert res["n_gt"] == synthetic["n"] + 1 and res["n_matched"] == synthetic["n"]
    assert res["errors_m"][-1] is None and res["points"][-1] == 0
    assert res["points"][:-1] == synthetic["points"]
    assert res["score"] == pytest.approx(sum(synthetic["points"]) / ((synthetic["n"] + 1) / 10))


def test_without_tip_offset_errors_change(synthetic):
    res = hilti_score(synthetic["est"], synthetic["gt"], tip_offset=False)
    assert np.mean(res["errors_m"]) > 0.05


def test_too_few_matches(tmp_path, synthetic):
    far = write_tum(tmp_path / "far.tum", [1.0, 2.0, 3.0], np.eye(3), np.tile([0, 0, 0, 1.0], (3, 1)))
    with pytest.raises(InputError, match="need >= 3"):
        hilti_score(far, synthetic["gt"])


def _real_files(name: str) -> tuple[Path, Path]:
    if not REAL_GT.is_dir():
        pytest.fail(f"HILTI ground truth folder {REAL_GT} is missing: it ships in "
                    "the repository (tests/data/real)")
    sparse, pattern = REAL[name]
    dense = sorted(REAL_GT.glob(pattern))
    if not (REAL_GT / sparse).is_file() or not dense:
        pytest.fail(f"HILTI file {sparse} or {pattern} missing in {REAL_GT}")
    return dense[0], REAL_GT / sparse


def _independent_errors(dense: Path, sparse: Path, tip: bool) -> np.ndarray:
    """Nearest pose in time, tip offset via scipy, Umeyama in numpy."""
    est = np.loadtxt(dense)
    gt = np.loadtxt(sparse)
    k = np.abs(est[:, 0][None, :] - gt[:, 0][:, None]).argmin(1)
    assert np.all(np.abs(est[k, 0] - gt[:, 0]) < 2.0)
    p = est[k, 1:4] + (Rotation.from_quat(est[k, 4:8]).apply(TIP_M) if tip else 0.0)
    q = gt[:, 1:4]
    mu_p, mu_q = p.mean(0), q.mean(0)
    U, _, Vt = np.linalg.svd((q - mu_q).T @ (p - mu_p))
    S = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    return np.linalg.norm(p @ R.T + (mu_q - R @ mu_p) - q, axis=1)


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_hilti_dense_against_control_points(name):
    dense, sparse = _real_files(name)
    res = hilti_score(dense, sparse)
    err = np.array(res["errors_m"], dtype=float)
    assert res["n_matched"] == res["n_gt"] >= 6
    assert np.allclose(err, _independent_errors(dense, sparse, tip=True), atol=1e-9)
    assert err.max() < 0.07  # README: 0.4 to 5.9 cm
    assert 40.0 <= res["score"] <= 90.0
    no_tip = hilti_score(dense, sparse, tip_offset=False)
    assert np.allclose(no_tip["errors_m"], _independent_errors(dense, sparse, tip=False),
                       atol=1e-9)
    assert np.mean(no_tip["errors_m"]) > np.mean(err) + 0.01  # README: 3.3 to 10.2 cm
    assert no_tip["score"] < res["score"]
