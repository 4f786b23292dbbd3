"""Overlay scenes rendered off screen: CT mesh, US points before/after registration, completion.

Every coordinate is in the CT mesh's patient space (LPS or RAS, mm); the US points are expected
already in that frame ("before": as received, i.e. under the initial pose; "after": mapped by the
estimated ``T_ct_us``). Rendering is deterministic: a fixed window size, fixed colours
(:mod:`comreg_core.report.style`), parallel projection with fixed presets
(:mod:`comreg_core.report.cameras`), no anti-aliasing, no random anything, and a theme of its own
(the process-wide pyvista theme is neither read nor changed).

Scenes (:data:`SCENES`):

* ``registered``: CT + US points after registration coloured by their distance to the CT
  surface (the same 0-5 mm viridis map and colour bar in every view: a wrong registration shows
  green-yellow points), framed on the CT: do the points sit on the bone?
* ``overlay``: CT + US points before (vermillion) and after (blue) registration, framed on all of
  them: where did the points start and where did they go?
* ``completion``: CT + the completed bone coloured by its distance to the CT surface (mm, viridis:
  dark purple = on the surface, yellow = at or beyond the top of the range), with a scalar bar.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from comreg_core.io.meshes import SurfaceMesh
from comreg_core.registration.geometry.surface import CTSurface
from comreg_core.report.backend import ensure_offscreen_rendering
from comreg_core.report.cameras import (VIEW_NAMES, BoneFrame, CameraView, bone_frame,
                                        frame_points, view_presets)
from comreg_core.report.style import DEFAULT_STYLE, Style, lookup_table, make_theme, unit_rgb
from comreg_core.transforms import as_points

log = logging.getLogger(__name__)

SCENES = ("registered", "overlay", "completion")


@dataclass
class SceneData:
    """The inputs of the scenes, checked, in the CT mesh's space.

    Attributes:
        ct: the CT bone surface.
        us_before, us_after: ``(N, 3)`` US points before/after registration, or None.
        completion: ``(M, 3)`` completed bone points, or None.
        completion_distance_mm: ``(M,)`` unsigned distance of each completion point to the CT
            surface (computed if not given).
        us_after_distance_mm: ``(N,)`` the same for the registered US points.
        scan_next: ``(3,)`` the CT point to scan next (drawn in the ``registered`` scene), or
            None.
    """

    ct: SurfaceMesh
    us_before: np.ndarray | None = None
    us_after: np.ndarray | None = None
    completion: np.ndarray | None = None
    completion_distance_mm: np.ndarray | None = None
    us_after_distance_mm: np.ndarray | None = None
    scan_next: np.ndarray | None = None
    frame: BoneFrame = field(init=False)

    def __post_init__(self) -> None:
        if not isinstance(self.ct, SurfaceMesh):
            raise TypeError(f"ct must be a SurfaceMesh, not {type(self.ct).__name__}")
        self.us_before = _points_or_none(self.us_before, "US points before registration")
        self.us_after = _points_or_none(self.us_after, "US points after registration")
        self.completion = _points_or_none(self.completion, "completion points")
        surface = CTSurface((self.ct.vertices, self.ct.faces))
        if self.completion is not None and self.completion_distance_mm is None:
            self.completion_distance_mm = surface.distance(self.completion)
        if self.us_after is not None and self.us_after_distance_mm is None:
            self.us_after_distance_mm = surface.distance(self.us_after)
        if self.completion_distance_mm is not None:
            self.completion_distance_mm = np.asarray(self.completion_distance_mm, np.float64)
            n = None if self.completion is None else len(self.completion)
            if self.completion_distance_mm.shape != (n,):
                raise ValueError("completion_distance_mm needs one value per completion point")
        self.frame = bone_frame(self.ct.vertices, self.ct.faces, self.ct.space)

    def available_scenes(self) -> list[str]:
        """The :data:`SCENES` these inputs can show (``["ct"]`` when there are no points)."""
        scenes = []
        if self.us_after is not None:
            scenes.append("registered")
        if self.us_before is not None:
            scenes.append("overlay")
        if self.completion is not None:
            scenes.append("completion")
        return scenes or ["ct"]


def _points_or_none(points, what: str) -> np.ndarray | None:
    if points is None:
        return None
    points = as_points(points, what)
    return points if len(points) else None


@dataclass(frozen=True)
class Screenshot:
    """One rendered image: ``image`` ``(H, W, 3)`` uint8, the scene and the camera it used."""

    scene: str
    view: str
    image: np.ndarray
    camera: CameraView


SCAN_NEXT_RADIUS_MM = 7.5  #: radius (mm) of the patch to scan next as drawn (half a patch)
#: Along the bone axis, a whole long bone projects onto itself; the CT is cut to the span of the
#: registered US points along the axis, extended by this much each side (mm).
SLAB_MARGIN_MM = 15.0

# Layout as fractions of the window (VTK viewport coordinates, y up): the content box the camera
# frames into keeps clear of the title (upper left), legend (upper right), orientation letters
# (edge middles) and scalar bar (bottom).
_CONTENT = (0.07, 0.07, 0.93, 0.86)
_CONTENT_WITH_BAR = (0.07, 0.17, 0.93, 0.86)


class SceneRenderer:
    """Builds one scene in an off-screen pyvista plotter and screenshots it from each preset.

    Use as a context manager (the plotter and its OpenGL context are released on exit)::

        with SceneRenderer(data, "registered", window_size=(800, 800)) as scene:
            shot = scene.screenshot("anterior")

    In the ``bone_axis`` view of the ``registered`` and ``overlay`` scenes the CT mesh is cut to
    the span of the registered US points along the bone axis +- :data:`SLAB_MARGIN_MM`, so the
    cross-section they lie on is visible (a whole long bone seen end-on is a blur of overlapping
    translucent layers); the image title says so.

    Raises:
        OpenGLUnavailableError: (on construction) no off-screen OpenGL backend works.
    """

    def __init__(self, data: SceneData, scene: str, *, window_size: tuple[int, int] = (800, 800),
                 style: Style = DEFAULT_STYLE, lateral_side: str = "left",
                 show_text: bool = True):
        if scene not in SCENES + ("ct",):
            raise ValueError(f"unknown scene {scene!r}; one of {SCENES + ('ct',)}")
        ensure_offscreen_rendering()  # before the first VTK render window of the process
        import pyvista as pv

        self.data, self.scene, self.style = data, scene, style
        self.window_size = (int(window_size[0]), int(window_size[1]))
        self.show_text = show_text
        self.lateral_side = lateral_side
        self.presets = view_presets(data.frame, lateral_side)
        height = self.window_size[1]
        self._font = max(6, int(round(height * style.font_fraction)))
        self.plotter = pv.Plotter(off_screen=True, window_size=list(self.window_size),
                                  theme=make_theme(style), lighting="light kit")
        self._build(pv)

    # --- the scene ----------------------------------------------------------------------------
    def _build(self, pv) -> None:
        data, style, p = self.data, self.style, self.plotter
        height = self.window_size[1]
        ct = data.ct.to_pyvista()
        bone = dict(color=unit_rgb(style.bone_rgb), opacity=style.bone_opacity, smooth_shading=True,
                    specular=0.2)
        self._ct_actor = p.add_mesh(ct, name="ct", **bone)
        legend = [("CT bone surface", style.bone_rgb)]
        point_sets = []
        point_px = max(3.0, height * style.point_size_fraction)
        if self.scene == "overlay":
            p.add_points(data.us_before, color=unit_rgb(style.us_before_rgb), point_size=point_px,
                         render_points_as_spheres=True, name="us_before")
            point_sets.append(data.us_before)
            legend.append((f"US before registration ({len(data.us_before)})",
                           style.us_before_rgb))
        if self.scene == "registered" and data.us_after is not None:
            self._distance_points(pv, data.us_after, data.us_after_distance_mm, point_px,
                                  "US points: distance to the CT surface", "us_after")
            point_sets.append(data.us_after)
        if self.scene == "registered" and data.scan_next is not None:
            centre = np.asarray(data.scan_next, dtype=np.float64)
            p.add_mesh(pv.Sphere(radius=SCAN_NEXT_RADIUS_MM, center=centre), name="scan_next",
                       color=unit_rgb(style.scan_next_rgb), opacity=0.85)
            point_sets.append(centre[None])
            legend.append(("Scan next here", style.scan_next_rgb))
        if self.scene == "overlay" and data.us_after is not None:
            p.add_points(data.us_after, color=unit_rgb(style.us_after_rgb), point_size=point_px,
                         render_points_as_spheres=True, name="us_after")
            point_sets.append(data.us_after)
            legend.append((f"US after registration ({len(data.us_after)})", style.us_after_rgb))
        if self.scene == "completion":
            self._distance_points(pv, data.completion, data.completion_distance_mm,
                                  max(3.0, height * style.completion_point_size_fraction),
                                  "Completion: distance to CT surface", "completion")
            point_sets.append(data.completion)
        self._point_sets = point_sets
        self._slab_actor, self._slab_vertices = None, None
        slab = self._slab(ct)
        if slab is not None:
            self._slab_actor = p.add_mesh(slab, name="ct_slab", **bone)
            self._slab_actor.SetVisibility(False)
            self._slab_vertices = np.asarray(slab.points, np.float64)
        if self.show_text:
            self._add_legend(legend)
        self._content = (_CONTENT_WITH_BAR if self.scene in ("completion", "registered")
                         else _CONTENT)

    def _distance_points(self, pv, points, distance_mm, size_px: float, title: str, name: str):
        """Points coloured by their distance to the CT (the one fixed 0-5 mm map), with a
        horizontal colour bar in mm at the bottom."""
        cloud = pv.PolyData(points)
        cloud["distance_mm"] = distance_mm
        lo, hi = self.style.distance_range_mm
        self.plotter.add_mesh(
            cloud, scalars="distance_mm", cmap=lookup_table(self.style), clim=(lo, hi),
            point_size=size_px, render_points_as_spheres=True, name=name,
            show_scalar_bar=self.show_text,
            scalar_bar_args=dict(
                title=f"{title} (mm; >= {hi:g} in yellow)", vertical=False, position_x=0.2,
                position_y=0.015, width=0.6, height=0.085, n_labels=6, fmt="%.1f",
                color=unit_rgb(self.style.text_rgb), title_font_size=self._font,
                label_font_size=self._font, bold=False, shadow=False))

    def _slab(self, ct):
        """The CT cut to the registered US points' span along the bone axis, or None."""
        if self.scene not in ("registered", "overlay") or self.data.us_after is None:
            return None
        frame = self.data.frame
        t_points = (self.data.us_after - frame.center) @ frame.axis
        ct = ct.copy()
        ct["t"] = (np.asarray(ct.points) - frame.center) @ frame.axis
        slab = ct.clip_scalar(scalars="t", value=float(t_points.max()) + SLAB_MARGIN_MM,
                              invert=True)
        if slab.n_points:
            slab = slab.clip_scalar(scalars="t", value=float(t_points.min()) - SLAB_MARGIN_MM,
                                    invert=False)
        return slab.extract_surface(algorithm="dataset_surface") if slab.n_points else None

    # --- cameras and screenshots --------------------------------------------------------------
    def _uses_slab(self, view: str) -> bool:
        return view == "bone_axis" and self._slab_actor is not None

    def camera(self, view: str) -> CameraView:
        """The camera of ``view`` (a preset name) for this scene's framing."""
        if view not in self.presets:
            raise ValueError(f"unknown view {view!r}; one of {tuple(self.presets)}")
        bone = self._slab_vertices if self._uses_slab(view) else self.data.ct.vertices
        points = np.concatenate([bone, *self._point_sets], axis=0)
        return frame_points(self.presets[view], points, self.window_size, content=self._content,
                            space=self.data.ct.space)

    def screenshot(self, view: str) -> Screenshot:
        """Render from preset ``view`` and return the image with its camera."""
        camera = self.camera(view)
        slab = self._uses_slab(view)
        self._ct_actor.SetVisibility(not slab)
        if self._slab_actor is not None:
            self._slab_actor.SetVisibility(slab)
        camera.apply(self.plotter.renderer)
        self.plotter.camera_set = True  # else pyvista resets the camera on the first render
        if self.show_text:
            self._set_text(camera)
        image = self.plotter.screenshot(return_img=True, window_size=list(self.window_size))
        image = np.ascontiguousarray(np.asarray(image)[..., :3], dtype=np.uint8)
        return Screenshot(self.scene, view, image, camera)

    def view_title(self, view: str) -> str:
        """The title written on the screenshots of ``view`` (also the report's caption)."""
        titles = {"anterior": "Anterior view",
                  "lateral": f"Lateral view, from the patient's {self.lateral_side}",
                  "bone_axis": "Along the bone axis, from inferior"}
        title = titles.get(view, view)
        if self._uses_slab(view):
            title += f"\nCT cut to the US span +-{SLAB_MARGIN_MM:g} mm"
        return title

    def _text(self, text: str, x: float, y: float, *, size: int, name: str, halign: str = "left",
              valign: str = "bottom", rgb=None):
        """A text ``size`` pixels high at pixel ``(x, y)`` (from the lower left), replacing any
        text called ``name``; returns the vtkTextActor."""
        actor = self.plotter.add_text(text, position=(int(round(x)), int(round(y))),
                                      font_size=size, name=name,
                                      color=unit_rgb(rgb or self.style.text_rgb))
        prop = actor.GetTextProperty()
        prop.SetFontSize(int(size))  # pyvista doubles font_size for positioned text
        prop.SetJustification({"left": 0, "center": 1, "right": 2}[halign])
        prop.SetVerticalJustification({"bottom": 0, "center": 1, "top": 2}[valign])
        prop.SetLineSpacing(1.15)
        return actor

    def _add_legend(self, entries: list[tuple[str, tuple[int, int, int]]]) -> None:
        """Upper-right legend: a filled disc in each colour and its label in the text colour
        (VTK's legend box scales its text to the box and writes it in the entry colour)."""
        import vtk

        width, height = self.window_size
        font = self._font
        row, radius, margin = 1.35 * font, 0.35 * font, 0.012 * width
        texts = [self._text(label, 0, 0, size=font, name=f"legend_{i}", valign="center")
                 for i, (label, _) in enumerate(entries)]
        text_width = 0.0
        for actor in texts:
            box = [0.0] * 4
            actor.GetBoundingBox(self.plotter.renderer, box)
            text_width = max(text_width, box[1] - box[0])
        x_text = width - margin - text_width
        for i, actor in enumerate(texts):
            actor.SetPosition(x_text, height - margin - (i + 0.5) * row)
        x_disc = x_text - 1.6 * radius
        for i, (_, rgb) in enumerate(entries):
            disc = vtk.vtkRegularPolygonSource()
            disc.SetNumberOfSides(32)
            disc.SetRadius(radius)
            disc.SetCenter(x_disc, height - margin - (i + 0.5) * row, 0.0)
            mapper = vtk.vtkPolyDataMapper2D()
            mapper.SetInputConnection(disc.GetOutputPort())
            actor = vtk.vtkActor2D()
            actor.SetMapper(mapper)
            actor.GetProperty().SetColor(*unit_rgb(rgb))
            self.plotter.add_actor(actor, name=f"legend_disc_{i}", reset_camera=False,
                                   pickable=False)

    def _set_text(self, camera: CameraView) -> None:
        width, height = self.window_size
        font, big = self._font, int(round(self._font * 1.4))
        self._text(self.view_title(camera.name), 0.012 * width, 0.988 * height, size=font,
                   name="title", valign="top")
        labels = camera.orientation_labels()
        bottom = 0.115 if self.scene in ("completion", "registered") else 0.012
        places = {"left": (0.012, 0.5, "left", "center"),
                  "right": (0.988, 0.5, "right", "center"),
                  "top": (0.5, 0.875, "center", "bottom"),
                  "bottom": (0.5, bottom, "center", "bottom")}
        for edge, (x, y, halign, valign) in places.items():
            self._text(labels[edge], x * width, y * height, size=big, name=f"orient_{edge}",
                       halign=halign, valign=valign)
        self._scale_bar(camera)

    def _scale_bar(self, camera: CameraView) -> None:
        """A scale bar in the lower left: a round length (mm) about a sixth of the width."""
        import vtk

        width, height = self.window_size
        mm_per_px = camera.mm_per_pixel
        target = width / 6 * mm_per_px
        length = max(v for v in (1, 2, 5, 10, 20, 50, 100, 200, 500) if v <= max(target, 1))
        x0, y0 = 0.03 * width, (0.20 if self._content is _CONTENT_WITH_BAR else 0.10) * height
        line = vtk.vtkLineSource()
        line.SetPoint1(x0, y0, 0.0)
        line.SetPoint2(x0 + length / mm_per_px, y0, 0.0)
        mapper = vtk.vtkPolyDataMapper2D()
        mapper.SetInputConnection(line.GetOutputPort())
        actor = vtk.vtkActor2D()
        actor.SetMapper(mapper)
        actor.GetProperty().SetColor(*unit_rgb(self.style.text_rgb))
        actor.GetProperty().SetLineWidth(max(2.0, height / 250))
        self.plotter.add_actor(actor, name="scale_bar", reset_camera=False, pickable=False)
        self._text(f"{length:g} mm", x0, y0 + 0.01 * height, size=self._font,
                   name="scale_bar_label")

    def close(self) -> None:
        self.plotter.close()

    def __enter__(self) -> "SceneRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

