"""Nearest cloud points of points that move a little between queries (an ICP's), exactly as a
fresh KD-tree query finds them, with most of the queries skipped.

A query at ``p0`` finds the ``K + 1`` nearest cloud points at ``d1 <= d2 <= ... <= d(K+1)``;
the first ``K`` are remembered with ``d(K+1)``. A point ``p`` that moved ``m = |p - p0|``
is at least ``d(K+1) - m`` from every cloud point not remembered (triangle inequality). So
:class:`NearestTracker` measures ``p``'s distances to the ``K`` remembered points and, when
the smallest is unique and below ``d(K+1) - m``, that point is the nearest; a point that moved
less than ``(d2 - d1) / 2`` keeps its first without measuring. Only the other points are
queried. Distances are computed as pykdtree computes them (``sqrt((dx^2 + dy^2) + dz^2)`` in
float64), so the answer is the tree's, bit for bit: an ICP that uses it ends at the same
poses, only sooner.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Safety margin (mm) of the guarantees, far above the rounding of the distances compared.
MARGIN_MM = 1e-9
#: Nearest cloud points remembered per point (a query asks for one more).
REMEMBERED = 4


@njit(cache=True, inline="always")
def _distance(points, i, j, cloud_points, c):
    dx = points[i, j, 0] - cloud_points[c, 0]
    dy = points[i, j, 1] - cloud_points[c, 1]
    dz = points[i, j, 2] - cloud_points[c, 2]
    return np.sqrt((dx * dx + dy * dy) + dz * dz)


@njit(cache=True)
def known_nearest(points, rows, at, candidates, reach, bound, cloud_points):
    """``(m, n)`` int64: the nearest cloud point of each of ``points`` ``(m, n, 3)`` (start
    ``rows[i]`` each) that its start's memory settles, -1 where it does not. The memory:
    where each point was last queried (``at`` ``(R, n, 3)``), its ``K`` nearest cloud points
    there (``candidates`` ``(R, n, K)``), how far (mm) it may move with the first still the
    nearest (``reach`` ``(R, n)``, -inf: never queried) and the distance of the nearest cloud
    point not remembered (``bound`` ``(R, n)``)."""
    m, n = points.shape[0], points.shape[1]
    nearest = np.full((m, n), -1, dtype=np.int64)
    for i in range(m):
        r = rows[i]
        for j in range(n):
            dx = points[i, j, 0] - at[r, j, 0]
            dy = points[i, j, 1] - at[r, j, 1]
            dz = points[i, j, 2] - at[r, j, 2]
            moved = np.sqrt((dx * dx + dy * dy) + dz * dz) + MARGIN_MM
            if moved < reach[r, j]:
                nearest[i, j] = candidates[r, j, 0]
                continue
            if reach[r, j] == -np.inf:
                continue
            best, second, found = np.inf, np.inf, -1
            for c in candidates[r, j]:
                d = _distance(points, i, j, cloud_points, c)
                if d < best:
                    best, second, found = d, best, c
                elif d < second:
                    second = d
            if best < second and best + MARGIN_MM < bound[r, j] - moved:
                nearest[i, j] = found
    return nearest


@njit(cache=True)
def remember(points, rows, nearest, distances, indices, at, candidates, reach, bound):
    """Store the fresh queries of the unsettled points (``nearest`` -1, in row-major order:
    ``distances`` ``(s, K + 1)`` to and ``indices`` ``(s, K + 1)`` of their nearest cloud
    points) in their starts' memory (:func:`known_nearest`) and in ``nearest``."""
    k = 0
    K = candidates.shape[2]
    for i in range(nearest.shape[0]):
        r = rows[i]
        for j in range(nearest.shape[1]):
            if nearest[i, j] < 0:
                at[r, j, 0], at[r, j, 1], at[r, j, 2] = (points[i, j, 0], points[i, j, 1],
                                                         points[i, j, 2])
                candidates[r, j] = indices[k, :K]
                reach[r, j] = (distances[k, 1] - distances[k, 0]) / 2.0
                bound[r, j] = distances[k, K]
                nearest[i, j] = indices[k, 0]
                k += 1


