import pytest

from tests.helpers import FIBULA_STL
from tests.report.support import TEST_WINDOW, make_case


@pytest.fixture(scope="session")
def fibula(shared_data):
    from comreg_core.io import read_mesh

    return read_mesh(FIBULA_STL)


@pytest.fixture(scope="session")
def case(fibula):
    return make_case(fibula)


@pytest.fixture(scope="session")
def scene_data(case):
    from comreg_core.report.scenes import SceneData

    return SceneData(case.ct, case.us_before, case.us_after, case.completion)


@pytest.fixture(scope="session")
def shots(scene_data):
    """Every scene from every preset at the test size: {(scene, view): Screenshot}."""
    from comreg_core.report.scenes import render_screenshots

    return {(s.scene, s.view): s
            for s in render_screenshots(scene_data, window_size=TEST_WINDOW)}


@pytest.fixture
def no_opengl(monkeypatch):
    """Make every backend probe crash (a real SIGSEGV, in the probe's own child process) and
    forget the cached backend for this test only; restored afterwards."""
    from comreg_core.report import backend

    monkeypatch.setattr(backend, "PROBE_CODE",
                        "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)")
    monkeypatch.setattr(backend, "_cached", None)
    # ensure_offscreen_rendering() sets this; monkeypatch puts the original back.
    monkeypatch.setenv(backend.VTK_WINDOW_ENV, "")
    monkeypatch.delenv(backend.VTK_WINDOW_ENV)
    return backend


