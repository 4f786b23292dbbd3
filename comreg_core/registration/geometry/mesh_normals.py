"""The smooth surface a triangle mesh stands for: vertex normals and their interpolation."""

from __future__ import annotations

import numpy as np
from numba import njit


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray,
                   face_areas: np.ndarray) -> np.ndarray:
    """``(V, 3)`` unit normals of the vertices: their triangles' normals weighted by area."""
    weighted = face_normals * face_areas[:, None]
    out = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(out, faces[:, corner], weighted)
    norm = np.sqrt((out[:, 0] * out[:, 0] + out[:, 1] * out[:, 1]) + out[:, 2] * out[:, 2])
    return out / np.maximum(norm, 1e-12)[:, None]


def smooth_normals(vertices: np.ndarray, faces: np.ndarray, normals_v: np.ndarray,
                   closest: np.ndarray, face: np.ndarray) -> np.ndarray:
    """``(N, 3)`` unit normals at ``closest`` points ``(N, 3)`` on triangles ``face`` ``(N,)``
    (-1: none, NaN out): the triangle's vertex normals ``normals_v`` ``(V, 3)`` interpolated
    barycentrically (compiled; ``tests/registration/test_mesh_normals.py`` holds the numpy
    formula it matches bit for bit). On a faceted mesh of a round shaft they point the way the
    shaft's surface does, not the way its facets do."""
    return _smooth_normals(np.ascontiguousarray(vertices, dtype=np.float64),
                           np.ascontiguousarray(faces, dtype=np.int64),
                           np.ascontiguousarray(normals_v, dtype=np.float64),
                           np.ascontiguousarray(closest, dtype=np.float64),
                           np.ascontiguousarray(face, dtype=np.int64))


@njit(cache=True)
def _smooth_normals(vertices, faces, normals_v, closest, face):
    out = np.full((len(face), 3), np.nan)
    weights, mixed = np.empty(3), np.empty(3)
    for i in range(len(face)):
        if face[i] < 0:
            continue
        corners = faces[face[i]]
        a, b, c = vertices[corners[0]], vertices[corners[1]], vertices[corners[2]]
        v0 = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
        v1 = (c[0] - a[0], c[1] - a[1], c[2] - a[2])
        v2 = (closest[i, 0] - a[0], closest[i, 1] - a[1], closest[i, 2] - a[2])
        d00, d01, d11 = _dot(v0, v0), _dot(v0, v1), _dot(v1, v1)
        d20, d21 = _dot(v2, v0), _dot(v2, v1)
        denominator = d00 * d11 - d01 * d01
        if not abs(denominator) > 0:
            denominator = 1.0
        v = (d11 * d20 - d01 * d21) / denominator
        w = (d00 * d21 - d01 * d20) / denominator
        weights[0], weights[1], weights[2] = 1.0 - v - w, v, w
        for axis in range(3):
            mixed[axis] = ((weights[0] * normals_v[corners[0], axis]
                            + weights[1] * normals_v[corners[1], axis])
                           + weights[2] * normals_v[corners[2], axis])
        norm = np.sqrt((mixed[0] * mixed[0] + mixed[1] * mixed[1]) + mixed[2] * mixed[2])
        for axis in range(3):
            out[i, axis] = mixed[axis] / max(norm, 1e-12)
    return out


@njit(cache=True, inline="always")
def _dot(x, y):
    return (x[0] * y[0] + x[1] * y[1]) + x[2] * y[2]