def render_screenshots(data: SceneData, scenes: Sequence[str] | None = None,
                       views: Sequence[str] = VIEW_NAMES, *,
                       window_size: tuple[int, int] = (800, 800), style: Style = DEFAULT_STYLE,
                       lateral_side: str = "left", show_text: bool = True) -> Iterator[Screenshot]:
    """Yield a :class:`Screenshot` per scene and view (scene-major order); one plotter per scene.
    ``scenes`` defaults to :meth:`SceneData.available_scenes`. Raises OpenGLUnavailableError when
    nothing can render off screen, ValueError for a scene whose inputs are missing."""
    scenes = list(scenes) if scenes is not None else data.available_scenes()
    needs = {"registered": ("us_after",), "overlay": ("us_before",), "completion": ("completion",)}
    for scene in scenes:
        for attribute in needs.get(scene, ()):
            if getattr(data, attribute) is None:
                raise ValueError(f"scene {scene!r} needs {attribute}")
    for scene in scenes:
        with SceneRenderer(data, scene, window_size=window_size, style=style,
                           lateral_side=lateral_side, show_text=show_text) as renderer:
            for view in views:
                yield renderer.screenshot(view)


def render_scene(ct_mesh: SurfaceMesh, *, us_before=None, us_after=None, completion=None,
                 scene: str | None = None, view: str = "anterior",
                 window_size: tuple[int, int] = (800, 800), style: Style = DEFAULT_STYLE,
                 lateral_side: str = "left", show_text: bool = True) -> Screenshot:
    """Render one screenshot of one scene (default: the first available) from one preset view."""
    data = SceneData(ct_mesh, us_before, us_after, completion)
    scene = scene or data.available_scenes()[0]
    return next(render_screenshots(data, [scene], [view], window_size=window_size, style=style,
                                   lateral_side=lateral_side, show_text=show_text))
