"""Choosing an off-screen OpenGL backend for VTK without ever crashing the calling process.

VTK's Linux wheels (9.4 and later, 9.6.2 here) pick the OpenGL render-window class at run time from
the environment variable ``VTK_DEFAULT_OPENGL_WINDOW``: ``vtkEGLRenderWindow`` (headless EGL: Mesa
``libegl1 libegl-mesa0 libgl1-mesa-dri``, or a GPU driver's EGL), ``vtkOSOpenGLRenderWindow``
(OSMesa software rendering: ``libosmesa6``) or ``vtkXOpenGLRenderWindow`` (an X display). When the
requested class cannot be made VTK logs a warning and silently falls back to another one; when no
OpenGL at all can be loaded, making a render window can abort or segfault the process.

So before the first render window is made in this process, :func:`ensure_offscreen_rendering`
renders one small frame in a *subprocess* (``python -c`` with pyvista, off screen) for each
candidate, in order of preference:

1. whatever the user already put in ``VTK_DEFAULT_OPENGL_WINDOW`` (their choice wins),
2. ``vtkEGLRenderWindow`` (Linux),
3. ``vtkOSOpenGLRenderWindow`` (Linux),
4. VTK's own default (no variable set: X, Win32, Cocoa, ... whatever the platform has).

A candidate passes when the child exits 0, reports that the render window it made is of the
requested class (so VTK's silent fallback is not mistaken for success) and the frame is not blank.
The first that passes is put into ``os.environ["VTK_DEFAULT_OPENGL_WINDOW"]`` of this process and
remembered (also a failure is remembered: probing again is not free); if none passes,
:class:`OpenGLUnavailableError` says what to install. A crash, however hard, stays in the child.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
from dataclasses import dataclass

from comreg_core.errors import ComRegError

log = logging.getLogger(__name__)

#: The environment variable VTK reads to choose its OpenGL render-window class.
VTK_WINDOW_ENV = "VTK_DEFAULT_OPENGL_WINDOW"

EGL = "vtkEGLRenderWindow"
OSMESA = "vtkOSOpenGLRenderWindow"

#: Seconds one probe may take (llvmpipe start-up on a busy 2-core machine is ~1-2 s).
PROBE_TIMEOUT_S = 60.0

INSTALL_HINT = (
    "Install Mesa EGL or OSMesa: `sudo apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri` "
    "(EGL, preferred) or `sudo apt-get install libosmesa6` (OSMesa), or run "
    "scripts/install-system-deps.sh; then run the command again. To force one backend set "
    f"{VTK_WINDOW_ENV}={EGL} or {VTK_WINDOW_ENV}={OSMESA}.")

# Renders one lit sphere on black in a 64 x 64 off-screen window and prints, as one JSON line, the
# class of the render window VTK really made, the fraction of lit pixels and the OpenGL renderer.
PROBE_CODE = r"""
import json, sys
import pyvista as pv
plotter = pv.Plotter(off_screen=True, window_size=(64, 64))
plotter.set_background("black")
plotter.add_mesh(pv.Sphere(radius=0.5), color="white")
image = plotter.screenshot(return_img=True)
window = plotter.render_window
renderer_string = ""
try:
    for line in window.ReportCapabilities().splitlines():
        if "renderer string" in line.lower():
            renderer_string = line.split(":", 1)[1].strip()
            break
except Exception:
    pass
result = {"window": window.GetClassName(), "lit_fraction": float((image.max(axis=-1) > 64).mean()),
          "renderer": renderer_string}
plotter.close()
sys.stdout.write("COMREG_PROBE " + json.dumps(result) + "\n")
"""


class OpenGLUnavailableError(ComRegError):
    """No OpenGL backend can render off screen, so screenshots and reports cannot be made."""

    def __init__(self, tried: list[str]):
        self.tried = list(tried)
        detail = "; ".join(tried) if tried else "no backend was tried"
        super().__init__(
            f"Off-screen rendering with VTK does not work on this machine ({detail}).",
            INSTALL_HINT)


@dataclass(frozen=True)
class RenderBackend:
    """The off-screen OpenGL backend this process renders with.

    Attributes:
        window_class: VTK render-window class (``vtkEGLRenderWindow``, ``vtkOSOpenGLRenderWindow``,
            ...), as the probe saw it made.
        renderer: the OpenGL renderer string (e.g. ``llvmpipe (LLVM 15.0.6, 256 bits)``), or "".
    """

    window_class: str
    renderer: str = ""

    @property
    def name(self) -> str:
        """Short name: "EGL", "OSMesa", or the window class for anything else."""
        return {EGL: "EGL", OSMESA: "OSMesa"}.get(self.window_class, self.window_class)

    def describe(self) -> str:
        return f"{self.name} ({self.window_class}{', ' + self.renderer if self.renderer else ''})"


_lock = threading.Lock()
_cached: RenderBackend | OpenGLUnavailableError | None = None


def candidate_windows(environ=None, platform: str | None = None) -> list[str | None]:
    """Render-window classes to try, best first; ``None`` means VTK's own default."""
    environ = os.environ if environ is None else environ
    platform = sys.platform if platform is None else platform
    candidates: list[str | None] = []
    user = environ.get(VTK_WINDOW_ENV, "").strip()
    if user:
        candidates.append(user)
    if platform.startswith("linux"):
        candidates += [EGL, OSMESA]
    candidates.append(None)
    unique: list[str | None] = []
    for c in candidates:
        if c not in unique:
            unique.append(c)
    return unique


