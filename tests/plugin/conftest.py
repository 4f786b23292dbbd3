"""Fixtures of the headless 3D Slicer module tests: slicer-core's MRML, a fresh Logic per test,
the module's synthetic case (sample CT + simulated sweep moved by a known transform) and a small
real tracked sweep."""

from __future__ import annotations


import pytest

from tests.helpers import cut_sweep

#: Why the plugin tests skip when the headless MRML library is missing.
SLICER_CORE_MISSING = ("slicer-core (3D Slicer's MRML as a Python wheel) is not installed: run "
                       "'pip install -e .[test]' or scripts/setup-env.sh")


@pytest.fixture
def logic():
    """A ComRegLogic on its own empty scene."""
    pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)
    from comreg_plugin.logic import ComRegLogic

    return ComRegLogic()


@pytest.fixture(scope="session")
def case(tmp_path_factory):
    """The module's synthetic case (comreg_plugin.testing.buildSyntheticCase)."""
    pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)
    from comreg_plugin.testing import buildSyntheticCase

    return buildSyntheticCase(tmp_path_factory.mktemp("synthetic_case"))


@pytest.fixture(scope="session")
def small_sweep(shared_data, tmp_path_factory):
    """Every 5th frame of the real UltraBones100k fibula sweep, as a frame folder."""
    return cut_sweep(tmp_path_factory.mktemp("sweep"), 0, 10**6, step=5)
