"""voxel_downsample against a brute-force dictionary reference (lio-design.md §6.1)."""

from collections import defaultdict

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from adalio.errors import InputError
from adalio.lio.voxel import voxel_downsample, voxel_downsample_with_index


def reference_downsample(points: np.ndarray, leaf_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Python dict of floor(p / leaf) -> points; returns (sorted keys, centroids)."""
    groups: dict[tuple[int, int, int], list[np.ndarray]] = defaultdict(list)
    for p in points:
        if not np.all(np.isfinite(p)):
            continue
        key = tuple(int(np.floor(c / leaf_m)) for c in p)
        groups[key].append(p)
    keys = sorted(groups)
    centroids = np.array([np.mean(groups[k], axis=0) for k in keys]).reshape(-1, 3)
    return np.array(keys, dtype=np.int64).reshape(-1, 3), centroids


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("leaf_m", [0.1, 0.25, 0.7, 3.0])
def test_matches_reference_on_random_clouds(seed: int, leaf_m: float) -> None:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-6.0, 4.0, size=(3000, 3))
    points[:, 2] *= 0.3
    _, expected = reference_downsample(points, leaf_m)
    got = voxel_downsample(points, leaf_m)
    assert got.dtype == np.float64
    assert got.shape == expected.shape
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(
    points=arrays(
        np.float64,
        st.tuples(st.integers(0, 60), st.just(3)),
        elements=st.floats(-50.0, 50.0, allow_nan=False, width=64),
    ),
    leaf_m=st.floats(0.05, 5.0),
)
def test_matches_reference_property(points: np.ndarray, leaf_m: float) -> None:
    _, expected = reference_downsample(points, leaf_m)
    centroids, idx = voxel_downsample_with_index(points, leaf_m)
    np.testing.assert_allclose(centroids, expected, rtol=1e-12, atol=1e-12)
    keys = np.floor(points / leaf_m).astype(np.int64)
    for j in range(len(centroids)):
        assert len(np.unique(keys[idx == j], axis=0)) == 1


def test_output_order_independent_of_input_order() -> None:
    rng = np.random.default_rng(5)
    points = rng.normal(scale=3.0, size=(5000, 3))
    a = voxel_downsample(points, 0.5)
    b = voxel_downsample(points[rng.permutation(len(points))], 0.5)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    keys = np.floor(voxel_downsample(points, 0.5) / 0.5)
    assert np.all(np.diff(keys @ np.array([1e12, 1e6, 1.0])) > 0)


def test_points_on_voxel_boundaries_and_negative_coordinates() -> None:
    leaf = 0.25
    points = np.array(
        [
            [0.0, 0.0, 0.0],
            [0.2499, 0.0, 0.0],
            [0.25, 0.0, 0.0],
            [-1e-12, 0.0, 0.0],
            [-0.25, 0.0, 0.0],
            [-0.25 - 1e-12, 0.0, 0.0],
            [0.5, -0.5, -0.75],
        ]
    )
    got = voxel_downsample(points, leaf)
    expected = np.array(
        [
            [(-0.25 - 1e-12), 0.0, 0.0],
            [(-1e-12 - 0.25) / 2.0, 0.0, 0.0],
            [0.2499 / 2.0, 0.0, 0.0],
            [0.25, 0.0, 0.0],
            [0.5, -0.5, -0.75],
        ]
    )
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-15)


def test_index_per_point_and_nonfinite_points() -> None:
    rng = np.random.default_rng(3)
    points = rng.uniform(-2, 2, size=(800, 3))
    points[10] = np.nan
    points[20, 1] = np.inf
    centroids, idx = voxel_downsample_with_index(points, 0.4)
    assert idx[10] == -1 and idx[20] == -1
    assert np.all(idx[np.isfinite(points).all(axis=1)] >= 0)
    for j in range(len(centroids)):
        np.testing.assert_allclose(points[idx == j].mean(axis=0), centroids[j], atol=1e-12)
    _, expected = reference_downsample(points, 0.4)
    np.testing.assert_allclose(centroids, expected, atol=1e-12)


def test_wide_key_span_uses_fallback_order() -> None:
    rng = np.random.default_rng(4)
    points = rng.uniform(-1e6, 1e6, size=(200, 3))
    points = np.vstack([points, points[:50] + 1e-3])
    _, expected = reference_downsample(points, 0.01)
    np.testing.assert_allclose(voxel_downsample(points, 0.01), expected, rtol=1e-15, atol=0)


def test_empty_and_bad_input() -> None:
    assert voxel_downsample(np.empty((0, 3)), 0.2).shape == (0, 3)
    with pytest.raises(InputError):
        voxel_downsample(np.zeros((4, 2)), 0.2)
    with pytest.raises(InputError):
        voxel_downsample(np.zeros((4, 3)), 0.0)
    with pytest.raises(InputError):
        voxel_downsample(np.zeros((4, 3)), float("nan"))
