"""Fixed camera presets from the CT bone's principal axes, and the parallel-projection framing.

How the three presets are made (all from the CT mesh alone, so every report of the same CT looks
the same, whatever the US data):

* **Bone axis** ``b``: the first principal axis of the CT surface (eigenvector of the largest
  eigenvalue of the triangle-area-weighted covariance of the triangle centroids), signed to point
  to the patient's superior (S is +z in both LPS and RAS). For a bone without a clear long axis
  (largest eigenvalue < 1.5 x the second) the patient superior axis is used instead.
* **Anterior direction** ``a``: the patient's anterior axis (A = -y in LPS, +y in RAS) made
  orthogonal to ``b`` (Gram-Schmidt). The second and third principal axes of a near-cylindrical
  long bone are unstable (their order and sign flip with small changes of the mesh), so they are
  used only when the bone axis runs within ~17 degrees of anterior-posterior (then the one of them
  closest to anterior).
* **Left direction** ``l = b x a``: the patient's left (L = +x in LPS, -x in RAS) made orthogonal to
  both.

The presets (``direction`` = from the focal point towards the camera):

======================  ==================  ========  ======================================
preset                  camera at           view-up   on screen
======================  ==================  ========  ======================================
``anterior``            ``+a`` (in front)   ``+b``    superior up, patient's right on the
                                                      image left (like an AP radiograph)
``lateral``             ``+l`` (at the      ``+b``    superior up, anterior on the image left
                        patient's left)               (``lateral_side="right"``: camera at the
                                                      patient's right, anterior on the right)
``bone_axis``           ``-b`` (below,      ``+a``    looking up the bone from its inferior end:
                        looking superior)             anterior up, patient's left on the image
                                                      right (the radiological axial convention)
======================  ==================  ========  ======================================

Which of ``lateral`` is the anatomically lateral side depends on the limb: for a left limb the
default (camera at the patient's left) is lateral, for a right limb it is medial; pass
``lateral_side="right"`` for a right limb. Every screenshot also carries orientation letters
(R/L, A/P, S/I) at its edges, computed from the same vectors.

Projection is parallel (orthographic): no perspective distortion, the same mm-per-pixel scale
everywhere in an image, and a point's pixel is an affine function of its position
(:meth:`CameraView.project`), which the tests use to find known points in screenshots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comreg_core.errors import InvalidGeometryError
from comreg_core.transforms import check_space

VIEW_NAMES = ("anterior", "lateral", "bone_axis")

#: Long-axis test: a bone is "long" when its largest principal variance is this many times the
#: second; otherwise the patient superior axis is the bone axis.
ELONGATION_MIN = 1.5
#: The anterior axis projected off the bone axis must keep at least this length (sin ~17 deg).
ANTERIOR_MIN = 0.3


def patient_directions(space: str) -> dict[str, np.ndarray]:
    """Unit vectors of the patient's left, anterior and superior in ``space`` ("LPS"/"RAS")."""
    space = check_space(space)
    x = 1.0 if space == "LPS" else -1.0  # +x is L in LPS, R in RAS
    return {"left": np.array([x, 0.0, 0.0]),
            "anterior": np.array([0.0, -x, 0.0]),  # +y is P in LPS, A in RAS
            "superior": np.array([0.0, 0.0, 1.0])}


@dataclass(frozen=True)
class BoneFrame:
    """Orthonormal frame of a bone in its patient space (mm).

    Attributes:
        center: ``(3,)`` area-weighted surface centroid.
        axis: ``(3,)`` unit long axis, towards superior.
        anterior: ``(3,)`` unit, orthogonal to ``axis``, towards the patient's anterior.
        left: ``(3,)`` unit, ``axis x anterior``, towards the patient's left.
        variances: ``(3,)`` principal variances (mm^2), largest first.
        space: "LPS" or "RAS".
        long_axis_from_pca: False when the bone was too round for a principal long axis and the
            patient superior axis was used.
    """

    center: np.ndarray
    axis: np.ndarray
    anterior: np.ndarray
    left: np.ndarray
    variances: np.ndarray
    space: str
    long_axis_from_pca: bool


