"""``filter.robust_kernel``: the rows' IRLS weights, against a brute-force formula and against the
true pose of a synthetic room (floor and two walls) whose scan holds rows off their planes."""

import numpy as np
import pytest

from adalio.config import Config
from adalio.lio.ieskf import iterated_update
from adalio.lio.ivox import IVox
from adalio.lio.measurement import (
    KERNEL_WIDTH,
    MAD_TO_SIGMA,
    normal_noise_terms,
    pose_quadratic,
    robust_row_factors,
)
from adalio.lio.odometry import _Association, robust_kernel_name
from adalio.lio.state import DIM, State


def test_factors_follow_the_kernels_formulas() -> None:
    rng = np.random.default_rng(3)
    m = 40
    r = rng.normal(scale=0.03, size=m)
    H = rng.normal(size=(m, 6))
    A = rng.normal(size=(6, 6)) * 0.01
    P = A @ A.T
    sigma = MAD_TO_SIGMA * np.median(np.abs(r))
    for name in ("geman_mcclure", "huber"):
        for scale in (1.0, 3.0):
            c = robust_row_factors(r, H, P, name, scale)
            for i in range(m):
                k2 = scale**2 * (sigma**2 + H[i] @ P @ H[i])
                w = (k2 / (k2 + r[i] ** 2)) ** 2 if name == "geman_mcclure" else min(
                    1.0, np.sqrt(k2) / abs(r[i]))
                assert c[i] ** 2 == pytest.approx(w, rel=1e-12)
    np.testing.assert_array_equal(robust_row_factors(r, H, P, "none", 3.0), np.ones(m))
    for name, width in KERNEL_WIDTH.items():  # scale 0: the kernel's usual width
        np.testing.assert_array_equal(robust_row_factors(r, H, P, name, 0.0),
                                      robust_row_factors(r, H, P, name, width))
    # without the prediction's covariance, the width is the scan's own noise alone
    c = robust_row_factors(r, H, None, "geman_mcclure", 3.0)
    k2 = 9 * sigma**2
    np.testing.assert_allclose(c, k2 / (k2 + r**2), rtol=1e-12)


def test_the_rows_spread_is_numpys_einsum_bit_for_bit() -> None:
    """``pose_quadratic`` replaced ``einsum("ij,jk,ik->i")`` in the robust kernel's spread: it
    must round exactly as einsum did, or every trajectory would move in its last digits (and
    the shaft's chaos grows those to centimetres). Rows as the filter passes them: the pose
    columns of an (m, 12) array, a (6, 6) slice of a larger covariance; scales over six decades."""
    rng = np.random.default_rng(7)
    for trial in range(50):
        m = int(rng.integers(1, 2000))
        H = rng.normal(size=(m, 12)) * 10.0 ** rng.uniform(-3, 1, size=(1, 12))
        A = rng.normal(size=(23, 23))
        P = (A @ A.T) * 10.0 ** rng.uniform(-7, -1)
        expected = np.einsum("ij,jk,ik->i", H[:, :6], P[:6, :6], H[:, :6])
        got = pose_quadratic(H[:, :6], P[:6, :6])
        np.testing.assert_array_equal(got, expected)
        # and it is h P hᵀ
        i = int(rng.integers(m))
        assert got[i] == pytest.approx(H[i, :6] @ P[:6, :6] @ H[i, :6], rel=1e-10)
    assert pose_quadratic(np.zeros((0, 6)), np.eye(6)).shape == (0,)


def test_the_update_reuses_the_normals_noise_only_while_its_search_holds() -> None:
    """The errors-in-variables terms reuse each search's normal covariances over the update's
    iterations: at every evaluation they equal :func:`normal_noise_terms` computed afresh from
    the rows as they are then (accepted rows, weights, pose), also after a new search."""
    cfg = Config()
    ivox, scan, _ = _room(cfg, np.random.default_rng(13), 300)
    cfg.filter.robust_kernel = "huber"
    P_pose = np.diag([0.05**2] * 3 + [np.radians(0.5) ** 2] * 3)
    a = _Association(scan, ivox, cfg, 5.0, 0.1, cfg.map.map_leaf_m, None, P_pose)
    poses = [np.array([0.0, 0.0, 0.04]), np.array([0.0, 0.0, 0.03]), np.array([0.01, 0.0, 0.0])]
    searches = []
    for k, p in enumerate(poses):
        x = State(p=p, R_LI=np.eye(3), t_LI=np.zeros(3))
        a.measure(x, k != 1)  # search, reuse the search at another pose, search again
        searches.append(a.n_searches)
        F, b = a.noise_terms(x)
        F0, b0 = normal_noise_terms(a.points_lidar, a.selected, x.R, x.p, x.R_LI, x.t_LI,
                                    a.normals, a.mu, a.neighbours, a.counts, a.row_weights,
                                    cfg.filter.laser_point_cov, True)
        np.testing.assert_array_equal(F, F0)
        np.testing.assert_array_equal(b, b0)
        assert np.any(F != 0.0)
    assert searches == [1, 1, 2]


