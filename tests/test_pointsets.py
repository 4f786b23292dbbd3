"""Farthest point sampling (comreg_core.pointsets): against a naive numpy FPS, and bit for bit
against what its two callers ran before it existed (model/ops.py's fpsample call on float32
points, surfaces/us.py's on float64 points)."""

from __future__ import annotations

import math

import fpsample
import numpy as np
import pytest

from comreg_core import pointsets
from comreg_core.pointsets import farthest_point_indices, fps_bucket_height


def naive_fps(points: np.ndarray, n: int, start: int) -> list[int]:
    """Exact farthest point sampling from ``start``: each next point is the farthest from all
    chosen so far (squared distances in float64)."""
    points = np.asarray(points, dtype=np.float64)
    chosen = [start]
    dist = np.sum((points - points[start]) ** 2, axis=1)
    for _ in range(n - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.sum((points - points[chosen[-1]]) ** 2, axis=1))
    return chosen


def previous_fpsample_call(points: np.ndarray, n: int, start: int) -> np.ndarray:
    """The call both callers made before: their bucket height formula, fpsample on the array
    as given."""
    N = len(points)
    h = int(min(9, max(1, round(math.log2(N)) - 5)))
    while 2 ** h > N:
        h -= 1
    return np.asarray(fpsample.bucket_fps_kdline_sampling(points, n, h, start_idx=start),
                      dtype=np.int64)


def test_exact_fps_from_its_first_sample():
    points = np.random.default_rng(8).uniform(0, 10, (2000, 3))
    chosen = farthest_point_indices(points, 64)
    assert chosen.dtype == np.int64 and chosen.shape == (64,)
    assert list(chosen) == naive_fps(points, 64, int(chosen[0]))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("n_points,n,start", [(3000, 200, 0), (257, 64, 5), (2, 1, 1),
                                              (40_000, 512, 123)])
def test_bit_identical_to_the_previous_calls_in_the_callers_dtype(dtype, n_points, n, start):
    points = np.random.default_rng(n_points).normal(size=(n_points, 3)).astype(dtype)
    chosen = farthest_point_indices(points, n, start)
    np.testing.assert_array_equal(chosen, previous_fpsample_call(points, n, start))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_fpsample_gets_the_points_in_the_callers_type(dtype, monkeypatch):
    seen, original = [], fpsample.bucket_fps_kdline_sampling

    def spy(points, *args, **kwargs):
        seen.append(points.dtype)
        return original(points, *args, **kwargs)

    monkeypatch.setattr(pointsets.fpsample, "bucket_fps_kdline_sampling", spy)
    farthest_point_indices(np.random.default_rng(1).normal(size=(100, 3)).astype(dtype), 10)
    assert seen == [np.dtype(dtype)]


def test_all_points_when_asking_for_as_many_or_more():
    points = np.zeros((5, 3))
    np.testing.assert_array_equal(farthest_point_indices(points, 5), np.arange(5))
    np.testing.assert_array_equal(farthest_point_indices(points, 9), np.arange(5))


def test_numpy_loop_without_fpsample_starts_at_start(monkeypatch):
    monkeypatch.setattr(pointsets, "fpsample", None)
    points = np.random.default_rng(3).uniform(0, 10, (500, 3))
    chosen = farthest_point_indices(points, 40, start=17)
    assert chosen.dtype == np.int64
    assert list(chosen) == naive_fps(points, 40, 17)
    integers = np.random.default_rng(4).integers(0, 1000, (300, 3))  # read as float64
    assert list(farthest_point_indices(integers, 20, start=2)) == naive_fps(integers, 20, 2)


@pytest.mark.parametrize("n_points,height", [(2, 1), (3, 1), (257, 3), (3000, 7), (10 ** 6, 9)])
def test_bucket_height(n_points, height):
    assert fps_bucket_height(n_points) == height
