"""The clean-up of :func:`~comreg_core.surfaces.us_denoise.denoise_points` kept up to date while
a sweep grows (:class:`IncrementalDenoise`): each call clusters only the new points against
those kept so far, and gives the same points as the full clean-up of all of them.

Why it is the same:

- **Cluster selection** (DBSCAN, radius ``r``, ``min_points``). Adding points only raises
  neighbour counts, so core points stay core; only points within ``r`` of a new point change
  their count, and only core pairs with a newly core point are new edges; all of them lie
  within ``2 r`` of the new points' bounding box. The clusters are a union-find over the core
  points (the same partition, whatever the order the edges come in); a border point joins the
  cluster of its nearest core point within ``r``, and a nearer core point can only be a newly
  core one. Cluster sizes and the selection (at least ``min_cluster_fraction`` of the largest)
  are recounted each call over all points: ``O(N)`` array passes.
- **Statistical outlier removal** (``k`` neighbours). Each selected point keeps its ``k``
  nearest distances among the selected points. A point's list changes only when a point
  closer than its ``k``-th neighbour comes (merged in) or one of its neighbours leaves the
  selection (its list found again); new points find theirs in a box grown until it holds
  them. The mean and spread over all points and the threshold are recomputed each call, in
  frame order, with the same numpy expressions as the full clean-up: the same bits.

Pair tests use the full clean-up's arithmetic (``dx*dx + dy*dy + dz*dz <= r*r`` for the
neighbour counts, strictly below ``r`` for a border's core, scipy's ``cKDTree`` distances for
the ``k`` neighbours). Down-sampling, when configured, runs on the kept points as the full
clean-up runs it. Points: ``(N, 3)`` mm.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from comreg_core.surfaces.us_config import DenoiseConfig
from comreg_core.surfaces.us_denoise import denoise_points, find_root
from comreg_core.surfaces.us_points import NoBoneFoundError, USSurfacePoints


class IncrementalDenoise:
    """:func:`denoise_points` of a growing point set, updated by the points added (module
    docstring). :meth:`add` the points of one or more frames (any frame order); :meth:`cloud`
    gives what ``denoise_points`` gives for all points so far, in frame order."""

    def __init__(self, config: DenoiseConfig | None = None):
        self.config = config or DenoiseConfig()
        self.points = np.zeros((0, 3))
        self.frames = np.zeros(0, np.int64)
        self.scores = np.zeros(0)
        self._order = np.zeros(0, np.int64)  # insertion index -> frame order
        self._counts = np.zeros(0, np.int64)
        self._parent = np.zeros(0, np.int64)
        self._nearest = np.zeros(0, np.int64)  # a border point's nearest core point, or -1
        self._nearest_d2 = np.zeros(0)
        k = max(self.config.outlier_neighbors, 1)
        self._knn = np.zeros((0, k))  # the k nearest distances among the selected points
        self._selected = np.zeros(0, bool)  # the selection the k lists were made for
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def add(self, points: np.ndarray, frames: np.ndarray, scores: np.ndarray) -> None:
        """Points ``(M, 3)`` of new frames, their frame indices ``(M,)`` (each frame's points
        added in one call, frames not seen before) and scores ``(M,)``."""
        if len(points):
            self._pending.append((np.asarray(points, np.float64).reshape(-1, 3),
                                  np.asarray(frames, np.int64).reshape(-1),
                                  np.asarray(scores, np.float64).reshape(-1)))

    def cloud(self, frames_examined: int, frames_with_bone: int,
              reference: str = "Reference") -> USSurfacePoints:
        """``denoise_points`` of all points so far (frame order); raises
        :class:`NoBoneFoundError` when it keeps none, as ``denoise_points`` does."""
        if self._pending:
            points, frames, scores = (np.concatenate(part) for part in zip(*self._pending))
            self._pending = []
            self._insert(points, frames, scores)
        order = self._order
        raw = USSurfacePoints(self.points[order], self.frames[order], self.scores[order],
                              frames_examined, frames_with_bone, reference)
        c = self.config
        keep = np.ones(len(order), bool)
        if c.cluster_radius_mm > 0 and len(order):
            keep = self._clusters()[order]
        if c.outlier_neighbors > 0 and keep.any():
            keep[np.flatnonzero(keep)] = self._inliers(order[keep])
        out = raw.subset(keep)
        if len(out.points) == 0:
            raise NoBoneFoundError("Denoising removed every extracted bone point.",
                                   "Loosen the denoise settings (cluster_radius_mm, "
                                   "min_cluster_fraction, outlier_std_ratio) in the config.")
        if c.downsample != "none" or c.target_points > 0:
            out = denoise_points(out, replace(c, cluster_radius_mm=0.0, outlier_neighbors=0))
        return out

    # -- cluster selection --------------------------------------------------------------------

    def _insert(self, points: np.ndarray, frames: np.ndarray, scores: np.ndarray) -> None:
        n0, m = len(self.points), len(points)
        appended = n0 == 0 or frames.min() > self.frames.max()
        self.points = np.concatenate([self.points, points])
        self.frames = np.concatenate([self.frames, frames])
        self.scores = np.concatenate([self.scores, scores])
        if appended and (np.diff(frames) >= 0).all():
            self._order = np.concatenate([self._order, n0 + np.arange(m)])
        else:
            self._order = np.argsort(self.frames, kind="stable")
        self._knn = np.concatenate([self._knn, np.full((m, self._knn.shape[1]), np.inf)])
        self._selected = np.concatenate([self._selected, np.zeros(m, bool)])
        self._nearest = np.concatenate([self._nearest, np.full(m, -1, np.int64)])
        self._nearest_d2 = np.concatenate([self._nearest_d2, np.full(m, np.inf)])
        self._parent = np.concatenate([self._parent, n0 + np.arange(m)])
        c = self.config
        if c.cluster_radius_mm > 0:
            core_before = np.concatenate([self._counts >= c.cluster_min_points,
                                          np.zeros(m, bool)])
            self._counts = np.concatenate([self._counts, np.ones(m, np.int64)])
            self._link(n0, core_before)

    def _link(self, n0: int, core_before: np.ndarray) -> None:
        """Neighbour counts, new cluster edges and borders' nearest core points for the points
        from ``n0`` on (module docstring). Only two kinds of pairs within ``r`` can change
        anything: those with a new point, and those with an old point that has just become
        core; both lie within ``2 r`` of the new points' bounding box."""
        r = float(self.config.cluster_radius_mm)
        new = self.points[n0:]
        lo, hi = new.min(axis=0) - 2.0 * r, new.max(axis=0) + 2.0 * r
        local = np.flatnonzero(((self.points >= lo) & (self.points <= hi)).all(axis=1))
        tree = cKDTree(self.points[local])
        i, j, d2 = self._pairs_with(np.arange(n0, len(self.points)), local, tree, r)
        np.add.at(self._counts, i, 1)
        np.add.at(self._counts, j, 1)
        core = self._counts >= self.config.cluster_min_points
        newly = core & ~core_before
        old_newly = np.flatnonzero(newly[:n0])
        if len(old_newly):  # their pairs with old points (those with new ones are counted)
            a, b, ab2 = self._pairs_with(old_newly, local[local < n0], None, r)
            i, j, d2 = np.concatenate([i, a]), np.concatenate([j, b]), np.concatenate([d2, ab2])
        edges = core[i] & core[j] & (newly[i] | newly[j])
        _union(self._parent, i[edges], j[edges])
        self._nearest[newly] = -1
        self._nearest_d2[newly] = np.inf
        border_a = np.concatenate([i, j])  # each pair both ways: (border, core)
        core_b = np.concatenate([j, i])
        dist2 = np.concatenate([d2, d2])
        use = ~core[border_a] & core[core_b] & (dist2 < r * r)
        border_a, core_b, dist2 = border_a[use], core_b[use], dist2[use]
        first = np.lexsort((core_b, dist2, border_a))  # per border: nearest first
        border_a, core_b, dist2 = border_a[first], core_b[first], dist2[first]
        lead = np.concatenate([[True], border_a[1:] != border_a[:-1]]) if len(first) else \
            np.zeros(0, bool)
        border_a, core_b, dist2 = border_a[lead], core_b[lead], dist2[lead]
        closer = dist2 < self._nearest_d2[border_a]
        self._nearest[border_a[closer]] = core_b[closer]
        self._nearest_d2[border_a[closer]] = dist2[closer]

    def _pairs_with(self, queries: np.ndarray, others: np.ndarray, tree, r: float):
        """``(i, j, d2)``, ``i < j``: each pair within ``r`` (``d2 <= r * r``, the full clean-up's
        arithmetic) of one of the points ``queries`` and one of ``others`` (insertion indices,
        ascending; ``tree``: the ``cKDTree`` of ``others``' points, or None), once."""
        if tree is None:
            tree = cKDTree(self.points[others])
        found = cKDTree(self.points[queries]).sparse_distance_matrix(
            tree, r * (1.0 + 1e-9), output_type="ndarray")
        a, b = queries[found["i"]], others[found["j"]]
        in_queries = np.isin(b, queries)
        once = (a != b) & (~in_queries | (a < b))
        i, j = np.minimum(a[once], b[once]), np.maximum(a[once], b[once])
        d = self.points[i] - self.points[j]
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        within = d2 <= r * r
        return i[within], j[within], d2[within]

    def _clusters(self) -> np.ndarray:
        """``(N,)`` bool, insertion order: the points of the selected clusters."""
        core = self._counts >= self.config.cluster_min_points
        label = _labels(self._parent, core, self._nearest)
        if (label < 0).all():
            return np.zeros(len(label), bool)
        sizes = np.bincount(label[label >= 0], minlength=len(label))
        kept = sizes >= self.config.min_cluster_fraction * sizes.max()
        return (label >= 0) & kept[np.maximum(label, 0)]

    # -- statistical outlier removal ----------------------------------------------------------

    def _inliers(self, chosen: np.ndarray) -> np.ndarray:
        """``(len(chosen),)`` bool: the inliers among the points ``chosen`` (insertion indices,
        frame order), as ``statistical_outliers`` finds them."""
        c = self.config
        k = c.outlier_neighbors
        selected = np.zeros(len(self.points), bool)
        selected[chosen] = True
        if len(chosen) <= k:
            self._selected = selected
            return np.ones(len(chosen), bool)
        self._refresh_neighbours(selected, k)
        d = np.concatenate([np.zeros((len(chosen), 1)), self._knn[chosen]], axis=1)
        mean = d[:, 1:].mean(axis=1)
        return mean <= mean.mean() + c.outlier_std_ratio * mean.std()

    def _refresh_neighbours(self, selected: np.ndarray, k: int) -> None:
        """Bring the ``k`` nearest distances of the ``selected`` points up to date."""
        before = self._selected
        added, removed = selected & ~before, before & ~selected
        if before.sum() <= k:
            redo = selected.copy()
        else:
            redo = added.copy()
            if removed.any():
                kept = np.flatnonzero(selected & before)
                redo[kept[_within_kth(self.points[kept], self._knn[kept, -1],
                                      self.points[removed])]] = True
            rest = np.flatnonzero(selected & ~redo)
            if added.any() and len(rest):
                self._merge_added(rest, self.points[added], k)
        target = self.points[selected]
        ids = np.flatnonzero(redo)
        if len(ids):
            self._knn[ids] = _local_knn(self.points[ids], target, k,
                                        2.0 * max(self.config.cluster_radius_mm, 1.0))
        self._selected = selected

    def _merge_added(self, rest: np.ndarray, added: np.ndarray, k: int) -> None:
        """Merge the ``added`` points ``(A, 3)`` into the neighbour lists of the points
        ``rest`` (insertion indices) that they may enter."""
        lo, hi = added.min(axis=0), added.max(axis=0)
        gap = np.maximum(0.0, np.maximum(lo - self.points[rest], self.points[rest] - hi))
        near = rest[np.sqrt((gap * gap).sum(axis=1)) <= self._knn[rest, -1] * (1 + 1e-9)]
        if not len(near):
            return
        d, _ = cKDTree(added).query(self.points[near], k=min(k, len(added)))
        d = d.reshape(len(near), -1)
        self._knn[near] = np.sort(np.concatenate([self._knn[near], d], axis=1), axis=1)[:, :k]