@njit(cache=True)
def gather(points, nearest, cloud_points, cloud_normals):
    """``(closest (m, n, 3), normals (m, n, 3), distance (m, n))`` of ``points`` ``(m, n, 3)``
    from their ``nearest`` ``(m, n)`` cloud points."""
    m, n = points.shape[0], points.shape[1]
    closest = np.empty((m, n, 3))
    normals = np.empty((m, n, 3))
    distance = np.empty((m, n))
    for i in range(m):
        for j in range(n):
            c = nearest[i, j]
            for a in range(3):
                closest[i, j, a] = cloud_points[c, a]
                normals[i, j, a] = cloud_normals[c, a]
            distance[i, j] = _distance(points, i, j, cloud_points, c)
    return closest, normals, distance


class NearestTracker:
    """An ICP :data:`~comreg_core.registration.geometry.surface.Matcher` on a
    :class:`~comreg_core.registration.geometry.surface.SurfaceCloud`: the same answers as its
    :meth:`~comreg_core.registration.geometry.surface.SurfaceCloud.match` with the same
    ``max_distance`` gate (mm; pairs beyond it unmatched), each point's last query remembered.

    Call it with ``points`` ``(m, n, 3)`` (or ``(n, 3)``) and ``rows`` ``(m,)``: which of the
    ICP's starts each row is (a row's points are compared with that start's last query; a start
    seen first, or points of another ``n``, are queried). One tracker per ICP run: its memory is
    ``(starts, n)``. ``queried``/``reused`` count the points looked up each way."""

    def __init__(self, cloud, max_distance: float = np.inf, remembered: int = REMEMBERED):
        self.cloud = cloud
        self.max_distance = float(max_distance)
        self.remembered = int(remembered)
        self._points = np.ascontiguousarray(cloud.points, dtype=np.float64)
        self._normals = np.ascontiguousarray(cloud.normals, dtype=np.float64)
        self._forget(0)
        self.queried = 0
        self.reused = 0

    def _forget(self, n: int) -> None:
        """An empty memory for starts of ``n`` points."""
        self._at, self._reach = np.empty((0, n, 3)), np.empty((0, n))
        self._bound = np.empty((0, n))
        self._candidates = np.empty((0, n, self.remembered), dtype=np.int64)

    def _make_room(self, starts: int, n: int) -> None:
        """Memory for ``starts`` starts of ``n`` points (all forgotten when ``n`` changes)."""
        if n != self._at.shape[1]:
            self._forget(n)
        grow = starts - len(self._at)
        if grow > 0:
            self._at = np.concatenate([self._at, np.zeros((grow, n, 3))])
            self._candidates = np.concatenate(
                [self._candidates, np.zeros((grow, n, self.remembered), dtype=np.int64)])
            self._reach = np.concatenate([self._reach, np.full((grow, n), -np.inf)])
            self._bound = np.concatenate([self._bound, np.zeros((grow, n))])

    def __call__(self, points: np.ndarray, rows: np.ndarray | None = None):
        """``(closest (m, n, 3), normals (m, n, 3), distance (m, n) mm)`` of ``points``
        ``(m, n, 3)`` (``(n, 3)``: one start, row 0)."""
        pts = np.ascontiguousarray(points, dtype=np.float64)
        single = pts.ndim == 2
        pts = pts[None] if single else pts
        rows = (np.arange(len(pts)) if rows is None
                else np.ascontiguousarray(rows, dtype=np.int64))
        self._make_room(int(rows.max()) + 1 if len(rows) else 0, pts.shape[1])
        nearest = known_nearest(pts, rows, self._at, self._candidates, self._reach,
                                self._bound, self._points)
        unknown = nearest < 0
        count = int(unknown.sum())
        if count:
            distances, indices = self.cloud.tree.query(np.ascontiguousarray(pts[unknown]),
                                                       k=self.remembered + 1)
            remember(pts, rows, nearest, np.asarray(distances, dtype=np.float64),
                     np.asarray(indices, dtype=np.int64), self._at, self._candidates,
                     self._reach, self._bound)
        self.queried += count
        self.reused += nearest.size - count
        closest, normals, distance = gather(pts, nearest, self._points, self._normals)
        if self.max_distance < np.inf:
            distance = np.where(distance <= self.max_distance, distance, np.inf)
        if single:
            return closest[0], normals[0], distance[0]
        return closest, normals, distance
