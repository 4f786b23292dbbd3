"""Clean-up of extracted ultrasound bone points (``(N, 3)`` mm): DBSCAN-like cluster selection
(radius in mm), statistical outlier removal, then optional voxel or farthest-point downsampling.
"""

from __future__ import annotations

import logging

import numpy as np

from comreg_core.pointsets import farthest_point_indices
from comreg_core.surfaces.us_config import DenoiseConfig
from comreg_core.surfaces.us_points import NoBoneFoundError, USSurfacePoints

log = logging.getLogger(__name__)


def cluster_labels(points: np.ndarray, radius_mm: float, min_points: int = 5) -> np.ndarray:
    """DBSCAN labels ``(N,)`` (-1 = noise) of ``(N, 3)`` points: core points have at least
    ``min_points`` points (self included) within ``radius_mm``; core points closer than the
    radius share a cluster; other points join the cluster of their nearest core point within
    the radius. Clusters are numbered by decreasing size."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels
    tree = cKDTree(points)
    counts = tree.query_ball_point(points, radius_mm, return_length=True)
    core = np.flatnonzero(counts >= min_points)
    if len(core) == 0:
        return labels
    pairs = cKDTree(points[core]).query_pairs(radius_mm, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(core), len(core)))
    _, component = connected_components(graph, directed=False)
    labels[core] = component
    border = np.setdiff1d(np.arange(n), core)
    if len(border):
        d, nearest = cKDTree(points[core]).query(points[border], distance_upper_bound=radius_mm)
        hit = np.isfinite(d)
        labels[border[hit]] = component[nearest[hit]]
    sizes = np.bincount(labels[labels >= 0])
    rank = np.empty_like(sizes)
    rank[np.argsort(-sizes, kind="stable")] = np.arange(len(sizes))
    labels[labels >= 0] = rank[labels[labels >= 0]]
    return labels


def select_clusters(points: np.ndarray, radius_mm: float, min_points: int = 5,
                    min_fraction: float = 1.0) -> np.ndarray:
    """Boolean mask ``(N,)`` of the points in DBSCAN clusters holding at least ``min_fraction``
    of the largest cluster's points (1.0 = largest cluster only)."""
    labels = cluster_labels(points, radius_mm, min_points)
    if (labels < 0).all():
        return np.zeros(len(points), dtype=bool)
    sizes = np.bincount(labels[labels >= 0])
    kept = np.flatnonzero(sizes >= min_fraction * sizes.max())
    return np.isin(labels, kept)


def statistical_outliers(points: np.ndarray, k: int = 16, std_ratio: float = 2.5) -> np.ndarray:
    """Boolean mask ``(N,)`` of inliers: points whose mean distance to their ``k`` nearest
    neighbours is at most mean + ``std_ratio`` * std of that distance over all points (PCL's
    StatisticalOutlierRemoval)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    if len(points) <= k:
        return np.ones(len(points), dtype=bool)
    d, _ = cKDTree(points).query(points, k=k + 1)
    mean = d[:, 1:].mean(axis=1)
    return mean <= mean.mean() + std_ratio * mean.std()


def voxel_downsample(points: np.ndarray, voxel_mm: float) -> np.ndarray:
    """``(M, 3)`` centroids of the points in each occupied cubic voxel of edge ``voxel_mm``,
    in order of first occurrence."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return points.reshape(0, 3)
    keys = np.floor((points - points.min(axis=0)) / voxel_mm).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse)
    sums = np.stack([np.bincount(inverse, weights=points[:, i]) for i in range(3)], axis=1)
    order = np.argsort(first, kind="stable")
    return (sums / counts[:, None])[order]


def denoise_points(surface: USSurfacePoints, config: DenoiseConfig | None = None
                   ) -> USSurfacePoints:
    """Cluster selection, outlier removal, then downsampling of extracted points. Points merged
    by voxel downsampling get ``frame_index`` -1 and the mean score."""
    c = config or DenoiseConfig()
    out = surface
    if c.cluster_radius_mm > 0 and len(out.points):
        keep = select_clusters(out.points, c.cluster_radius_mm, c.cluster_min_points,
                               c.min_cluster_fraction)
        log.info("cluster selection (%.3g mm): kept %d of %d points", c.cluster_radius_mm,
                 int(keep.sum()), len(keep))
        out = out.subset(keep)
    if c.outlier_neighbors > 0 and len(out.points):
        keep = statistical_outliers(out.points, c.outlier_neighbors, c.outlier_std_ratio)
        log.info("outlier removal: kept %d of %d points", int(keep.sum()), len(keep))
        out = out.subset(keep)
    if c.downsample == "voxel" and len(out.points):
        frames_with_bone = out.frames_with_bone
        points = voxel_downsample(out.points, c.voxel_size_mm)
        score = np.full(len(points), float(out.score.mean()))
        out = USSurfacePoints(points, np.full(len(points), -1), score, out.frames_examined,
                              frames_with_bone, out.reference)
    if c.target_points > 0 and len(out.points) > c.target_points:
        merged = bool((out.frame_index < 0).any())
        frames_with_bone = out.frames_with_bone
        out = out.subset(farthest_point_indices(np.asarray(out.points, dtype=np.float64),
                                                c.target_points))
        if merged:
            out.frames_with_bone = frames_with_bone
    if len(out.points) == 0:
        raise NoBoneFoundError("Denoising removed every extracted bone point.",
                               "Loosen the denoise settings (cluster_radius_mm, "
                               "min_cluster_fraction, outlier_std_ratio) in the config.")
    return out
