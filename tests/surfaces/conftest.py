"""Fixtures shared by the surface tests."""

from __future__ import annotations

import pytest
import trimesh

from comreg_core.io.meshes import SurfaceMesh
from tests.helpers import FIBULA_STL


@pytest.fixture(scope="module")
def fibula(shared_data) -> SurfaceMesh:
    tm = trimesh.load_mesh(FIBULA_STL)
    return SurfaceMesh(tm.vertices, tm.faces)
