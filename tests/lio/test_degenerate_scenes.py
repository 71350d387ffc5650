"""End-to-end: the estimator on the simulator's degenerate corridor against its ground truth.

The corridor is feature-poor along its axis; before the one-point-per-cell map rule and the
plane-extent test, clustered map cells gave plane fits with arbitrary normals that held the
estimate against the IMU (ATE of metres). Data: ``adalio.sim.cached_sequence`` (generated once
into ``$ADALIO_CACHE_DIR``, the repo's ``.cache`` under pytest).
"""

from pathlib import Path

import pytest

from adalio.config import load_config
from adalio.eval.metrics import ate
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
