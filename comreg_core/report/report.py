"""``write_report``: screenshots of the overlay scenes and ``report.html`` in a run folder.

Output (inside ``out_dir``, which may already hold the run's other files)::

    report.html                      the page (inline CSS, no scripts, no external resources)
    report_images/<scene>_<view>.png the screenshots it shows (relative links)

Images are linked, not embedded, by default: the report references existing images, the PNGs
are useful on their own (README, slides, the Slicer module), the page stays small and opens fast,
and a run folder is already the unit that is kept and shared. For a single file to e-mail,
``embed_images=True`` puts the PNGs into the page as ``data:`` URIs and writes no image folder.

Writing is all or nothing: everything is made in a hidden staging folder inside ``out_dir`` and
moved into place only when every screenshot and the page are done (``report_images/`` first,
``report.html`` last). If anything fails (no OpenGL, bad input, a full disk, Ctrl-C) the staging
folder is removed and an earlier report in ``out_dir`` is left exactly as it was.
"""

from __future__ import annotations

import base64
import logging
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from comreg_core.progress import Progress
from comreg_core import runs
from comreg_core import __version__
from comreg_core.io._files import check_output_folder
from comreg_core.io.meshes import SurfaceMesh, read_mesh
from comreg_core.report.backend import ensure_offscreen_rendering
from comreg_core.report.cameras import VIEW_NAMES
from comreg_core.report.html import Figure, Section, build_html
from comreg_core.report.scenes import SLAB_MARGIN_MM, SceneData, Screenshot, render_screenshots
from comreg_core.report.style import DEFAULT_STYLE, Style

log = logging.getLogger(__name__)

IMAGES_DIR = "report_images"


def image_name(scene: str, view: str) -> str:
    """File name of a screenshot inside ``report_images/``."""
    return f"{scene}_{view}.png"


def write_png(image: np.ndarray, path: Path) -> None:
    """An ``(H, W, 3)`` uint8 image as PNG (Pillow; no metadata, so equal images give equal
    files)."""
    from PIL import Image

    Image.fromarray(np.asarray(image, np.uint8)).save(path, format="PNG", optimize=False)


def write_report(out_dir: str | Path, *, ct_mesh: SurfaceMesh | str | Path,
                 us_before: np.ndarray | None = None, us_after: np.ndarray | None = None,
                 completion: np.ndarray | None = None, metrics: Mapping[str, Any] | None = None,
                 inputs: Mapping[str, Any] | None = None, seed: int | None = None,
                 device: str | None = None, title: str | None = None,
                 views: Sequence[str] = VIEW_NAMES, scenes: Sequence[str] | None = None,
                 window_size: tuple[int, int] = (800, 800), embed_images: bool = False,
                 lateral_side: str = "left", style: Style = DEFAULT_STYLE,
                 progress: Progress | None = None, verdict=None, sweep=None,
                 T_ct_ref: np.ndarray | None = None, n_frames: int = 4,
                 scan_next: np.ndarray | None = None) -> Path:
    """Render the screenshots and write ``report.html`` into ``out_dir``; returns its path. On
    OpenGLUnavailableError or bad inputs (InvalidGeometryError, ...) nothing is written.

    Args:
        out_dir: the run folder (created if missing; other files in it are left alone).
        ct_mesh: the CT bone surface (a :class:`~comreg_core.io.SurfaceMesh` or a mesh file).
            Everything else is in its patient space (LPS or RAS, mm).
        us_before: ``(N, 3)`` US bone points before registration, as received (initial pose).
        us_after: ``(N, 3)`` the same points mapped into the CT by the estimated ``T_ct_us``.
        completion: ``(M, 3)`` the network's completed bone in the CT frame.
        metrics: any JSON-like mapping, one table row per leaf, labels in words and units apart
            (:func:`~comreg_core.report.html.metric_rows`).
        inputs: what the run used (file paths, parameters), shown as given; point counts and the
            CT mesh's file, size and space are added.
        seed, device: shown in the "Run" table. title: the page title.
        views, scenes: camera presets (:data:`~comreg_core.report.cameras.VIEW_NAMES`) and
            scenes (default: :meth:`~comreg_core.report.scenes.SceneData.available_scenes`).
        window_size: screenshot size in pixels ``(width, height)``.
        embed_images: the PNGs inside the page as base64 ``data:`` URIs, no ``report_images/``.
        lateral_side: "left" or "right": the side the lateral view looks from.
        style: colours and sizes. progress: ``progress(done, total, name)`` after each shot.
        verdict: a :class:`~comreg_core.registration.judgement.verdict.Verdict`: the page then
            starts with ``Verdict: OK`` or ``Verdict: CHECK`` and its reasons.
        sweep: the :class:`~comreg_core.io.TrackedSweep` the US points came from, with
            ``T_ct_ref`` (``(4, 4)``: its reference frame -> CT): the page then shows
            ``n_frames`` of its valid B-mode frames with the registered CT contour
            (:func:`~comreg_core.report.sections.frame_overlays`). With ``us_after`` it shows
            CT cuts with the registered points (:func:`~comreg_core.report.sections.ct_sections`).
        scan_next: ``(3,)`` the CT point to scan next, drawn with the registered points.
    """
    out_dir = check_output_folder(out_dir, what="report folder")
    data = SceneData(ct_mesh if isinstance(ct_mesh, SurfaceMesh) else read_mesh(ct_mesh),
                     us_before, us_after, completion, scan_next=scan_next)
    scenes = list(scenes) if scenes is not None else data.available_scenes()
    views = list(views)
    backend = ensure_offscreen_rendering()  # fail before making any folder
    out_dir.mkdir(parents=True, exist_ok=True)
    with _staging_folder(out_dir) as staging:
        images = _Images(staging / IMAGES_DIR, embed_images)
        shots, render_s = _render_scenes(images, data, scenes, views, window_size=window_size,
                                         style=style, lateral_side=lateral_side,
                                         progress=progress)
        cuts = _render_cuts(images, data, style, sweep, T_ct_ref, n_frames)
        _write_page(staging / runs.REPORT, data, shots, cuts, images.sources, title=title,
                    metrics=metrics, inputs=inputs, run=[("Seed", seed), ("Device", device)],
                    versions=_versions(backend, len(shots), render_s, window_size),
                    lateral_side=lateral_side, style=style, verdict=verdict)
        _publish(staging, out_dir, with_images=not embed_images)
    report = out_dir / runs.REPORT
    log.info("wrote %s (%d screenshots)", report, len(shots))
    return report


