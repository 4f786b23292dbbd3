"""The smooth surface a triangle mesh stands for: vertex normals and their interpolation."""

from __future__ import annotations

import numpy as np


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
    barycentrically. On a faceted mesh of a round shaft they point the way the shaft's surface
    does, not the way its facets do."""
    out = np.full((len(face), 3), np.nan)
    ok = face >= 0
    corners = faces[face[ok]]
    weights = barycentric(closest[ok], vertices[corners])
    vn = normals_v[corners]  # n 3 3
    mixed = (weights[:, 0:1] * vn[:, 0] + weights[:, 1:2] * vn[:, 1]) + weights[:, 2:3] * vn[:, 2]
    norm = np.sqrt((mixed[:, 0] * mixed[:, 0] + mixed[:, 1] * mixed[:, 1])
                   + mixed[:, 2] * mixed[:, 2])
    out[ok] = mixed / np.maximum(norm, 1e-12)[:, None]
    return out


def barycentric(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(N, 3)`` barycentric weights of ``(N, 3)`` points in their triangles ``(N, 3, 3)``
    (points on the triangles' planes; elementwise arithmetic)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    v0, v1, v2 = b - a, c - a, points - a

    def dot(x, y):
        return (x[:, 0] * y[:, 0] + x[:, 1] * y[:, 1]) + x[:, 2] * y[:, 2]

    d00, d01, d11, d20, d21 = dot(v0, v0), dot(v0, v1), dot(v1, v1), dot(v2, v0), dot(v2, v1)
    denominator = np.where(np.abs(d00 * d11 - d01 * d01) > 0, d00 * d11 - d01 * d01, 1.0)
    v = (d11 * d20 - d01 * d21) / denominator
    w = (d00 * d21 - d01 * d20) / denominator
    return np.stack([1.0 - v - w, v, w], axis=1)
