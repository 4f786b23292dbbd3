"""Rigid ICP of a point cloud to a triangle mesh: exact closest points, point-to-plane.

- :func:`closest_points_on_triangles`: the exact closest point of a point on a triangle.
- :class:`SurfaceMatcher`: closest points on a CT mesh with their triangle normals (a KD-tree
  of dense surface samples and triangle centroids nominates the candidate triangles).
- :func:`point_to_plane_icp`: point-to-plane ICP against a :class:`SurfaceMatcher`, pairs
  farther apart than a gate rejected.

Used by the registration's final polish (:mod:`comreg_core.hypotheses`) and by the ``icp-gt``
baseline (:mod:`comreg_core.evaluation.baselines`).
"""

from __future__ import annotations

import numpy as np

from comreg_core.errors import InvalidGeometryError
from comreg_core.transforms import apply_transform, as_points, check_rigid, orthonormalize


def source_points(points, what: str = "US points", minimum: int = 3) -> np.ndarray:
    """``(N, 3)`` float64 points, or a clear :class:`InvalidGeometryError` below ``minimum``."""
    pts = as_points(points, what)
    if len(pts) < minimum:
        raise InvalidGeometryError(f"The {what} have {len(pts)} points; registration needs at "
                                   f"least {minimum}.", "Pass a larger cloud.")
    return pts


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
                                ) -> np.ndarray:
    """Exact closest point of each point ``p[i]`` on triangle ``(a[i], b[i], c[i])`` (all
    ``(..., 3)``), by the Voronoi-region tests of Ericson, *Real-Time Collision Detection*, 5.1.5.
    """
    dot = lambda u, v: np.einsum("...j,...j->...", u, v)  # noqa: E731
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        out = a + ab * v[..., None] + ac * w[..., None]  # interior (face region)
        # edge regions (each overrides the face region where it applies)
        t_bc = np.clip((d4 - d3) / ((d4 - d3) + (d5 - d6)), 0, 1)
        on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        out = np.where(on_bc[..., None], b + (c - b) * t_bc[..., None], out)
        t_ac = np.clip(d2 / (d2 - d6), 0, 1)
        on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out = np.where(on_ac[..., None], a + ac * t_ac[..., None], out)
        t_ab = np.clip(d1 / (d1 - d3), 0, 1)
        on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out = np.where(on_ab[..., None], a + ab * t_ab[..., None], out)
    # vertex regions
    out = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, out)
    return out