@contextmanager
def _staging_folder(out_dir: Path) -> Iterator[Path]:
    """A hidden folder inside ``out_dir`` to make the report in, removed on exit (after
    :func:`_publish` moved what it holds, or on any error)."""
    staging = Path(tempfile.mkdtemp(prefix=".report.", suffix=".tmp", dir=out_dir))
    try:
        yield staging
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _write_page(path: Path, data: SceneData, shots: list[Screenshot], cuts: list,
                sources: dict[tuple[str, str], str], *, title: str | None, metrics, inputs,
                run: list[tuple[str, Any]], versions: list[tuple[str, Any]], lateral_side: str,
                style: Style, verdict) -> None:
    """The HTML page (:func:`~comreg_core.report.html.build_html`) of the screenshots and the
    2D pictures (``cuts``), linked by ``sources``, as ``path`` (UTF-8, LF line ends)."""
    page = build_html(
        title=title or "ComReg registration report",
        sections=_sections(shots, sources, lateral_side, data) + _cut_sections(cuts, sources),
        metrics=metrics,
        inputs=_inputs(inputs, data),
        run=run,
        versions=versions,
        notes=_notes(data, lateral_side, style),
        legend=_legend(data, style),
        verdict=None if verdict is None else (verdict.headline, verdict.reasons))
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(page)


class _Images:
    """The report's PNG folder (the staging ``report_images/``) and what the page links for each
    picture: ``sources[(group, name)]`` a relative path, or a ``data:`` URI when embedded."""

    def __init__(self, folder: Path, embed: bool):
        self.folder, self.embed = folder, embed
        self.sources: dict[tuple[str, str], str] = {}
        folder.mkdir()

    def add(self, key: tuple[str, str], image: np.ndarray, name: str) -> None:
        """Write ``image`` ``(H, W, 3)`` uint8 as ``name`` and record its link under ``key``."""
        write_png(image, self.folder / name)
        self.sources[key] = (_data_uri(self.folder / name) if self.embed
                             else f"{IMAGES_DIR}/{name}")


def _render_scenes(images: _Images, data: SceneData, scenes: list[str], views: list[str], *,
                   window_size: tuple[int, int], style: Style, lateral_side: str,
                   progress: Progress | None) -> tuple[list[Screenshot], float]:
    """Every scene from every view into ``images``; the screenshots and the seconds it took."""
    total = len(scenes) * len(views)
    shots: list[Screenshot] = []
    started = time.perf_counter()
    for shot in render_screenshots(data, scenes, views, window_size=window_size, style=style,
                                   lateral_side=lateral_side):
        name = image_name(shot.scene, shot.view)
        images.add((shot.scene, shot.view), shot.image, name)
        shots.append(shot)
        if progress is not None:
            progress(len(shots), total, name)
    return shots, time.perf_counter() - started