def _room(cfg: Config, rng: np.random.Generator, n_per_face: int):
    """Map points on a floor (z = -1) and two walls (x = 2, y = 2), and scan points sampled on
    the same faces with 5 mm of noise; returns (ivox, scan, face of each scan point)."""
    g = np.arange(-1.5, 1.5, cfg.map.map_leaf_m) + 0.05
    a, b = (u.ravel() for u in np.meshgrid(g, g))
    faces = [np.column_stack([a, b, np.full(a.size, -1.0)]),
             np.column_stack([np.full(a.size, 2.0), a, b]),
             np.column_stack([a, np.full(a.size, 2.0), b])]
    ivox = IVox.from_config(cfg.map)
    ivox.add_points(np.vstack(faces))
    scan, face = [], []
    for k in range(3):
        u = rng.uniform(-1.2, 1.2, size=(n_per_face, 2))
        axis = (2, 0, 1)[k]  # the face's constant coordinate
        pts = np.insert(u, axis, (-1.0, 2.0, 2.0)[k], axis=1)
        pts[:, axis] += rng.normal(scale=0.005, size=n_per_face)
        scan.append(pts)
        face.append(np.full(n_per_face, k))
    return ivox, np.vstack(scan), np.concatenate(face)


def _update(cfg: Config, ivox: IVox, scan: np.ndarray, x_prior: State, sigma_p_m: float,
            kernel_cov_scale: float | None, kernel: str = "geman_mcclure") -> State:
    """The filter's iterated update of ``scan`` from ``x_prior`` with pose sigmas ``sigma_p_m``
    (m) and 0.5°; the kernel sees that covariance times ``kernel_cov_scale`` (None: no kernel)."""
    P = np.eye(DIM) * 1e-4
    P[:3, :3] = np.eye(3) * sigma_p_m**2
    P[3:6, 3:6] = np.eye(3) * np.radians(0.5) ** 2
    cfg.filter.robust_kernel = "none" if kernel_cov_scale is None else kernel
    cov = None if kernel_cov_scale is None else P[:6, :6] * kernel_cov_scale
    assoc = _Association(scan, ivox, cfg, 5.0, 0.1, cfg.map.map_leaf_m, None, cov)
    cfg.filter.max_iterations = 6
    return iterated_update(x_prior, P, assoc.measure, cfg.filter).state


