"""Nearest cloud points of points that move a little between queries (an ICP's), exactly as a
fresh KD-tree query finds them, with most of the queries skipped.

A query at ``p0`` finds the three nearest cloud points at ``d1 <= d2 <= d3``. A point ``p``
within ``(d2 - d1) / 2`` of ``p0`` has the same nearest cloud point, and one within
``(d3 - d2) / 2`` has it among the first two (by the triangle inequality: a point that was at
``d`` is now within ``d +- |p - p0|``). So :class:`NearestTracker` reads the nearest point from
its memory (the nearer of the two, measured again, in the second case) and queries the tree
only for the points that moved farther, or whose two candidates tie. Distances are computed
as pykdtree computes them (``sqrt((dx^2 + dy^2) + dz^2)`` in float64), so the answer is the
tree's, bit for bit: an ICP that uses it ends at the same poses, only sooner.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Safety margin (mm) of the guarantees, far above the rounding of the distances compared.
MARGIN_MM = 1e-9


@njit(cache=True, inline="always")
def _distance(points, i, j, cloud_points, c):
    dx = points[i, j, 0] - cloud_points[c, 0]
    dy = points[i, j, 1] - cloud_points[c, 1]
    dz = points[i, j, 2] - cloud_points[c, 2]
    return np.sqrt((dx * dx + dy * dy) + dz * dz)


@njit(cache=True)
def known_nearest(points, rows, at, first, second, reach, cloud_points):
    """``(m, n)`` int64: the nearest cloud point of each of ``points`` ``(m, n, 3)`` (start
    ``rows[i]`` each) that its start's memory settles, -1 where it does not. The memory:
    where each point was last queried (``at`` ``(R, n, 3)``), its ``first`` and ``second``
    nearest cloud points there (``(R, n)``) and how far (mm) it may move with the first
    (``reach[..., 0]``) or one of the two (``reach[..., 1]``) still the nearest (-inf: never
    queried)."""
    m, n = points.shape[0], points.shape[1]
    nearest = np.full((m, n), -1, dtype=np.int64)
    for i in range(m):
        r = rows[i]
        for j in range(n):
            dx = points[i, j, 0] - at[r, j, 0]
            dy = points[i, j, 1] - at[r, j, 1]
            dz = points[i, j, 2] - at[r, j, 2]
            moved = np.sqrt((dx * dx + dy * dy) + dz * dz) + MARGIN_MM
            if moved < reach[r, j, 0]:
                nearest[i, j] = first[r, j]
            elif moved < reach[r, j, 1]:
                a = _distance(points, i, j, cloud_points, first[r, j])
                b = _distance(points, i, j, cloud_points, second[r, j])
                if a < b:
                    nearest[i, j] = first[r, j]
                elif b < a:
                    nearest[i, j] = second[r, j]
    return nearest


@njit(cache=True)
def remember(points, rows, nearest, distances, indices, at, first, second, reach):
    """Store the fresh queries of the unsettled points (``nearest`` -1, in row-major order:
    ``distances`` ``(s, 3)`` to and ``indices`` ``(s, 3)`` of their three nearest cloud points)
    in their starts' memory (:func:`known_nearest`) and in ``nearest``."""
    k = 0
    for i in range(nearest.shape[0]):
        r = rows[i]
        for j in range(nearest.shape[1]):
            if nearest[i, j] < 0:
                at[r, j, 0], at[r, j, 1], at[r, j, 2] = (points[i, j, 0], points[i, j, 1],
                                                         points[i, j, 2])
                first[r, j], second[r, j] = indices[k, 0], indices[k, 1]
                reach[r, j, 0] = (distances[k, 1] - distances[k, 0]) / 2.0
                reach[r, j, 1] = (distances[k, 2] - distances[k, 1]) / 2.0
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

    def __init__(self, cloud, max_distance: float = np.inf):
        self.cloud = cloud
        self.max_distance = float(max_distance)
        self._points = np.ascontiguousarray(cloud.points, dtype=np.float64)
        self._normals = np.ascontiguousarray(cloud.normals, dtype=np.float64)
        self._at = np.empty((0, 0, 3))
        self._first = np.empty((0, 0), dtype=np.int64)
        self._second = np.empty((0, 0), dtype=np.int64)
        self._reach = np.empty((0, 0, 2))
        self.queried = 0
        self.reused = 0

    def _make_room(self, starts: int, n: int) -> None:
        """Memory for ``starts`` starts of ``n`` points (all forgotten when ``n`` changes)."""
        if n != self._at.shape[1]:
            self._at, self._reach = np.empty((0, n, 3)), np.empty((0, n, 2))
            self._first = np.empty((0, n), dtype=np.int64)
            self._second = np.empty((0, n), dtype=np.int64)
        grow = starts - len(self._at)
        if grow > 0:
            self._at = np.concatenate([self._at, np.zeros((grow, n, 3))])
            self._first = np.concatenate([self._first, np.zeros((grow, n), dtype=np.int64)])
            self._second = np.concatenate([self._second, np.zeros((grow, n), dtype=np.int64)])
            self._reach = np.concatenate([self._reach, np.full((grow, n, 2), -np.inf)])

    def __call__(self, points: np.ndarray, rows: np.ndarray | None = None):
        """``(closest (m, n, 3), normals (m, n, 3), distance (m, n) mm)`` of ``points``
        ``(m, n, 3)`` (``(n, 3)``: one start, row 0)."""
        pts = np.ascontiguousarray(points, dtype=np.float64)
        single = pts.ndim == 2
        pts = pts[None] if single else pts
        rows = (np.arange(len(pts)) if rows is None
                else np.ascontiguousarray(rows, dtype=np.int64))
        self._make_room(int(rows.max()) + 1 if len(rows) else 0, pts.shape[1])
        nearest = known_nearest(pts, rows, self._at, self._first, self._second, self._reach,
                                self._points)
        unknown = nearest < 0
        count = int(unknown.sum())
        if count:
            distances, indices = self.cloud.tree.query(np.ascontiguousarray(pts[unknown]), k=3)
            remember(pts, rows, nearest, np.asarray(distances, dtype=np.float64),
                     np.asarray(indices, dtype=np.int64), self._at, self._first,
                     self._second, self._reach)
        self.queried += count
        self.reused += nearest.size - count
        closest, normals, distance = gather(pts, nearest, self._points, self._normals)
        if self.max_distance < np.inf:
            distance = np.where(distance <= self.max_distance, distance, np.inf)
        if single:
            return closest[0], normals[0], distance[0]
        return closest, normals, distance