def bone_frame(vertices: np.ndarray, faces: np.ndarray, space: str = "LPS") -> BoneFrame:
    """The :class:`BoneFrame` of a triangle mesh (see the module docstring for the rules)."""
    vertices = np.asarray(vertices, np.float64)
    tri = vertices[np.asarray(faces)]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) / 2
    total = area.sum()
    if not np.isfinite(total) or total <= 0:
        raise InvalidGeometryError("The CT mesh has no area, so no camera can be placed for it.",
                                   "Check that the mesh is a bone surface in mm.")
    centroids = tri.mean(axis=1)
    center = (area[:, None] * centroids).sum(0) / total
    d = centroids - center
    cov = (area[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) / total
    values, vectors = np.linalg.eigh(cov)
    order = np.argsort(values)[::-1]
    values, vectors = values[order], vectors[:, order].T  # rows: principal axes, largest first
    patient = patient_directions(space)
    sup, ant = patient["superior"], patient["anterior"]
    from_pca = bool(values[0] >= ELONGATION_MIN * max(values[1], 1e-12))
    axis = _signed(vectors[0], sup) if from_pca else sup.copy()
    anterior = ant - (ant @ axis) * axis
    if np.linalg.norm(anterior) < ANTERIOR_MIN:
        # Bone axis close to anterior-posterior: take the principal axis (2nd or 3rd) closest to
        # anterior, off the bone axis.
        candidates = [v - (v @ axis) * axis for v in vectors[1:]]
        anterior = max(candidates, key=lambda v: abs(v @ ant))
        anterior = _signed(anterior, ant)
    anterior = anterior / np.linalg.norm(anterior)
    left = np.cross(axis, anterior)
    return BoneFrame(center, axis, anterior, left / np.linalg.norm(left), values,
                     check_space(space), from_pca)


def _signed(v: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """``v`` or ``-v``, whichever points towards ``towards`` (ties: largest component positive)."""
    dot = float(v @ towards)
    if abs(dot) < 1e-9:
        dot = float(v[np.argmax(np.abs(v))])
    return v if dot >= 0 else -v


@dataclass(frozen=True)
class ViewPreset:
    """A camera orientation: ``direction`` from the focal point towards the camera (unit) and the
    screen's ``view_up`` (unit, orthogonal to it), both in the CT mesh's space."""

    name: str
    direction: np.ndarray
    view_up: np.ndarray
    description: str


def view_presets(frame: BoneFrame, lateral_side: str = "left") -> dict[str, ViewPreset]:
    """The ``anterior``, ``lateral`` and ``bone_axis`` presets of a bone (module docstring)."""
    if lateral_side not in ("left", "right"):
        raise ValueError(f"lateral_side must be 'left' or 'right', not {lateral_side!r}")
    b, a, left = frame.axis, frame.anterior, frame.left
    side = left if lateral_side == "left" else -left
    anterior_on = "left" if lateral_side == "left" else "right"
    return {
        "anterior": ViewPreset("anterior", a, b,
                               "Anterior: seen from the front, superior up, the patient's right "
                               "on the image left."),
        "lateral": ViewPreset("lateral", side, b,
                              f"Lateral: seen from the patient's {lateral_side}, superior up, "
                              f"anterior on the image {anterior_on}."),
        "bone_axis": ViewPreset("bone_axis", -b, a,
                                "Along the bone axis: seen from the inferior end looking superior, "
                                "anterior up, the patient's left on the image right."),
    }


@dataclass(frozen=True)
class CameraView:
    """A parallel-projection camera for one screenshot.

    Attributes:
        name: preset name.
        focal_point, position, view_up: VTK camera settings (mm, in the CT mesh's space).
        parallel_scale: half the image height in mm (VTK's ParallelScale).
        window_size: ``(width, height)`` in pixels.
        space: the patient space of the coordinates.
    """

    name: str
    focal_point: np.ndarray
    position: np.ndarray
    view_up: np.ndarray
    parallel_scale: float
    window_size: tuple[int, int]
    space: str = "LPS"

    @property
    def direction_of_projection(self) -> np.ndarray:
        d = self.focal_point - self.position
        return d / np.linalg.norm(d)

    @property
    def screen_right(self) -> np.ndarray:
        r = np.cross(self.direction_of_projection, self.view_up)
        return r / np.linalg.norm(r)

    @property
    def mm_per_pixel(self) -> float:
        return 2.0 * self.parallel_scale / self.window_size[1]

    def project(self, points: np.ndarray) -> np.ndarray:
        """``(N, 2)`` pixel coordinates ``(column, row)`` of ``(N, 3)`` points, row 0 at the top of
        the image (as in the PNG and the screenshot array); pixel ``(c, r)`` covers
        ``[c, c + 1) x [r, r + 1)``."""
        d = np.asarray(points, np.float64).reshape(-1, 3) - self.focal_point
        width, height = self.window_size
        k = 1.0 / self.mm_per_pixel
        col = width / 2.0 + (d @ self.screen_right) * k
        row = height / 2.0 - (d @ self.view_up) * k
        return np.stack([col, row], axis=1)

    def orientation_labels(self) -> dict[str, str]:
        """Patient-direction letters at the ``right``, ``left``, ``top`` and ``bottom`` image
        edges (e.g. ``{"right": "L", "left": "R", "top": "S", "bottom": "I"}``); two letters when
        the edge direction is oblique (second component > 0.38, ~22 deg), like DICOM viewers."""
        patient = patient_directions(self.space)
        right, up = self.screen_right, self.view_up
        return {"right": _letters(right, patient), "left": _letters(-right, patient),
                "top": _letters(up, patient), "bottom": _letters(-up, patient)}

    def apply(self, renderer) -> None:
        """Put this camera on a VTK/pyvista renderer (and reset its clipping range)."""
        camera = renderer.GetActiveCamera()
        camera.ParallelProjectionOn()
        camera.SetFocalPoint(*self.focal_point)
        camera.SetPosition(*self.position)
        camera.SetViewUp(*self.view_up)
        camera.SetParallelScale(self.parallel_scale)
        renderer.ResetCameraClippingRange()


def _letters(v: np.ndarray, patient: dict[str, np.ndarray]) -> str:
    names = (("L", "R", patient["left"]), ("A", "P", patient["anterior"]),
             ("S", "I", patient["superior"]))
    parts = sorted(((abs(v @ axis), pos if v @ axis >= 0 else neg) for pos, neg, axis in names),
                   reverse=True)
    letters = parts[0][1]
    if parts[1][0] > 0.38:
        letters += parts[1][1]
    return letters


#: Default content rectangle ``(left, bottom, right, top)`` as fractions of the window: the part
#: kept free of the title, legend and orientation letters.
CONTENT_BOX = (0.06, 0.06, 0.94, 0.86)


def frame_points(preset: ViewPreset, points: np.ndarray, window_size: tuple[int, int], *,
                 content: tuple[float, float, float, float] = CONTENT_BOX, margin: float = 0.04,
                 space: str = "LPS") -> CameraView:
    """The :class:`CameraView` looking along ``preset`` that fits ``points`` ``(N, 3)`` into the
    ``content`` rectangle of a ``window_size`` image (with ``margin`` of it left free each side),
    centred there, at the largest scale that fits."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0:
        raise InvalidGeometryError("Nothing to frame in the view.", "Pass a non-empty CT mesh.")
    width, height = (int(window_size[0]), int(window_size[1]))
    x0, y0, x1, y1 = content
    direction = preset.direction / np.linalg.norm(preset.direction)
    up = preset.view_up - (preset.view_up @ direction) * direction
    up /= np.linalg.norm(up)
    right = np.cross(-direction, up)
    c0 = points.mean(axis=0)
    u, v = (points - c0) @ right, (points - c0) @ up
    span_u = max(float(u.max() - u.min()), 1e-6) * (1 + 2 * margin)
    span_v = max(float(v.max() - v.min()), 1e-6) * (1 + 2 * margin)
    aspect = width / height
    scale = max(span_v / (2 * (y1 - y0)), span_u / (2 * aspect * (x1 - x0)))
    # Shift the focal point so that the middle of the points lands in the middle of the content box.
    du = ((x0 + x1) / 2 - 0.5) * 2 * scale * aspect
    dv = ((y0 + y1) / 2 - 0.5) * 2 * scale
    u_mid, v_mid = (u.max() + u.min()) / 2, (v.max() + v.min()) / 2
    focal = c0 + right * (u_mid - du) + up * (v_mid - dv)
    radius = float(np.linalg.norm(points - focal, axis=1).max())
    position = focal + direction * (2.0 * radius + 1.0)
    return CameraView(preset.name, focal, position, up, float(scale), (width, height),
                      check_space(space))
