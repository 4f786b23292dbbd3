"""Denoising steps of extracted ultrasound points against naive implementations, and the
pipeline's frame bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.surfaces.us_config import DenoiseConfig
from comreg_core.surfaces.us_denoise import (cluster_labels, denoise_points, select_clusters,
                                             statistical_outliers, voxel_downsample)
from comreg_core.surfaces.us_points import NoBoneFoundError, USSurfacePoints
from tests.helpers import assert_close


def naive_dbscan(points, radius, min_points):
    n = len(points)
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    core = (d <= radius).sum(axis=1) >= min_points
    labels = -np.ones(n, dtype=int)
    current = 0
    for i in range(n):
        if not core[i] or labels[i] >= 0:
            continue
        stack, labels[i] = [i], current
        while stack:
            j = stack.pop()
            for k in np.flatnonzero((d[j] <= radius) & core & (labels < 0)):
                labels[k] = current
                stack.append(k)
        current += 1
    for i in np.flatnonzero(~core):
        near = np.flatnonzero(core & (d[i] <= radius))
        if len(near):
            labels[i] = labels[near[np.argmin(d[i, near])]]
    return labels


def test_dbscan_clusters_match_naive():
    rng = np.random.default_rng(6)
    points = np.concatenate([rng.normal(0, 1, (150, 3)), rng.normal(10, 1, (80, 3)),
                             rng.uniform(-20, 30, (20, 3))])
    ours = cluster_labels(points, 1.2, 5)
    naive = naive_dbscan(points, 1.2, 5)
    assert np.array_equal(ours < 0, naive < 0)
    for label in np.unique(naive[naive >= 0]):  # same partition, whatever the numbering
        assert len(np.unique(ours[naive == label])) == 1
    sizes = np.bincount(ours[ours >= 0])
    assert np.all(np.diff(sizes) <= 0)  # numbered by decreasing size
    largest = select_clusters(points, 1.2, 5)
    assert np.array_equal(largest, ours == 0)
    both = select_clusters(points, 1.2, 5, min_fraction=0.3)
    assert np.array_equal(both, np.isin(ours, np.flatnonzero(sizes >= 0.3 * sizes[0])))


def test_dbscan_labels_are_exactly_the_naive_ones_numbered_by_size():
    """The compiled grid kernel against the naive DBSCAN, label for label: clusters numbered by
    decreasing size, ties by their lowest point index; neighbours at exactly the radius count
    (points on an integer grid, radius 1: exact distances); duplicates; clouds far from 0."""
    rng = np.random.default_rng(11)
    problems = [(np.argwhere(np.ones((4, 3, 3))).astype(float) * [1, 1, 1], 1.0, 3),
                (np.argwhere(rng.random((6, 6, 2)) < 0.5).astype(float), 1.0, 2),
                (np.repeat(rng.normal(size=(20, 3)), 3, axis=0), 0.3, 4)]
    for _ in range(60):
        n = int(rng.integers(1, 200))
        centres = rng.normal(scale=15.0, size=(int(rng.integers(1, 5)), 3)) + rng.normal(
            scale=500.0, size=3)
        points = centres[rng.integers(0, len(centres), n)] + rng.normal(
            scale=rng.uniform(0.3, 3.0), size=(n, 3))
        problems.append((points, float(rng.uniform(0.5, 4.0)), int(rng.integers(1, 8))))
    for points, radius, min_points in problems:
        naive = naive_dbscan(points, radius, min_points)
        expected = naive.copy()
        if (naive >= 0).any():
            sizes = np.bincount(naive[naive >= 0])
            rank = np.empty_like(sizes)
            rank[np.argsort(-sizes, kind="stable")] = np.arange(len(sizes))
            expected[naive >= 0] = rank[naive[naive >= 0]]
        assert np.array_equal(cluster_labels(points, radius, min_points), expected)
    assert np.array_equal(cluster_labels(np.zeros((0, 3)), 1.0), np.zeros(0, dtype=int))


def test_statistical_outliers_match_naive():
    rng = np.random.default_rng(7)
    points = np.concatenate([rng.normal(0, 1, (300, 3)), [[8, 8, 8], [-9, 0, 9]]])
    d = np.sort(np.linalg.norm(points[:, None] - points[None], axis=2), axis=1)[:, 1:9]
    mean = d.mean(axis=1)
    naive = mean <= mean.mean() + 2.0 * mean.std()
    assert np.array_equal(statistical_outliers(points, 8, 2.0), naive)
    assert not naive[-2:].any()


def test_voxel_downsampling_matches_naive():
    rng = np.random.default_rng(8)
    points = rng.uniform(0, 10, (2000, 3))
    cells: dict = {}
    for p in points:
        cells.setdefault(tuple(np.floor((p - points.min(axis=0)) / 2.0).astype(int)), []).append(p)
    naive = np.array([np.mean(v, axis=0) for v in cells.values()])  # first-occurrence order
    assert_close(voxel_downsample(points, 2.0), naive, atol=1e-12)


def test_denoise_pipeline_keeps_frames_and_counts():
    rng = np.random.default_rng(9)
    points = np.concatenate([rng.normal(0, 2, (500, 3)), rng.uniform(40, 60, (5, 3))])
    surface = USSurfacePoints(points, np.repeat(np.arange(101), 5), np.ones(505), 101, 101)
    out = denoise_points(surface)
    assert len(out.points) < 505 and out.frame_index.max() < 100  # the far points are gone
    voxel = denoise_points(surface, DenoiseConfig(downsample="voxel", voxel_size_mm=2.0))
    assert np.all(voxel.frame_index == -1) and voxel.frames_with_bone == out.frames_with_bone
    fps = denoise_points(surface, DenoiseConfig(downsample="fps", target_points=50))
    assert len(fps.points) == 50
    with pytest.raises(NoBoneFoundError, match="Denoising removed"):
        denoise_points(USSurfacePoints(rng.uniform(0, 1000, (20, 3)), np.arange(20),
                                       np.ones(20), 20, 20))