class SurfaceMatcher:
    """Closest points on a triangle mesh for ICP: the ``k`` points nearest a query among dense
    area-uniform CT surface samples and every triangle's centroid (one KD-tree) nominate their
    triangles, and the exact closest point over those triangles is returned with that triangle's
    normal. It is the mesh's true closest point whenever the closest triangle is among the
    candidates; otherwise it is another surface point slightly farther away. Measured on the
    fibula (44k triangles, 200k samples, k = 8): exact for ~98% of points within 3 mm of the
    surface, at most ~0.1 mm farther for the rest (small triangles without samples), which moves
    an ICP pose by well under 0.01 mm. Much faster than a VTK locator queried point by point."""

    def __init__(self, ct_mesh, n_samples: int = 200_000, k: int = 8):
        from scipy.spatial import cKDTree

        from comreg_core.evaluation.metrics import as_surface  # here: evaluation imports us

        surface = as_surface(ct_mesh)
        self.vertices, self.faces = surface.vertices, surface.faces
        self.face_normals = surface.face_normals
        points, _ = surface.samples(n_samples)
        # every triangle's centroid too, so that small triangles (few or no samples) are found
        centroids = self.vertices[self.faces].mean(axis=1)
        self._sample_face = np.concatenate([surface.sample_faces(n_samples),
                                            np.arange(len(self.faces))])
        self._tree = cKDTree(np.vstack([points, centroids]))
        self.k = int(k)

    def closest(self, points: np.ndarray, max_distance: float = np.inf
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(closest (N, 3), normals (N, 3), distance (N,))``; ``distance`` is ``inf`` where the
        nearest sample is farther than ``max_distance`` + 1 mm (then the point is not matched)."""
        d, idx = self._tree.query(points, k=self.k, distance_upper_bound=max_distance + 1.0)
        ok = np.isfinite(d[:, 0])
        n = len(points)
        closest = np.full((n, 3), np.nan)
        normals = np.full((n, 3), np.nan)
        dist = np.full(n, np.inf)
        if ok.any():
            idx = np.where(np.isfinite(d[ok]), idx[ok], idx[ok][:, :1])
            faces = self._sample_face[idx]  # (n_ok, k)
            tri = self.vertices[self.faces[faces]]  # (n_ok, k, 3, 3)
            p = points[ok][:, None, :]
            q = closest_points_on_triangles(p, tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
            dq = np.linalg.norm(q - p, axis=2)
            best = np.argmin(dq, axis=1)
            rows = np.arange(len(best))
            closest[ok] = q[rows, best]
            normals[ok] = self.face_normals[faces[rows, best]]
            dist[ok] = dq[rows, best]
        dist[dist > max_distance] = np.inf
        return closest, normals, dist


def point_to_plane_icp(source: np.ndarray, target: SurfaceMatcher, T_init: np.ndarray, *,
                       max_distance_mm: float = 5.0, max_iterations: int = 100,
                       tolerance_mm: float = 1e-5) -> tuple[np.ndarray, dict]:
    """Rigid point-to-plane ICP against a mesh: ``T`` minimising ``sum ((T s_i - q_i) . n_i)^2``
    with ``q_i`` the exact closest surface point of ``T s_i`` and ``n_i`` its triangle's normal
    (:class:`SurfaceMatcher`); pairs farther apart than ``max_distance_mm`` are ignored.

    Each iteration linearises the rotation about the centroid of the matched moved source points
    and solves the 6x6 least-squares problem (``numpy.linalg.lstsq``, so directions the surface
    does not constrain, e.g. sliding along a cylinder, get the minimum-norm update), then applies
    the exact rotation of that rotation vector. Stops when an update moves no source point by
    more than ``tolerance_mm``.

    Returns:
        ``T`` ``(4, 4)`` and ``{"iterations", "inlier_fraction", "rmse_mm", "converged"}``
        (``rmse_mm``: point-to-surface distance of the matched points at the last iteration).
    """
    from scipy.spatial.transform import Rotation

    src = source_points(source, "source points", 6)
    T = check_rigid(T_init).copy()
    info = {"iterations": 0, "inlier_fraction": 0.0, "rmse_mm": float("nan"), "converged": False}
    extent = float(np.linalg.norm(np.ptp(src, axis=0))) or 1.0
    for it in range(1, max_iterations + 1):
        moved = apply_transform(T, src)
        q, n, d = target.closest(moved, max_distance_mm)
        ok = np.isfinite(d)
        info.update(iterations=it, inlier_fraction=float(ok.mean()))
        if ok.sum() < 6:
            break
        p, q, n = moved[ok], q[ok], n[ok]
        info["rmse_mm"] = float(np.sqrt(np.mean(d[ok] ** 2)))
        c = p.mean(axis=0)
        A = np.hstack([np.cross(p - c, n), n])
        r = np.einsum("ij,ij->i", p - q, n)
        x, *_ = np.linalg.lstsq(A, -r, rcond=None)
        step = np.eye(4)
        step[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
        step[:3, 3] = c - step[:3, :3] @ c + x[3:]
        T = step @ T
        # bound on the largest displacement of a cloud point by this update
        if np.linalg.norm(x[:3]) * extent + np.linalg.norm(x[3:]) < tolerance_mm:
            info["converged"] = True
            break
    return orthonormalize(T), info
