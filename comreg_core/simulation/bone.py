"""``BoneModel``: a CT bone mesh checked and prepared once for simulating many sweeps.

Holds the mesh (mm), its principal axes (area-weighted PCA of the surface), one embree BVH for
ray casting, and per-slab tables of the bone's cross-section (support function and centre) used
to place the probe at a chosen distance from the bone.
"""

from __future__ import annotations

import logging

import numpy as np

from comreg_core.errors import InvalidGeometryError
from comreg_core.registration.geometry.surface import CTSurface, mesh_arrays, sample_triangles
from comreg_core.surfaces.mesh_repair import (  # noqa: F401 (MIN_EXTENT_MM re-exported)
    MIN_EXTENT_MM, check_millimetres)

log = logging.getLogger(__name__)


class BoneModel:
    """A closed CT bone surface ready for ray casting.

    Args:
        mesh: a :class:`~comreg_core.io.meshes.SurfaceMesh`, a ``trimesh.Trimesh``, a path to a
            mesh file, or a ``(vertices (V, 3), faces (F, 3))`` tuple; millimetres.
        slab_mm: axial slab thickness of the cross-section tables.
        n_angles: angular resolution of the support-function table.

    Raises:
        InvalidGeometryError: no faces, non-finite vertices, all triangles degenerate, extent
            below 1 mm (metres), or an open (not watertight) surface.

    Attributes:
        vertices ``(V, 3)`` float64 mm, faces ``(F, 3)`` int64 (outward winding),
        face_normals ``(F, 3)``, face_areas ``(F,)`` mm^2, space ("LPS"/"RAS"),
        centre ``(3,)`` area-weighted surface centroid, axes ``(3, 3)`` columns e0 (long axis),
        e1, e2 (right-handed), axial_range ``(a_min, a_max)`` of the surface along e0 relative to
        ``centre``, length (mm).
    """

    def __init__(self, mesh, *, slab_mm: float = 2.0, n_angles: int = 72):
        vertices, faces, self.space, self.path = mesh_arrays(mesh)
        tm = _checked_trimesh(vertices, faces, self.path)
        self.vertices = np.asarray(tm.vertices, dtype=np.float64)
        self.faces = np.asarray(tm.faces, dtype=np.int64)
        self.face_normals = np.asarray(tm.face_normals, dtype=np.float64)
        self.face_areas = np.asarray(tm.area_faces, dtype=np.float64)
        self._trimesh = tm
        self._principal_axes()
        self._cross_section_tables(slab_mm, n_angles)
        self._scene = None
        self._distance = None
        self._support_cache: dict[int, np.ndarray] = {}
        log.debug("BoneModel: %d faces, length %.1f mm", len(self.faces), self.length)

    # --- geometry tables --------------------------------------------------------------------

    def _principal_axes(self) -> None:
        centroids = self.vertices[self.faces].mean(axis=1)
        w = self.face_areas / self.face_areas.sum()
        centre = w @ centroids
        d = centroids - centre
        cov = (d * w[:, None]).T @ d
        _, vecs = np.linalg.eigh(cov)
        e0, e1 = vecs[:, 2], vecs[:, 1]
        # canonical signs: the largest-magnitude component of e0 and e1 is positive
        e0 = e0 * np.sign(e0[np.argmax(np.abs(e0))])
        e1 = e1 * np.sign(e1[np.argmax(np.abs(e1))])
        self.centre = centre
        self.axes = np.column_stack([e0, e1, np.cross(e0, e1)])
        axial = (self.vertices - centre) @ e0
        self.axial_range = (float(axial.min()), float(axial.max()))
        self.length = self.axial_range[1] - self.axial_range[0]

    def _cross_section_tables(self, slab_mm: float, n_angles: int) -> None:
        samples = np.concatenate([self.vertices, self.vertices[self.faces].mean(axis=1)])
        local = (samples - self.centre) @ self.axes  # (P, 3): axial, e1, e2
        a_min, a_max = self.axial_range
        n_slabs = max(1, int(np.ceil(self.length / slab_mm)))
        self._slab_mm = self.length / n_slabs
        slab = np.clip(((local[:, 0] - a_min) / self._slab_mm).astype(np.int64), 0, n_slabs - 1)
        self._angles = np.linspace(0.0, 2 * np.pi, n_angles, endpoint=False)
        proj = local[:, 1:2] * np.cos(self._angles) + local[:, 2:3] * np.sin(self._angles)
        order = np.argsort(slab, kind="stable")
        slab_sorted = slab[order]
        present, starts = np.unique(slab_sorted, return_index=True)
        support = np.full((n_slabs, n_angles), np.nan)
        support[present] = np.maximum.reduceat(proj[order], starts, axis=0)
        counts = np.bincount(slab, minlength=n_slabs)
        centre2 = np.full((n_slabs, 2), np.nan)
        sums = np.stack([np.bincount(slab, local[:, k], n_slabs) for k in (1, 2)], axis=1)
        centre2[present] = sums[present] / counts[present, None]
        # empty slabs (possible for very coarse meshes): copy the nearest filled slab
        if len(present) < n_slabs:
            nearest = present[np.abs(np.arange(n_slabs)[:, None] - present[None]).argmin(axis=1)]
            support, centre2 = support[nearest], centre2[nearest]
        self._support = support
        self._section_centre = centre2

    def _slab_index(self, axial: np.ndarray) -> np.ndarray:
        idx = np.floor((np.asarray(axial) - self.axial_range[0]) / self._slab_mm).astype(np.int64)
        return np.clip(idx, 0, len(self._support) - 1)

    def support(self, axial: np.ndarray, angle: np.ndarray, halfwidth_mm: float = 0.0
                ) -> np.ndarray:
        """Height of the bone surface in direction ``u(angle) = cos(angle) e1 + sin(angle) e2``:
        the largest ``(p - centre) . u`` over surface points ``p`` whose axial coordinate lies
        within ``halfwidth_mm`` (plus one slab) of ``axial``. Shapes broadcast; mm, radians.
        Positions past the bone ends use the end slab."""
        radius = int(np.ceil(halfwidth_mm / self._slab_mm))
        table = self._support_cache.get(radius)
        if table is None:
            from scipy.ndimage import maximum_filter1d

            table = maximum_filter1d(self._support, size=2 * radius + 3, axis=0, mode="nearest")
            self._support_cache[radius] = table
        n_angles = table.shape[1]
        pos = np.mod(np.asarray(angle, dtype=np.float64), 2 * np.pi) / (2 * np.pi) * n_angles
        k0 = np.floor(pos).astype(np.int64) % n_angles
        frac = pos - np.floor(pos)
        idx = self._slab_index(axial)
        return (1 - frac) * table[idx, k0] + frac * table[idx, (k0 + 1) % n_angles]

    def section_centre(self, axial: np.ndarray) -> np.ndarray:
        """``(..., 3)`` centre of the bone cross-section at ``axial`` (mm along e0 from
        ``centre``), as an offset from the long axis (no e0 component)."""
        c = self._section_centre[self._slab_index(axial)]
        return c[..., 0:1] * self.axes[:, 1] + c[..., 1:2] * self.axes[:, 2]

    # --- ray casting ---------------------------------------------------------------------------

    @property
    def scene(self):
        """The embree scene (built on first use): vertices centred on ``centre`` in float32."""
        if self._scene is None:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh

            scene = rtcore_scene.EmbreeScene()
            TriangleMesh(scene=scene, vertices=(self.vertices - self.centre).astype(np.float32),
                         indices=self.faces.astype(np.int32))
            self._scene = scene
        return self._scene

    def cast(self, origins: np.ndarray, directions: np.ndarray, max_distance: float
             ) -> tuple[np.ndarray, np.ndarray]:
        """First intersection of each ray with the surface, within ``max_distance`` mm.

        Args:
            origins: ``(R, 3)`` ray starts in mm (CT frame).
            directions: ``(R, 3)`` unit directions.
            max_distance: rays end here (the image depth).

        Returns:
            face ``(R,)`` int64 index of the first triangle hit, -1 where the ray misses or
            first meets a triangle from behind (it starts inside the bone); points ``(R, 3)``
            float64 hit positions computed on that triangle from embree's barycentric
            coordinates (NaN where face is -1).
        """
        o = (np.asarray(origins, dtype=np.float64) - self.centre).astype(np.float32)
        d = np.asarray(directions, dtype=np.float32)
        n = len(o)
        if n == 0:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        result = self.scene.run(o, d, dists=np.full(n, max_distance, dtype=np.float32),
                                output=1)
        face = result["primID"].astype(np.int64)
        hit = face >= 0
        hit_idx = np.flatnonzero(hit)
        hit_face = face[hit_idx]
        front = np.einsum("ij,ij->i", self.face_normals[hit_face],
                          np.asarray(directions, dtype=np.float64)[hit_idx]) < 0
        face[hit_idx[~front]] = -1
        hit_idx, hit_face = hit_idx[front], hit_face[front]
        u = result["u"][hit_idx].astype(np.float64)[:, None]
        v = result["v"][hit_idx].astype(np.float64)[:, None]
        tri = self.vertices[self.faces[hit_face]]  # (H, 3, 3)
        points = np.full((n, 3), np.nan)
        points[hit_idx] = (1 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]
        return face, points

    # --- sampling and distances -------------------------------------------------------------------

    def sample_surface(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``n`` points uniform over the surface area: points ``(n, 3)`` mm, faces ``(n,)``
        (:func:`~comreg_core.registration.geometry.surface.sample_triangles`)."""
        return sample_triangles(self.vertices, self.faces, self.face_areas, n, rng)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (mm) from ``(N, 3)`` points to the surface (exact point-to-triangle,
        :meth:`CTSurface.distance`: an implementation independent of the ray caster)."""
        if self._distance is None:
            self._distance = CTSurface((self.vertices, self.faces))
        return self._distance.distance(points)

    def to_trimesh(self):
        """The checked mesh as a ``trimesh.Trimesh`` (merged vertices, outward winding)."""
        return self._trimesh


def _checked_trimesh(vertices: np.ndarray, faces: np.ndarray, path):
    import trimesh

    where = f" '{path}'" if path else ""
    extent = np.ptp(vertices[np.unique(faces)], axis=0)
    check_millimetres(vertices[np.unique(faces)], where)
    tm = trimesh.Trimesh(vertices, faces, process=True, validate=False)
    areas = tm.area_faces
    good = areas > 1e-10 * max(extent.max(), 1.0) ** 2
    if not good.any():
        raise InvalidGeometryError(
            f"Every triangle of the bone mesh{where} is degenerate (zero area).",
            "Export the bone surface again from its segmentation.")
    if not good.all():
        log.info("Removing %d zero-area triangles", int((~good).sum()))
        tm.update_faces(good)
        tm.remove_unreferenced_vertices()
    if not tm.is_watertight:
        edges = tm.edges_sorted
        _, counts = np.unique(edges, axis=0, return_counts=True)
        open_edges = int((counts == 1).sum())
        raise InvalidGeometryError(
            f"The bone mesh{where} is not closed ({open_edges} boundary edges, "
            f"{int((counts > 2).sum())} edges shared by more than two triangles).",
            "The simulator needs a closed (watertight) bone surface: fill the holes, e.g. with "
            "3D Slicer's Surface Toolbox, or extract the surface again from the segmentation.")
    if not tm.is_winding_consistent:
        raise InvalidGeometryError(
            f"The triangles of the bone mesh{where} are not consistently oriented.",
            "Repair the mesh (e.g. 'Surface Toolbox > Normals > Auto-orient') and export it "
            "again.")
    if tm.volume < 0:
        tm.invert()
    if abs(tm.volume) < 1e-9 * extent.max() ** 3:
        raise InvalidGeometryError(
            f"The bone mesh{where} encloses no volume (it is flat or degenerate).",
            "Export the bone surface again from its segmentation.")
    return tm
