"""Compiled kernels (numba) of exact closest points on a triangle mesh: the closest point of a
point on each of its candidate triangles (the Voronoi-region tests of Ericson, 5.1.5), for
:meth:`~comreg_core.registration.geometry.surface.CTSurface.closest`. Compiled on first use and
cached next to this file (``compile_kernels`` of :mod:`.kernels` compiles them at set-up)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _dot(ux, uy, uz, vx, vy, vz):
    return ux * vx + uy * vy + uz * vz


@njit(cache=True)
def _closest_on_triangle(p, vertices, face):
    """The exact closest point ``(x, y, z)`` of ``p`` ``(3,)`` on the triangle ``face`` (three
    row indices into ``vertices``): :func:`~comreg_core.registration.geometry.surface.
    closest_points_on_triangles` for one point (the Voronoi-region tests of Ericson, 5.1.5, in
    the same order of precedence), in scalars: no array is allocated per triangle."""
    ax, ay, az = vertices[face[0], 0], vertices[face[0], 1], vertices[face[0], 2]
    bx, by, bz = vertices[face[1], 0], vertices[face[1], 1], vertices[face[1], 2]
    cx, cy, cz = vertices[face[2], 0], vertices[face[2], 1], vertices[face[2], 2]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    d1 = _dot(abx, aby, abz, p[0] - ax, p[1] - ay, p[2] - az)
    d2 = _dot(acx, acy, acz, p[0] - ax, p[1] - ay, p[2] - az)
    d3 = _dot(abx, aby, abz, p[0] - bx, p[1] - by, p[2] - bz)
    d4 = _dot(acx, acy, acz, p[0] - bx, p[1] - by, p[2] - bz)
    d5 = _dot(abx, aby, abz, p[0] - cx, p[1] - cy, p[2] - cz)
    d6 = _dot(acx, acy, acz, p[0] - cx, p[1] - cy, p[2] - cz)
    if d1 <= 0 and d2 <= 0:
        return ax, ay, az
    if d3 >= 0 and d4 <= d3:
        return bx, by, bz
    if d6 >= 0 and d5 <= d6:
        return cx, cy, cz
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        t = min(max(d1 / (d1 - d3), 0.0), 1.0)
        return ax + abx * t, ay + aby * t, az + abz * t
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        t = min(max(d2 / (d2 - d6), 0.0), 1.0)
        return ax + acx * t, ay + acy * t, az + acz * t
    if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
        t = min(max((d4 - d3) / ((d4 - d3) + (d5 - d6)), 0.0), 1.0)
        return bx + (cx - bx) * t, by + (cy - by) * t, bz + (cz - bz) * t
    denom = va + vb + vc
    v = vb / denom if denom != 0 else 0.0
    w = vc / denom if denom != 0 else 0.0
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w


@njit(cache=True, inline="always")
def _closest_of(i, points, candidates, vertices, faces, closest, face, dist):
    """Row ``i`` of :func:`closest_on_candidates`, written into its outputs."""
    best = np.inf
    for j in range(candidates.shape[1]):
        f = candidates[i, j]
        seen = False
        for earlier in range(j):  # a triangle listed again can only tie with itself: skipped
            if candidates[i, earlier] == f:
                seen = True
                break
        if seen:
            continue
        qx, qy, qz = _closest_on_triangle(points[i], vertices, faces[f])
        d = np.sqrt((qx - points[i, 0]) ** 2 + (qy - points[i, 1]) ** 2
                    + (qz - points[i, 2]) ** 2)
        if d < best:
            best = d
            closest[i, 0], closest[i, 1], closest[i, 2] = qx, qy, qz
            face[i] = f
    dist[i] = best


@njit(cache=True, parallel=True)
def closest_on_candidates(points, candidates, vertices, faces):
    """For each of ``points`` ``(n, 3)`` mm, the closest point on its candidate triangles
    ``candidates`` ``(n, k)`` (face indices into ``faces`` ``(F, 3)`` of ``vertices``
    ``(V, 3)``): ``(closest (n, 3), face (n,), distance (n,))``, the first candidate of the
    smallest distance winning ties. Rows spread over numba's threads."""
    n = candidates.shape[0]
    closest, face, dist = np.empty((n, 3)), np.empty(n, dtype=np.int64), np.empty(n)
    for i in prange(n):
        _closest_of(i, points, candidates, vertices, faces, closest, face, dist)
    return closest, face, dist


@njit(cache=True)
def closest_on_candidates_serial(points, candidates, vertices, faces):
    """:func:`closest_on_candidates` in the calling thread (the same numbers): for a caller
    limited to one thread, which would otherwise hand every call to numba's pool and wait."""
    n = candidates.shape[0]
    closest, face, dist = np.empty((n, 3)), np.empty(n, dtype=np.int64), np.empty(n)
    for i in range(n):
        _closest_of(i, points, candidates, vertices, faces, closest, face, dist)
    return closest, face, dist
