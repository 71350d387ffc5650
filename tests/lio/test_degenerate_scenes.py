"""End-to-end: the estimator on the simulator's degenerate corridor against its ground truth.

The corridor is feature-poor along its axis; before the one-point-per-cell map rule and the
plane-extent test, clustered map cells gave plane fits with arbitrary normals that held the
estimate against the IMU (ATE of metres). Data: ``adalio.sim.cached_sequence`` (generated once
into ``$ADALIO_CACHE_DIR``, the repo's ``.cache`` under pytest).
"""

from pathlib import Path

import numpy as np
import pytest

from adalio.config import Config, load_config
from adalio.eval.metrics import ate
from adalio.lio import odometry
from adalio.lio.ivox import IVox
from adalio.lio.state import State
from adalio.pipeline import run_bag
from adalio.sim import cached_sequence

MAX_ATE_M = 0.1


@pytest.mark.slow
def test_corridor_adaptive_tracks_ground_truth(tmp_path: Path) -> None:
    sim = cached_sequence("corridor", seed=0, duration_s=20, columns=2000)
    cfg = load_config(config_file=sim.config_path, overrides={"adaptive.mode": "adaptive"})
    res = run_bag(sim.bag_path, cfg, tmp_path / "run", progress=False)
    assert not res.interrupted
    assert res.n_scans >= 150
    err = ate(res.trajectory_path, sim.gt_path, align="se3")
    print(f"corridor 20 s adaptive: ATE {err['rmse_m'] * 100:.2f} cm over {err['n']} poses")
    assert err["n"] >= 0.9 * res.n_scans
    assert err["rmse_m"] < MAX_ATE_M


def test_residuals_sharing_a_map_point_count_once() -> None:
    """Duplicating every scan point (same nearest map point) must not add information: with the
    share weighting, HᵀH of the doubled scan equals that of the single scan, while the
    unweighted sum would double it (truth: the explicit single-scan H)."""
    rng = np.random.default_rng(5)
    cfg = Config()
    g = np.arange(-1.5, 1.5, cfg.map.map_leaf_m) + 0.05
    gx, gy = np.meshgrid(g, g)
    floor = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, -1.0)])
    wall = np.column_stack([np.full(gx.size, 2.0), gx.ravel(), gy.ravel()])
    ivox = IVox.from_config(cfg.map)
    ivox.add_points(np.vstack([floor, wall]))
    scan = np.vstack([floor[::3], wall[::3]])
    scan += rng.normal(scale=0.02, size=scan.shape)
    x = State(R_LI=np.eye(3), t_LI=np.zeros(3))

    def info(points: np.ndarray) -> np.ndarray:
        a = odometry._Association(points, ivox, cfg, 5.0, 0.1, cfg.map.map_leaf_m)
        H, _ = a.measure(x, True)
        assert H.shape[0] > 0.8 * points.shape[0]
        return H[:, :6].T @ H[:, :6]

    single = info(scan)
    doubled = info(np.vstack([scan, scan]))
    np.testing.assert_allclose(doubled, single, rtol=1e-9, atol=1e-9)
    cfg.filter.share_weighting = False
    np.testing.assert_allclose(info(np.vstack([scan, scan])), 2 * info(scan), rtol=1e-9)


@pytest.mark.slow
def test_corridor_adaptive_plus_holds_the_axis_only_if_told(tmp_path: Path) -> None:
    """adaptive+ in the corridor. With ``adaptive.hold_horizontal`` (the rule before session 30)
    the direction it leaves to the IMU is the corridor axis (the walking direction of the ground
    truth), and the run reports those scans. By default it does not hold a mostly horizontal
    translation, so it holds on fewer scans (measured: 6 against 89 of 200), as accurately.
    Which scans the old rule holds is fragile (its weakest direction's information sits near
    the threshold along this corridor): since session 77 (the sample after each scan's end in
    the propagation) it holds 89 with the zero-velocity update and 4 without it, where before
    it held 4 and 16; so the rules are compared with the default update."""
    sim = cached_sequence("corridor", seed=0, duration_s=20, columns=2000)
    held_scans = {}
    for hold_horizontal in (True, False):
        cfg = load_config(config_file=sim.config_path,
                          overrides={"adaptive.mode": "adaptive+",
                                     "adaptive.hold_horizontal": hold_horizontal})
        res = run_bag(sim.bag_path, cfg, tmp_path / f"run_{hold_horizontal}", progress=False)
        err = ate(res.trajectory_path, sim.gt_path, align="se3")
        assert err["rmse_m"] < MAX_ATE_M
        rows = np.genfromtxt(res.scans_csv_path, delimiter=",", names=True)
        held = rows["held_dirs"] > 0
        assert res.n_held == int(held.sum())
        held_scans[hold_horizontal] = res.n_held
        if not hold_horizontal:
            continue
        assert res.n_held >= 5
        assert res.held_ranges_s and res.held_ranges_s[0][0] <= res.held_ranges_s[-1][1]
        est = np.loadtxt(res.trajectory_path, comments="#")
        axis = est[-1, 1:4] - est[0, 1:4]
        axis /= np.linalg.norm(axis)
        weak_t = np.column_stack([rows["weak_tx"], rows["weak_ty"], rows["weak_tz"]])[held]
        weak_t /= np.maximum(np.linalg.norm(weak_t, axis=1, keepdims=True), 1e-12)
        along = np.abs(weak_t @ axis)
        print(f"held scans {res.n_held}; |cos(weakest, axis)| median {np.median(along):.2f}")
        assert np.median(along) > 0.8
    assert held_scans[False] < held_scans[True], held_scans
