"""Shared fixtures: the real fibula prepared once, a small closed test bone."""

import numpy as np
import pytest
import trimesh

from comreg_core.simulation import BoneModel
from tests.helpers import FIBULA_STL


@pytest.fixture(scope="session")
def fibula_bone(shared_data):
    return BoneModel(FIBULA_STL)


@pytest.fixture(scope="session")
def capsule_mesh():
    """A closed capsule 'bone': radius 8 mm, 120 mm long along z, centred at (10, -20, 300)."""
    mesh = trimesh.creation.capsule(height=120.0, radius=8.0, count=[32, 32])
    mesh.apply_translation([10.0, -20.0, 300.0])
    return mesh


@pytest.fixture(scope="session")
def capsule_bone(capsule_mesh):
    return BoneModel(capsule_mesh)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
