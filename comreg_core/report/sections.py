"""Cross-sections of a registration: the usual 2D check of a US–CT registration.

* :func:`frame_overlays` (a tracked sweep is known): a few of the sweep's B-mode frames with the
  registered CT bone's contour in the frame's plane drawn in. Right: the contour runs along the
  bright bone echo, with the acoustic shadow below it. Wrong: it crosses the image elsewhere.
* :func:`ct_sections` (any point cloud): CT cuts across the bone's long axis at the registered
  points' quartiles, with the registered points within +-1 mm of each cut, coloured by their
  distance to the CT surface (the report's 0-5 mm viridis map, with a colour bar in mm).

Every picture has a scale bar (a round number of mm) and is drawn with Pillow: plain 2D
drawing, no OpenGL, identical pixels on every machine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comreg_core.io.meshes import SurfaceMesh
from comreg_core.report.cameras import BoneFrame
from comreg_core.report.style import DEFAULT_STYLE, Style, colormap_rgb
from comreg_core.transforms import apply_transform, invert_rigid

#: Registered points at most this far from a CT cut are drawn on it (mm).
SECTION_HALF_WIDTH_MM = 1.0
#: Where along the registered points' span (fractions, by quantile) the CT is cut.
SECTION_QUANTILES = (0.25, 0.5, 0.75)
#: The CT contour on B-mode frames: Okabe-Ito yellow, visible on grey.
CONTOUR_ON_FRAME_RGB = (240, 228, 66)
#: The CT contour on a white CT cut.
CONTOUR_RGB = (90, 70, 40)


@dataclass(frozen=True)
class SectionPicture:
    """One 2D picture: ``image`` ``(H, W, 3)`` uint8, a file ``name`` stem, a ``title`` and a
    ``caption`` for the page, and what it shows in numbers: ``n_points`` registered points drawn
    (cuts; 0 for frames), ``contour_points`` ``(K, 2)`` pixel (x, y) samples of the CT contour."""

    image: np.ndarray
    name: str
    title: str
    caption: str
    n_points: int
    contour_points: np.ndarray


def plane_contour(ct, origin: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """``(S, 2, 3)`` line segments (mm) where the plane through ``origin`` with ``normal`` cuts
    the CT surface (a SurfaceMesh, or its ``pyvista.PolyData`` to cut it several times; VTK's
    cutter through PyVista); ``(0, 2, 3)`` when it misses the bone."""
    import pyvista as pv

    mesh = ct if isinstance(ct, pv.PolyData) else _polydata(ct)
    cut = mesh.slice(normal=tuple(np.asarray(normal, float)), origin=tuple(np.asarray(origin, float)))
    if cut.n_points == 0 or cut.n_lines == 0:
        return np.zeros((0, 2, 3))
    points, lines = np.asarray(cut.points, float), np.asarray(cut.lines)
    segments, i = [], 0
    while i < len(lines):
        n = int(lines[i])
        ids = lines[i + 1:i + 1 + n]
        segments.extend(zip(ids[:-1], ids[1:]))
        i += n + 1
    index = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    return points[index]


def ct_sections(ct: SurfaceMesh, frame: BoneFrame, points_ct: np.ndarray,
                distances_mm: np.ndarray, *, size_px: int = 480,
                style: Style = DEFAULT_STYLE) -> list[SectionPicture]:
    """CT cuts across the long axis at :data:`SECTION_QUANTILES` of the registered points'
    positions along it.

    Args:
        ct: the CT bone surface (patient space, mm).
        frame: the bone's frame (:func:`~comreg_core.report.cameras.bone_frame`): cuts are
            normal to ``frame.axis``; seen from inferior, anterior up, the patient's left on the
            image right (as the report's bone-axis view).
        points_ct: ``(N, 3)`` registered US points in the CT (mm).
        distances_mm: ``(N,)`` their distances to the CT surface (mm), for the colours.
        size_px: image width and height (pixels).
    """
    points_ct = np.asarray(points_ct, float).reshape(-1, 3)
    distances_mm = np.asarray(distances_mm, float).reshape(-1)
    along = (points_ct - frame.center) @ frame.axis
    mesh = _polydata(ct)
    pictures = []
    for q in SECTION_QUANTILES:
        level = float(np.quantile(along, q))
        origin = frame.center + level * frame.axis
        segments = plane_contour(mesh, origin, frame.axis)
        near = np.abs(along - level) <= SECTION_HALF_WIDTH_MM
        # image x = patient left, image y (down) = posterior
        to_plane = np.stack([frame.left, -frame.anterior])
        seg2 = (segments - origin) @ to_plane.T
        pts2 = (points_ct[near] - origin) @ to_plane.T
        image, contour = _draw_cut(seg2, pts2, distances_mm[near], size_px, style)
        pictures.append(SectionPicture(
            image, f"section_{int(round(q * 100)):02d}",
            f"CT cut at {int(round(q * 100))} % of the sweep's length",
            f"The CT bone cut across its long axis {level:+.1f} mm from the bone's centre "
            f"(seen from inferior, anterior up, the patient's left on the right), with the "
            f"{int(near.sum())} registered US points within +-{SECTION_HALF_WIDTH_MM:g} mm of "
            "the cut, coloured by their distance to the CT surface. Right: the points sit on the "
            "contour, dark purple.", int(near.sum()), contour))
    return pictures


def frame_overlays(frames: np.ndarray, T_ct_pixel: np.ndarray, spacing: np.ndarray,
                   ct: SurfaceMesh, frame_names: list[str]) -> list[SectionPicture]:
    """B-mode frames with the registered CT bone contour in each frame's plane.

    Args:
        frames: ``(F, H, W)`` B-mode pixel values (uint8; others are scaled to 0-255).
        T_ct_pixel: ``(F, 4, 4)`` pixel index ``(col, row, 0, 1)`` -> CT mm under the
            registration (``T_ct_us @ T_us_ref @ sweep.T_ref_pixel``).
        spacing: ``(2,)`` pixel size (mm) along columns and rows, for the scale bar.
        ct: the CT bone surface (mm, the space ``T_ct_pixel`` maps into).
        frame_names: ``F`` labels for the titles.
    """
    from PIL import Image, ImageDraw

    mesh = _polydata(ct)
    pictures = []
    for image, T, label in zip(frames, T_ct_pixel, frame_names):
        grey = np.asarray(image, np.float64)
        if np.asarray(image).dtype != np.uint8 and grey.max() > 255:
            grey = grey * (255.0 / grey.max())
        canvas = Image.fromarray(np.clip(grey, 0, 255).astype(np.uint8)).convert("RGB")
        normal = T[:3, 2] / np.linalg.norm(T[:3, 2])
        segments = plane_contour(mesh, T[:3, 3], normal)
        pixel = apply_transform(invert_rigid_pixel(T), segments.reshape(-1, 3))[:, :2]
        draw = ImageDraw.Draw(canvas)
        width = max(2, round(canvas.width / 250))
        for a, b in pixel.reshape(-1, 2, 2):
            draw.line([tuple(a), tuple(b)], fill=CONTOUR_ON_FRAME_RGB, width=width)
        _scale_bar(draw, canvas.size, 1.0 / float(spacing[0]), (255, 255, 255))
        pictures.append(SectionPicture(
            np.asarray(canvas), f"frame_{label}", f"US frame {label}",
            f"B-mode frame {label} as recorded (transducer at the top), with the registered CT "
            "bone's contour in the frame's plane (yellow). Right: the contour runs along the "
            "bright bone echo, the dark acoustic shadow below it.", 0, _contour_samples(pixel)))
    return pictures


def invert_rigid_pixel(T_ct_pixel: np.ndarray) -> np.ndarray:
    """The inverse of a pixel -> mm map whose first two columns are scaled (pixel size) and
    third is the unit plane normal: CT mm -> ``(col, row, out-of-plane mm)``."""
    scale = np.linalg.norm(T_ct_pixel[:3, :3], axis=0)
    rigid = T_ct_pixel.copy()
    rigid[:3, :3] = T_ct_pixel[:3, :3] / scale
    return np.diag([1.0 / scale[0], 1.0 / scale[1], 1.0, 1.0]) @ invert_rigid(rigid)


def _polydata(ct: SurfaceMesh):
    import pyvista as pv

    return pv.PolyData.from_regular_faces(ct.vertices, ct.faces)


# --- drawing ------------------------------------------------------------------------------------

def _contour_samples(pixel_segments: np.ndarray, step_px: float = 1.0) -> np.ndarray:
    """``(K, 2)`` points every ``step_px`` along the segments ``(S*2, 2)`` (pixels)."""
    segs = np.asarray(pixel_segments, float).reshape(-1, 2, 2)
    out = [np.zeros((0, 2))]
    for a, b in segs:
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / step_px)) + 1)
        out.append(a + (b - a) * np.linspace(0.0, 1.0, n)[:, None])
    return np.concatenate(out)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType sizes
        return ImageFont.load_default()


def _scale_bar(draw, size: tuple[int, int], px_per_mm: float, rgb) -> None:
    """A round length (mm) about a sixth of the width, lower left, with its label."""
    width, height = size
    target_mm = width / 6 / px_per_mm
    length = max(v for v in (1, 2, 5, 10, 20, 50, 100) if v <= max(target_mm, 1))
    x0, y0 = 0.04 * width, 0.94 * height
    bar = max(2, round(height / 200))
    draw.line([(x0, y0), (x0 + length * px_per_mm, y0)], fill=rgb, width=bar)
    draw.text((x0, y0 - 6 - height / 30), f"{length:g} mm", fill=rgb,
              font=_font(max(10, height // 30)))


def _colour_bar(draw, size: tuple[int, int], style: Style) -> None:
    """The 0-5 mm distance colour bar, lower right, labelled in mm."""
    width, height = size
    lo, hi = style.distance_range_mm
    x0, x1, y0 = 0.58 * width, 0.95 * width, 0.93 * height
    thick = max(6, height // 40)
    steps = 64
    colours = colormap_rgb(np.linspace(0, 1, steps))
    for k in range(steps):
        xa = x0 + (x1 - x0) * k / steps
        draw.rectangle([xa, y0, xa + (x1 - x0) / steps + 1, y0 + thick],
                       fill=tuple(int(c) for c in colours[k]))
    font = _font(max(10, height // 32))
    draw.text((x0, y0 - height / 28), f"{lo:g}", fill=style.text_rgb, font=font)
    draw.text((x1 - width / 12, y0 - height / 28), f"{hi:g} mm", fill=style.text_rgb, font=font)


def _draw_cut(segments: np.ndarray, points: np.ndarray, distances: np.ndarray, size_px: int,
              style: Style) -> tuple[np.ndarray, np.ndarray]:
    """Draw one cut (contour segments ``(S, 2, 2)`` and points ``(P, 2)`` in plane mm)."""
    from PIL import Image, ImageDraw

    everything = np.concatenate([segments.reshape(-1, 2), points.reshape(-1, 2)])
    if len(everything) == 0:
        everything = np.zeros((1, 2))
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    centre = (lo + hi) / 2.0
    extent = max(float((hi - lo).max()) * 1.25, 20.0)  # mm across the image
    px_per_mm = 0.8 * size_px / extent

    def to_px(xy):
        return (np.asarray(xy, float) - centre) * px_per_mm + size_px / 2.0

    canvas = Image.new("RGB", (size_px, size_px), style.background_rgb)
    draw = ImageDraw.Draw(canvas)
    pixel = to_px(segments.reshape(-1, 2))
    for a, b in pixel.reshape(-1, 2, 2):
        draw.line([tuple(a), tuple(b)], fill=CONTOUR_RGB, width=max(2, size_px // 200))
    lo_mm, hi_mm = style.distance_range_mm
    colours = colormap_rgb((distances - lo_mm) / (hi_mm - lo_mm))
    radius = max(3, size_px // 110)
    for (x, y), colour in zip(to_px(points.reshape(-1, 2)), colours):
        draw.ellipse([x - radius, y - radius, x + radius, y + radius],
                     fill=tuple(int(c) for c in colour), outline=(40, 40, 40))
    font = _font(max(12, size_px // 28))
    half = size_px / 2
    draw.text((half, 6), "A", fill=style.text_rgb, font=font)
    draw.text((half, size_px * 0.86), "P", fill=style.text_rgb, font=font)
    draw.text((6, half), "R", fill=style.text_rgb, font=font)
    draw.text((size_px - 6 - size_px // 28, half), "L", fill=style.text_rgb, font=font)
    _scale_bar(draw, canvas.size, px_per_mm, style.text_rgb)
    _colour_bar(draw, canvas.size, style)
    return np.asarray(canvas), _contour_samples(pixel)
