"""The off-screen OpenGL check: subprocess probes, backend choice, cache, and the typed error."""

from __future__ import annotations

import ctypes.util
import os

import pytest

from comreg_core.errors import ComRegError
from comreg_core.report import backend
from comreg_core.report.backend import (EGL, OSMESA, OpenGLUnavailableError, candidate_windows,
                                        ensure_offscreen_rendering, probe_backend)


def test_a_backend_is_chosen_set_for_vtk_and_cached(monkeypatch):
    chosen = ensure_offscreen_rendering()
    assert chosen.window_class in (EGL, OSMESA)  # Linux with Mesa: EGL preferred, OSMesa next
    assert os.environ[backend.VTK_WINDOW_ENV] == chosen.window_class

    def no_more_probes(*args, **kwargs):
        raise AssertionError("probed again although the answer is cached")

    monkeypatch.setattr(backend, "probe_backend", no_more_probes)
    assert ensure_offscreen_rendering() is chosen


@pytest.mark.parametrize("window_class, library", [(EGL, "EGL"), (OSMESA, "OSMesa")])
def test_each_mesa_backend_renders_in_this_vtk_wheel(window_class, library):
    if ctypes.util.find_library(library) is None:
        pytest.skip(f"lib{library} is not installed (scripts/install-system-deps.sh installs it)")
    found, reason = probe_backend(window_class)
    assert found is not None, reason
    assert found.window_class == window_class
    assert found.name == {EGL: "EGL", OSMESA: "OSMesa"}[window_class]


def test_vtk_silently_falling_back_to_another_window_is_not_success():
    found, reason = probe_backend("vtkNoSuchRenderWindow")
    assert found is None
    assert "vtkNoSuchRenderWindow" in reason and "instead" in reason


def test_candidates_user_choice_first_then_egl_osmesa_default():
    assert candidate_windows({}, "linux") == [EGL, OSMESA, None]
    assert candidate_windows({backend.VTK_WINDOW_ENV: OSMESA}, "linux") == [OSMESA, EGL, None]
    assert candidate_windows({backend.VTK_WINDOW_ENV: "vtkXOpenGLRenderWindow"}, "linux") == [
        "vtkXOpenGLRenderWindow", EGL, OSMESA, None]
    assert candidate_windows({}, "win32") == [None]


def test_a_probe_that_segfaults_gives_the_typed_error_with_the_install_hint(no_opengl):
    with pytest.raises(OpenGLUnavailableError) as caught:
        ensure_offscreen_rendering()
    error = caught.value
    assert isinstance(error, ComRegError)
    message = str(error)
    assert "Off-screen rendering with VTK does not work" in message
    assert "apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri" in message
    assert "libosmesa6" in message
    assert "scripts/install-system-deps.sh" in message
    assert len(error.tried) == len(candidate_windows())  # every candidate was tried...
    assert all("killed by signal 11" in reason for reason in error.tried)  # ...and crashed


def test_the_failure_is_cached_too(no_opengl, monkeypatch):
    calls = []
    real = backend.probe_backend

    def counting(window_class, **kwargs):
        calls.append(window_class)
        return real(window_class, **kwargs)

    monkeypatch.setattr(backend, "probe_backend", counting)
    for _ in range(2):
        with pytest.raises(OpenGLUnavailableError):
            ensure_offscreen_rendering()
    assert len(calls) == len(candidate_windows())


def test_a_hanging_probe_times_out(monkeypatch):
    monkeypatch.setattr(backend, "PROBE_CODE", "import time; time.sleep(60)")
    found, reason = probe_backend(EGL, timeout_s=1.0)
    assert found is None and "no frame within 1 s" in reason


def test_a_probe_that_prints_nothing_is_rejected(monkeypatch):
    monkeypatch.setattr(backend, "PROBE_CODE", "pass")
    found, reason = probe_backend(EGL)
    assert found is None and "no result" in reason
