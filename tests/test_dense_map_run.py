"""``map_dense.ply`` of a run (``output.dense_map_voxel_m``, on by default; ``adalio.lio.
dense_map``): on the corridor with four people walking by, it holds several times the points
of ``map.ply``, lies on the scene's surfaces as closely as ``map.ply`` does (the scene's mesh,
``adalio.eval.scene_map``), leaves out the points no map point is near (what later sweeps saw
through), and changes nothing else: without it the trajectory is the same to the byte, and a
run into the same folder removes the dense map an earlier run left."""

from __future__ import annotations

import filecmp

import numpy as np
from scipy.spatial import cKDTree

from adalio.config import load_config
from adalio.eval.files import read_map_points
from adalio.eval.scene_map import map_off_scene
from adalio.pipeline import run_bag
from adalio.sim import cached_sequence


def test_a_run_writes_a_dense_map_on_the_scene(tmp_path, summary_text):
    sim = cached_sequence("corridor", seed=0, duration_s=12.0, columns=512, people=4)
    cfg = load_config(config_file=sim.config_path)
    assert cfg.output.dense_map_voxel_m == 0.05
    res = run_bag(sim.bag_path, cfg, tmp_path / "dense", progress=False)
    assert res.dense_map_path == tmp_path / "dense" / "map_dense.ply"
    dense, coarse = read_map_points(res.dense_map_path), read_map_points(res.map_path)
    n_dense, left_out = res.dense_map_points
    assert n_dense == len(dense)
    # measured: 51702 points against map.ply's 17775; 663 left out (the walkers' trails;
    # 51711, 18657 and 654 before session 94 judged the backfill's and the waiting points)
    assert len(dense) > 2 * len(coarse), (len(dense), len(coarse))
    assert left_out > 0
    # each within a map cell of a point of the map written out (map.ply is that map through
    # output.map_voxel_m's filter, which moves a point by at most the voxel's diagonal)
    reach = cfg.map.map_leaf_m + np.sqrt(3) * cfg.output.map_voxel_m
    d, _ = cKDTree(coarse).query(dense)
    assert d.max() <= reach, d.max()
    # on the scene's surfaces: measured 0.33 % off, map.ply 0.36 % (0.35 / 0.38 % before)
    off_dense = map_off_scene(res.dense_map_path, res.trajectory_path, sim.gt_path,
                              sim.meta_path)
    off_coarse = map_off_scene(res.map_path, res.trajectory_path, sim.gt_path, sim.meta_path)
    print(f"dense {len(dense)} points, {left_out} left out, off scene {off_dense:.4f}; "
          f"map.ply {len(coarse)}, off scene {off_coarse:.4f}")
    assert off_dense < 0.01 and off_dense < off_coarse + 0.005, (off_dense, off_coarse)
    assert f"dense map: {len(dense)} points in map_dense.ply" in summary_text(res)

    off = load_config(config_file=sim.config_path, overrides={"output.dense_map_voxel_m": "0"})
    res_off = run_bag(sim.bag_path, off, tmp_path / "off", progress=False)
    assert res_off.dense_map_path is None
    assert not (tmp_path / "off" / "map_dense.ply").exists()
    assert filecmp.cmp(res.trajectory_path, res_off.trajectory_path, shallow=False)
    assert filecmp.cmp(res.map_path, res_off.map_path, shallow=False)
    assert "dense map" not in summary_text(res_off)
    # a run without it into the first run's folder leaves no dense map of that run behind
    run_bag(sim.bag_path, off, tmp_path / "dense", progress=False, max_scans=12)
    assert not (tmp_path / "dense" / "map_dense.ply").exists()
