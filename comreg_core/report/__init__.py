"""Off-screen rendering of registration results: overlay screenshots and an HTML report.

No Slicer, no Qt, no display needed. Typical use (all coordinates in the CT mesh's space, mm)::

    from comreg_core.report import write_report
    write_report(run_dir, ct_mesh=ct, us_before=us_points,
                 us_after=apply_transform(T_ct_us, us_points), completion=completion_ct,
                 metrics=metrics, inputs={"US sweep": path}, seed=0, device="cpu")

Before VTK makes its first render window, :func:`ensure_offscreen_rendering` checks in a
subprocess which OpenGL backend works (EGL, then OSMesa, then VTK's default) and raises
:class:`OpenGLUnavailableError` with install instructions if none does, so a missing OpenGL is a
clear error, not a segfault. Modules: ``backend`` (that check), ``cameras`` (principal-axis view
presets and framing), ``style`` (colours, the distance map, the theme), ``scenes`` (the 3D
overlays), ``sections`` (2D cuts and B-mode frames), ``html`` (the page), ``report`` (writing it),
``registration`` (the report of a ``comreg register`` folder, with its verdict).
"""

from comreg_core.report.backend import (OpenGLUnavailableError, RenderBackend,
                                        ensure_offscreen_rendering, reset_backend_cache)
from comreg_core.report.cameras import VIEW_NAMES, BoneFrame, CameraView, bone_frame, view_presets
from comreg_core.report.registration import write_report_for_registration
from comreg_core.report.report import IMAGES_DIR, image_name, write_report
from comreg_core.report.scenes import (SCENES, SceneData, SceneRenderer, Screenshot,
                                       render_scene, render_screenshots)
from comreg_core.report.style import DEFAULT_STYLE, Style

__all__ = [
    "BoneFrame", "CameraView", "DEFAULT_STYLE", "IMAGES_DIR", "OpenGLUnavailableError",
    "RenderBackend", "SCENES", "SceneData", "SceneRenderer", "Screenshot", "Style",
    "VIEW_NAMES", "bone_frame", "ensure_offscreen_rendering", "image_name", "render_scene",
    "render_screenshots", "reset_backend_cache", "view_presets", "write_report",
    "write_report_for_registration",
]