def test_rows_off_their_plane_stop_pulling() -> None:
    """A fifth of the floor's points lie 8 cm above it (clutter). Least squares lifts the pose
    by their share of the floor's rows; the kernel keeps it at the true pose (the origin)."""
    cfg = Config()
    rng = np.random.default_rng(11)
    ivox, scan, face = _room(cfg, rng, 300)
    floor = np.flatnonzero(face == 0)
    scan[floor[: len(floor) // 5], 2] += 0.08
    x0 = State(R_LI=np.eye(3), t_LI=np.zeros(3))
    plain = _update(cfg, ivox, scan, x0, 0.01, None)
    gm = _update(cfg, ivox, scan, x0, 0.01, 1.0)
    huber = _update(cfg, ivox, scan, x0, 0.01, 1.0, "huber")
    print(f"height error: plain {plain.p[2] * 100:.2f} cm, Geman-McClure {gm.p[2] * 100:.2f} cm,"
          f" Huber {huber.p[2] * 100:.2f} cm")
    assert plain.p[2] < -0.01  # the pose drops by about 8 cm x 1/5 to lift the points
    assert abs(gm.p[2]) < 0.002
    assert np.linalg.norm(gm.p) < 0.003
    # Huber bounds each row's pull (kappa), it does not silence it
    assert abs(huber.p[2]) < 0.5 * abs(plain.p[2])


def test_a_known_uncertainty_keeps_the_rows_that_correct_it() -> None:
    """The prediction is 10 cm too high and its covariance says so (sigma 10 cm): the floor's rows
    are 10 cm off their plane, but within their spread, so they keep their height information
    and bring the pose back to the truth. Told the prediction is good to a millimetre, the
    kernel takes them for outliers and the scan keeps under 1 % of its height information: the
    spread term is what lets the filter correct its own drift."""
    cfg = Config()
    ivox, scan, _ = _room(cfg, np.random.default_rng(12), 300)
    x0 = State(p=np.array([0.0, 0.0, 0.10]), R_LI=np.eye(3), t_LI=np.zeros(3))
    sigma_m = 0.10
    P_pose = np.diag([sigma_m**2] * 3 + [np.radians(0.5) ** 2] * 3)

    def height_information(kernel: str, cov: np.ndarray | None) -> float:
        cfg.filter.robust_kernel = kernel
        a = _Association(scan, ivox, cfg, 5.0, 0.1, cfg.map.map_leaf_m, None, cov)
        H, _ = a.measure(x0, True)
        return float(H[:, 2] @ H[:, 2])

    plain = height_information("none", None)
    known = height_information("geman_mcclure", P_pose)
    told_1mm = height_information("geman_mcclure", P_pose * 1e-4)
    print(f"height information kept: {known / plain:.3f} with the spread, {told_1mm / plain:.5f}"
          " told 1 mm")
    assert known > 0.5 * plain
    assert told_1mm < 0.01 * plain
    x = _update(cfg, ivox, scan, x0, sigma_m, 1.0)
    assert abs(x.p[2]) < 0.003


def test_the_odometry_reweights_its_rows_and_tracks(tmp_path) -> None:
    """Wiring: with ``filter.robust_kernel`` (Huber by default in mode adaptive) the odometry's
    rows carry the kernel's weights: the information the scans report (``eig0..5`` of
    ``HᵀH/R``) drops, by less
    for Huber than for Geman-McClure, which silences the rows Huber only bounds; the trajectory
    follows the ground truth with each."""
    from adalio.config import load_config
    from adalio.eval.files import read_scans_csv
    from adalio.eval.metrics import ate
    from adalio.pipeline import run_bag
    from adalio.sim import cached_sequence

    sim = cached_sequence("corridor", seed=0, duration_s=4.0, columns=512)
    assert robust_kernel_name(load_config(None, sim.config_path)) == "huber"
    info, err = {}, {}
    for kernel in ("none", "huber", "geman_mcclure"):
        cfg = load_config(None, sim.config_path, overrides={"filter.robust_kernel": kernel})
        out = tmp_path / kernel
        run_bag(sim.bag_path, cfg, out, progress=False)
        scans = read_scans_csv(out / "scans.csv")
        info[kernel] = np.asarray(sum(scans[f"eig{k}"] for k in range(6)))
        err[kernel] = ate(out / "trajectory.tum", sim.gt_path, align="se3")["rmse_m"]
    kept = {}
    for kernel in ("huber", "geman_mcclure"):
        a, b = info[kernel], info["none"]
        assert a.shape == b.shape
        both = (a > 0) & (b > 0)
        assert np.count_nonzero(both) > 30
        kept[kernel] = float(np.median(a[both] / b[both]))
    print(f"information kept: Huber {kept['huber']:.2f}, Geman-McClure "
          f"{kept['geman_mcclure']:.2f}; ATE " + ", ".join(
              f"{k} {v * 100:.2f} cm" for k, v in err.items()))
    assert kept["geman_mcclure"] < kept["huber"] < 0.97
    assert kept["geman_mcclure"] > 0.5
    assert max(err.values()) < 0.05


def test_auto_is_huber_except_in_adaptive_plus() -> None:
    cfg = Config()
    assert cfg.filter.robust_kernel == "auto"
    for mode, name in (("fixed", "huber"), ("adaptive", "huber"), ("adaptive+", "none")):
        cfg.adaptive.mode = mode
        assert robust_kernel_name(cfg) == name
    cfg.filter.robust_kernel = "geman_mcclure"
    assert robust_kernel_name(cfg) == "geman_mcclure"  # an explicit choice holds in every mode
