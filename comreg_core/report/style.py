"""How the report's pictures look: colours, the viridis distance map, sizes, the pyvista theme.

Colours are 0-255 sRGB triples. Distances to the CT surface (mm) are shown with one map
everywhere (3D scenes, CT cross-sections, scalar bars): viridis over
:attr:`Style.distance_range_mm`, dark purple = on the surface, yellow = at or beyond the top.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Colours as 0-255 sRGB. Vermillion and blue are the Okabe-Ito colour-blind-safe pair.
BONE_RGB = (241, 214, 145)  # 3D Slicer's "bone" colour
US_BEFORE_RGB = (213, 94, 0)  # vermillion
US_AFTER_RGB = (0, 114, 178)  # blue
SCAN_NEXT_RGB = (204, 121, 167)  # reddish purple (Okabe-Ito)
BACKGROUND_RGB = (255, 255, 255)
TEXT_RGB = (20, 20, 20)

#: Viridis (matplotlib's, sampled every 16 of its 256 entries and at the end): perceptually
#: uniform, readable in grey and by colour-blind viewers; dark purple = 0 mm, yellow = far.
VIRIDIS_ANCHORS = np.array([
    (0.2670, 0.0049, 0.3294), (0.2823, 0.0950, 0.4173), (0.2788, 0.1755, 0.4834),
    (0.2590, 0.2515, 0.5247), (0.2297, 0.3224, 0.5457), (0.1994, 0.3876, 0.5546),
    (0.1727, 0.4488, 0.5579), (0.1490, 0.5081, 0.5572), (0.1276, 0.5669, 0.5506),
    (0.1206, 0.6258, 0.5335), (0.1579, 0.6838, 0.5017), (0.2461, 0.7389, 0.4520),
    (0.3692, 0.7889, 0.3829), (0.5160, 0.8312, 0.2943), (0.6785, 0.8637, 0.1895),
    (0.8456, 0.8873, 0.0997), (0.9932, 0.9062, 0.1439)])


def colormap_rgb(t: np.ndarray) -> np.ndarray:
    """Viridis colours ``(N, 3)`` (0-255 float) at ``t`` in [0, 1] (clipped), linear between
    anchors: the same table the rendered lookup table uses."""
    t = np.clip(np.asarray(t, np.float64), 0.0, 1.0)
    x = np.linspace(0.0, 1.0, len(VIRIDIS_ANCHORS))
    return np.stack([np.interp(t, x, VIRIDIS_ANCHORS[:, k]) for k in range(3)], axis=-1) * 255.0


@dataclass(frozen=True)
class Style:
    """Everything about how scenes look; the defaults are what reports use.

    Attributes:
        bone_opacity: opacity of the CT mesh (semi-transparent so points behind it show).
        distance_range_mm: colour range of the completion's distance to the CT; beyond the top
            is drawn in the top colour.
        point_size_fraction: US point diameter as a fraction of the image height (>= 3 pixels).
        completion_point_size_fraction: the same for completion points.
        font_fraction: text height as a fraction of the image height.
    """

    bone_rgb: tuple[int, int, int] = BONE_RGB
    bone_opacity: float = 0.5
    us_before_rgb: tuple[int, int, int] = US_BEFORE_RGB
    us_after_rgb: tuple[int, int, int] = US_AFTER_RGB
    scan_next_rgb: tuple[int, int, int] = SCAN_NEXT_RGB
    background_rgb: tuple[int, int, int] = BACKGROUND_RGB
    text_rgb: tuple[int, int, int] = TEXT_RGB
    distance_range_mm: tuple[float, float] = (0.0, 5.0)
    point_size_fraction: float = 1 / 130
    completion_point_size_fraction: float = 1 / 170
    font_fraction: float = 1 / 42


DEFAULT_STYLE = Style()


def unit_rgb(rgb) -> tuple[float, float, float]:
    """A 0-255 colour as VTK's 0-1 floats."""
    return tuple(float(c) / 255.0 for c in rgb)


def make_theme(style: Style = DEFAULT_STYLE):
    """A pyvista theme for reproducible screenshots: plain background, no anti-aliasing (MSAA and
    FXAA output differs between OpenGL drivers), no edges, smooth shading, fixed fonts."""
    import pyvista as pv

    theme = pv.themes.DocumentTheme()
    theme.background = unit_rgb(style.background_rgb)
    theme.font.color = unit_rgb(style.text_rgb)
    theme.font.family = "arial"
    theme.anti_aliasing = None
    theme.multi_samples = 0
    theme.smooth_shading = True
    theme.show_edges = False
    theme.lighting = True
    theme.render_points_as_spheres = True
    return theme


def lookup_table(style: Style = DEFAULT_STYLE):
    """The distance map as a pyvista lookup table: 256 viridis entries (0-255 RGBA) over
    ``style.distance_range_mm`` (mm)."""
    import pyvista as pv

    lut = pv.LookupTable()
    lut.values = np.concatenate(
        [np.round(colormap_rgb(np.linspace(0, 1, 256))), np.full((256, 1), 255.0)],
        axis=1).astype(np.uint8)
    lut.scalar_range = tuple(float(v) for v in style.distance_range_mm)
    return lut
