"""Clean-up of extracted ultrasound bone points (``(N, 3)`` mm): DBSCAN-like cluster selection
(radius in mm), statistical outlier removal, then optional voxel or farthest-point downsampling.
"""

from __future__ import annotations

import logging

import numpy as np
from numba import njit

from comreg_core.errors import InvalidGeometryError
from comreg_core.pointsets import farthest_point_indices
from comreg_core.surfaces.us_config import DenoiseConfig
from comreg_core.surfaces.us_points import NoBoneFoundError, USSurfacePoints

log = logging.getLogger(__name__)


def cluster_labels(points: np.ndarray, radius_mm: float, min_points: int = 5) -> np.ndarray:
    """DBSCAN labels ``(N,)`` (-1 = noise) of ``(N, 3)`` points: core points have at least
    ``min_points`` points (self included) within ``radius_mm``; core points closer than the
    radius share a cluster; other points join the cluster of their nearest core point within
    the radius. Clusters are numbered by decreasing size (ties: the cluster of the lowest point
    index first). The neighbour counts and the core clusters come from a compiled grid kernel
    (:func:`_core_clusters`, ~5x scipy's KD-tree pairs and graph)."""
    from scipy.spatial import cKDTree

    points = np.ascontiguousarray(points, dtype=np.float64)
    n = len(points)
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels
    cells = np.floor((points - points.min(axis=0)) / radius_mm).astype(np.int64)
    shape = cells.max(axis=0) + 3  # a margin of one empty cell on each side
    if float(np.prod(shape.astype(np.float64))) > 2.0 ** 62:
        raise InvalidGeometryError(f"A cluster radius of {radius_mm:g} mm is too small for a "
                                   f"cloud {np.ptp(points, axis=0).max():.0f} mm wide.",
                                   "Check the points' units (mm) and denoise.cluster_radius_mm.")
    keys = ((cells[:, 0] + 1) * shape[1] + cells[:, 1] + 1) * shape[2] + cells[:, 2] + 1
    order = np.argsort(keys, kind="stable")
    is_core, component = _core_clusters(points, order, keys[order], shape, float(radius_mm),
                                        int(min_points))
    core = np.flatnonzero(is_core)
    if len(core) == 0:
        return labels
    labels[core] = component[core]
    border = np.flatnonzero(~is_core)
    if len(border):
        d, nearest = cKDTree(points[core]).query(points[border], distance_upper_bound=radius_mm)
        hit = np.isfinite(d)
        labels[border[hit]] = component[core[nearest[hit]]]
    sizes = np.bincount(labels[labels >= 0])
    rank = np.empty_like(sizes)
    rank[np.argsort(-sizes, kind="stable")] = np.arange(len(sizes))
    labels[labels >= 0] = rank[labels[labels >= 0]]
    return labels


@njit(cache=True)
def _core_clusters(points, order, sorted_keys, shape, radius, min_points):
    """DBSCAN's core points and their clusters on a grid of ``radius`` cells: ``order`` the
    points sorted by their cell, ``sorted_keys`` ``(N,)`` those cells (row-major in ``shape``,
    no point in the outer cells). Returns ``(is_core (N,) bool, component (N,))``:
    core points within ``radius`` (inclusive) of each other share a component, numbered in
    the order of their lowest point index (as scipy's ``connected_components``); -1 elsewhere."""
    n = len(points)
    r2 = radius * radius
    sorted_points = points[order]
    counts = np.zeros(n, np.int64)
    parent = np.arange(n)
    lo = np.empty(9, np.int64)
    hi = np.empty(9, np.int64)
    for phase in range(2):  # 0: count the neighbours; 1: join core neighbours
        first = 0
        while first < n:  # the points of one cell: sorted positions first..last-1
            last = first
            while last < n and sorted_keys[last] == sorted_keys[first]:
                last += 1
            k = 0
            for a in range(-1, 2):  # the 27 cells around it: 9 runs of 3 consecutive keys
                for b in range(-1, 2):
                    centre = sorted_keys[first] + (a * shape[1] + b) * shape[2]
                    lo[k] = np.searchsorted(sorted_keys, centre - 1)
                    hi[k] = np.searchsorted(sorted_keys, centre + 1, side="right")
                    k += 1
            for m in range(first, last):
                i = order[m]
                if phase == 1 and counts[i] < min_points:
                    continue
                x, y, z = sorted_points[m, 0], sorted_points[m, 1], sorted_points[m, 2]
                for k in range(9):
                    for q in range(lo[k], hi[k]):
                        dx = x - sorted_points[q, 0]
                        dy = y - sorted_points[q, 1]
                        dz = z - sorted_points[q, 2]
                        if dx * dx + dy * dy + dz * dz > r2:
                            continue
                        if phase == 0:
                            counts[i] += 1
                            continue
                        j = order[q]
                        if j > i and counts[j] >= min_points:
                            ri, rj = find_root(parent, i), find_root(parent, j)
                            if ri != rj:  # the root: the lowest index of its tree
                                parent[max(ri, rj)] = min(ri, rj)
            first = last
    is_core = counts >= min_points
    component = np.full(n, -1, np.int64)
    next_label = 0
    for i in range(n):
        if is_core[i]:
            root = find_root(parent, i)
            if component[root] < 0:
                component[root] = next_label
                next_label += 1
            component[i] = component[root]
    return is_core, component


@njit(cache=True)
def find_root(parent, i):
    """The root of ``i`` in the union-find forest ``parent``, halving the path on the way."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


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