def _render_cuts(images: _Images, data: SceneData, style: Style, sweep, T_ct_ref,
                 n_frames: int) -> list:
    """The 2D pictures (:func:`_cross_sections`) into ``images``, under ``("cuts", name)``."""
    cuts = _cross_sections(data, style, sweep, T_ct_ref, n_frames)
    for picture in cuts:
        images.add(("cuts", picture.name), picture.image, f"{picture.name}.png")
    return cuts


def _publish(staging: Path, out_dir: Path, *, with_images: bool) -> None:
    """Move the finished report from ``staging`` into ``out_dir``: the image folder first (the
    old one is moved aside and deleted only after the new one is in), the page last."""
    if with_images:
        target = out_dir / IMAGES_DIR
        old = None
        if target.exists():
            old = Path(tempfile.mkdtemp(prefix=".report_images.old.", dir=out_dir))
            os.replace(target, old / IMAGES_DIR)
        try:
            os.replace(staging / IMAGES_DIR, target)
        except BaseException:
            if old is not None:
                os.replace(old / IMAGES_DIR, target)
            raise
        finally:
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
    os.replace(staging / runs.REPORT, out_dir / runs.REPORT)


def _data_uri(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")


# --- page content --------------------------------------------------------------------------------

_SCENE_TEXT = {
    "registered": ("After registration",
                   "The US bone points mapped into the CT by the estimated transform, on the CT "
                   "bone surface. If the registration is right, the blue points lie on the bone "
                   "surface in every view."),
    "overlay": ("Before and after registration",
                "Where the US points were before registration (as received, vermillion) and "
                "where the registration put them (blue)."),
    "completion": ("Completed bone",
                   "The bone shape the network completed from the partial US surface, in the CT "
                   "frame, coloured by each point's distance to the CT surface."),
    "ct": ("CT bone surface", "The CT bone surface alone (no US points were given)."),
}
_VIEW_CAPTION = {
    "anterior": "Anterior view: from the front, superior up, the patient's right on the image "
                "left.",
    "bone_axis": "Along the bone axis: from the inferior end looking superior, anterior up, the "
                 "patient's left on the image right.",
}


def _caption(view: str, lateral_side: str, scene: str, data: SceneData) -> str:
    if view == "lateral":
        text = (f"Lateral view: from the patient's {lateral_side}, superior up, anterior on the "
                f"image {lateral_side}.")
    else:
        text = _VIEW_CAPTION.get(view, view)
    if view == "bone_axis" and scene in ("registered", "overlay") and data.us_after is not None:
        text += (f" The CT is cut to the registered points' span along the bone axis "
                 f"+-{SLAB_MARGIN_MM:g} mm.")
    return text


def _sections(shots: list[Screenshot], sources: dict, lateral_side: str,
              data: SceneData) -> list[Section]:
    sections: list[Section] = []
    for scene in dict.fromkeys(s.scene for s in shots):
        heading, text = _SCENE_TEXT.get(scene, (scene, ""))
        figures = []
        for shot in (s for s in shots if s.scene == scene):
            height, width = shot.image.shape[:2]
            figures.append(Figure(sources[(scene, shot.view)],
                                  f"{heading}, {shot.view.replace('_', ' ')} view",
                                  _caption(shot.view, lateral_side, scene, data), width, height))
        sections.append(Section(heading, text, figures))
    return sections


def _cross_sections(data: SceneData, style: Style, sweep, T_ct_ref, n_frames: int) -> list:
    """The 2D pictures (:mod:`comreg_core.report.sections`): CT cuts when there are registered
    points, B-mode frames with the CT contour when the sweep is known."""
    from comreg_core.report.sections import ct_sections, frame_overlays

    pictures = []
    if data.us_after is not None:
        pictures += ct_sections(data.ct, data.frame, data.us_after, data.us_after_distance_mm,
                                style=style)
    if sweep is not None and T_ct_ref is not None and n_frames > 0:
        valid = np.flatnonzero(sweep.valid)
        chosen = valid[np.unique(np.linspace(0, len(valid) - 1, n_frames + 2)[1:-1].round()
                                 .astype(int))]
        pictures += frame_overlays(sweep.frames[chosen],
                                   np.asarray(T_ct_ref, float) @ sweep.T_ref_pixel[chosen],
                                   sweep.spacing, data.ct,
                                   [sweep.frame_names[i] for i in chosen])
    return pictures


def _cut_sections(pictures: list, sources: dict) -> list[Section]:
    groups = {"frame": ("US frames with the CT contour",
                        "A few frames of the tracked sweep as recorded, with the contour where "
                        "the registered CT bone cuts each frame's plane: the usual visual check "
                        "of a US-CT registration. If it is right, the contour runs along the "
                        "bright bone echo, with the acoustic shadow below it."),
              "section": ("CT cross-sections",
                          "The CT bone cut across its long axis, with the registered US points "
                          "near each cut. If the registration is right, the points lie on the "
                          "contour and are dark purple (near 0 mm).")}
    sections = []
    for prefix, (heading, text) in groups.items():
        chosen = [p for p in pictures if p.name.startswith(prefix)]
        if chosen:
            sections.append(Section(heading, text, [
                Figure(sources[("cuts", p.name)], p.title, p.caption, p.image.shape[1],
                       p.image.shape[0]) for p in chosen]))
    return sections


def _legend(data: SceneData, style: Style) -> list[tuple[str, tuple[int, int, int]]]:
    legend = [("CT bone surface", style.bone_rgb)]
    if data.us_before is not None:
        legend.append(("US points before registration", style.us_before_rgb))
    if data.us_after is not None:
        legend.append(("US points after registration", style.us_after_rgb))
    return legend


def _inputs(inputs: Mapping[str, Any] | None, data: SceneData) -> list[tuple[str, Any]]:
    rows = [(str(k), v) for k, v in (inputs or {}).items()]
    ct = data.ct
    rows.append(("CT mesh", f"{ct.path}" if ct.path else "(in memory)"))
    rows.append(("CT mesh size", f"{len(ct.vertices)} vertices, {len(ct.faces)} triangles, "
                                 f"space {ct.space}"))
    for label, points in (("US points before registration", data.us_before),
                          ("US points after registration", data.us_after),
                          ("Completion points", data.completion)):
        rows.append((label, "none" if points is None else f"{len(points)} points"))
    return rows


def _package_version(name: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def _versions(backend, n_shots: int, render_s: float,
              window_size: tuple[int, int]) -> list[tuple[str, Any]]:
    import vtk

    rows: list[tuple[str, Any]] = [
        ("comreg", __version__),
        ("python", f"{platform.python_version()} ({platform.python_implementation()})"),
        ("vtk", vtk.vtkVersion.GetVTKVersion()),
    ]
    # Read from the package metadata: importing torch just for its version costs seconds.
    for name in ("torch", "pyvista", "numpy"):
        rows.append((name, _package_version(name) or "not installed"))
    rows.append(("platform", platform.platform()))
    rows.append(("off-screen rendering", backend.describe()))
    rows.append(("screenshots", f"{n_shots} at {window_size[0]} x {window_size[1]} px in "
                                f"{render_s:.1f} s"))
    return rows


def _notes(data: SceneData, lateral_side: str, style: Style) -> list[str]:
    frame = data.frame
    space = data.ct.space
    lo, hi = style.distance_range_mm
    axis_note = ("the first principal axis of the CT surface" if frame.long_axis_from_pca else
                 "the patient's superior axis (the bone has no clear long axis)")
    return [
        f"Coordinates are the CT's patient space, {space} ("
        + ("x to the patient's left, y posterior, z superior" if space == "LPS" else
           "x to the patient's right, y anterior, z superior") + "), in millimetres.",
        f"The views are built from the CT bone alone: the bone axis is {axis_note}, pointing "
        "superior; the anterior and left directions are the patient's, made orthogonal to it. "
        "They are principal-axis based, so for an oblique bone 'anterior' means 'from the front, "
        "across the bone axis'. Letters at the image edges (R/L, A/P, S/I) name the patient "
        "directions; the projection is parallel (no perspective), so distances on screen are "
        "to scale within an image.",
        f"The lateral view looks from the patient's {lateral_side}: that is the lateral side of "
        f"a {lateral_side} limb and the medial side of the other.",
        f"Completion colours: viridis from dark purple (0 mm, on the CT surface) to yellow "
        f"({hi:g} mm or more); distances are to the nearest point of the CT surface "
        f"(range {lo:g}-{hi:g} mm).",
    ]

