"""The dense map (``adalio.lio.dense_map``, ``output.dense_map_voxel_m``): the first point of
each voxel, against a brute-force pass over the same points; and the cleaning at the end of a
run (``Odometry.dense_map_cloud``), against the distances measured point by point."""

from __future__ import annotations

import numpy as np
import pytest

from adalio.config import load_config
from adalio.errors import ConfigError
from adalio.lio import Odometry
from adalio.lio.dense_map import DenseMap


def _first_per_voxel(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Brute force: walk the points in order, keep each one whose voxel no earlier one took."""
    seen: set[tuple[int, int, int]] = set()
    out = []
    for p in points:
        if not np.all(np.isfinite(p)):
            continue
        key = tuple(int(k) for k in np.floor(p / voxel_m))
        if key not in seen:
            seen.add(key)
            out.append(p)
    return np.asarray(out, dtype=np.float32).reshape(-1, 3)


def test_the_dense_map_keeps_the_first_point_to_reach_each_voxel():
    rng = np.random.default_rng(3)
    voxel = 0.05
    # batches over a few metres either side of the origin, so that voxels repeat within a
    # batch and across batches, and the table grows past its first 1024 slots several times
    batches = [rng.uniform(-1.5, 1.5, size=(n, 3)) for n in (5, 3000, 1, 0, 20000, 7000)]
    batches[4][::97] = np.nan  # rows a scan cannot have, skipped
    batches[4][5::101, 1] = np.inf
    dense = DenseMap(voxel)
    stored = [dense.add(b) for b in batches]
    expect = _first_per_voxel(np.concatenate(batches), voxel)
    assert len(dense) == len(expect) == sum(stored)
    np.testing.assert_array_equal(dense.points().astype(np.float32), expect)
    # a batch of points all in held voxels stores nothing
    assert dense.add(expect[:500].astype(np.float64) + 1e-4 * voxel) <= 500
    assert dense.add(np.concatenate(batches)[:2000]) == 0


@pytest.mark.parametrize("value", [0.005, -0.05, float("nan")])
def test_a_dense_map_voxel_below_a_centimetre_is_refused(value):
    with pytest.raises(ConfigError, match="dense_map_voxel_m"):
        load_config("hilti2022", overrides={"output.dense_map_voxel_m": str(value)}).validate()
    with pytest.raises(ConfigError, match="dense_map_voxel_m"):
        DenseMap(value)


def test_no_dense_map_with_a_zero_voxel():
    odom = Odometry(load_config("hilti2022", overrides={"output.dense_map_voxel_m": "0"}))
    points, left_out = odom.dense_map_cloud(np.zeros((3, 3)))
    assert points.shape == (0, 3) and left_out == 0


def test_the_dense_map_written_keeps_the_points_near_the_map():
    cfg = load_config("hilti2022")
    odom = Odometry(cfg)
    rng = np.random.default_rng(5)
    scan = rng.uniform(-3.0, 3.0, size=(4000, 3))
    odom._dense.add(scan)  # what a run's scans would have laid down
    map_points = rng.uniform(-3.0, 3.0, size=(300, 3))
    kept, left_out = odom.dense_map_cloud(map_points)
    stored = odom._dense.points()
    # brute force: every pair's distance
    d = np.sqrt(((stored[:, None, :] - map_points[None, :, :]) ** 2).sum(axis=2)).min(axis=1)
    near = d < cfg.map.map_leaf_m
    assert 0 < near.sum() < len(stored)
    np.testing.assert_array_equal(kept, stored[near])
    assert left_out == int((~near).sum())