def _within_kth(points: np.ndarray, kth: np.ndarray, others: np.ndarray) -> np.ndarray:
    """``(len(points),)`` bool: whether one of ``others`` is within the ``kth`` distance of each
    point (its neighbour list may hold it)."""
    d, _ = cKDTree(others).query(points, k=1)
    return d <= kth * (1 + 1e-9)


def _local_knn(queries: np.ndarray, target: np.ndarray, k: int, start_mm: float) -> np.ndarray:
    """``(Q, k)`` the sorted distances of each of ``queries`` (points of ``target``) to its
    ``k`` nearest other points of ``target``, as ``cKDTree(target).query(queries, k + 1)``'s
    columns 1 to k: searched in a box around the queries, grown until it holds them."""
    out = np.empty((len(queries), k))
    todo = np.arange(len(queries))
    reach = start_mm
    while len(todo):
        q = queries[todo]
        lo, hi = q.min(axis=0) - reach, q.max(axis=0) + reach
        inside = ((target >= lo) & (target <= hi)).all(axis=1)
        everything = inside.all()
        d, _ = cKDTree(target[inside]).query(q, k=k + 1)
        done = everything | (d[:, k] <= reach)
        out[todo[done]] = d[done, 1:]
        todo = todo[~done]
        reach *= 2.0
    return out


@njit(cache=True)
def _union(parent, a, b):
    """Join the trees of ``a[e]`` and ``b[e]`` for every edge ``e``."""
    for e in range(len(a)):
        ra, rb = find_root(parent, a[e]), find_root(parent, b[e])
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)


@njit(cache=True)
def _labels(parent, core, nearest):
    """``(N,)`` each point's cluster (the root of its core tree; a border point's nearest core
    point's), -1 for noise."""
    n = len(parent)
    out = np.full(n, -1, np.int64)
    for i in range(n):
        if core[i]:
            out[i] = find_root(parent, i)
        elif nearest[i] >= 0:
            out[i] = find_root(parent, nearest[i])
    return out