def probe_backend(window_class: str | None, *, timeout_s: float = PROBE_TIMEOUT_S
                  ) -> tuple[RenderBackend | None, str]:
    """Render one frame with ``window_class`` (``None``: VTK's default) in a subprocess.

    Returns ``(backend, "")`` when it works, else ``(None, reason)``. Never raises for a failing
    backend and never lets a crash reach this process.
    """
    env = dict(os.environ)
    env.pop(VTK_WINDOW_ENV, None)
    if window_class:
        env[VTK_WINDOW_ENV] = window_class
    env["PYVISTA_OFF_SCREEN"] = "true"
    label = window_class or "VTK default"
    try:
        done = subprocess.run([sys.executable, "-c", PROBE_CODE], env=env, capture_output=True,
                              text=True, timeout=timeout_s, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return None, f"{label}: no frame within {timeout_s:.0f} s"
    except OSError as exc:  # the interpreter itself could not start
        return None, f"{label}: cannot start a probe process ({exc})"
    if done.returncode != 0:
        how = (f"killed by signal {-done.returncode}" if done.returncode < 0
               else f"exit status {done.returncode}")
        tail = _last_line(done.stderr)
        return None, f"{label}: probe {how}" + (f" ({tail})" if tail else "")
    result = None
    for line in done.stdout.splitlines():
        if line.startswith("COMREG_PROBE "):
            try:
                result = json.loads(line[len("COMREG_PROBE "):])
            except ValueError:
                result = None
    if not isinstance(result, dict) or "window" not in result:
        return None, f"{label}: the probe printed no result"
    made = str(result["window"])
    if window_class and made != window_class:
        return None, f"{label}: VTK made a {made} instead"
    if float(result.get("lit_fraction", 0.0)) < 0.05:
        return None, f"{label}: the test frame came out blank"
    return RenderBackend(made, str(result.get("renderer", ""))), ""


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    return lines[-1][:300] if lines else ""


def ensure_offscreen_rendering() -> RenderBackend:
    """The working off-screen backend of this process, probing once (see the module docstring).

    Sets ``VTK_DEFAULT_OPENGL_WINDOW`` for this process to the chosen class, so every render
    window made afterwards uses it. The answer (or the failure) is cached per process; call
    :func:`reset_backend_cache` to probe again.

    Raises:
        OpenGLUnavailableError: no candidate renders; its message says what to install.
    """
    global _cached
    with _lock:
        if _cached is None:
            _cached = _choose()
        if isinstance(_cached, OpenGLUnavailableError):
            raise _cached
        # The class the probe saw VTK make; also for VTK's default, which saves later windows
        # the failing attempts (and their warnings) that preceded it in the probe.
        os.environ[VTK_WINDOW_ENV] = _cached.window_class
        return _cached


def _choose() -> RenderBackend | OpenGLUnavailableError:
    tried = []
    for window_class in candidate_windows():
        backend, reason = probe_backend(window_class)
        if backend is not None:
            log.info("off-screen rendering with %s", backend.describe())
            return backend
        log.info("off-screen backend rejected: %s", reason)
        tried.append(reason)
    return OpenGLUnavailableError(tried)


def cached_backend() -> RenderBackend | None:
    """The backend chosen so far in this process, without probing; ``None`` if none yet."""
    return _cached if isinstance(_cached, RenderBackend) else None


def reset_backend_cache() -> None:
    """Forget the cached answer so the next :func:`ensure_offscreen_rendering` probes again."""
    global _cached
    with _lock:
        _cached = None
