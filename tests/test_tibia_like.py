"""The tibia-like bone the learning benchmark trains on besides the fibula: a closed, outward
mesh of tibia size that the simulator sweeps like a real bone."""

import numpy as np
import trimesh

from comreg_core.registration.surface import CTSurface
from comreg_core.simulation.bone import BoneModel
from comreg_core.simulation.config import SimulationConfig
from comreg_core.simulation.simulator import simulate_sweep
from tests.helpers import tibia_like_mesh


def test_tibia_like_mesh_is_a_closed_bone_that_the_simulator_sweeps():
    vertices, faces = tibia_like_mesh()
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    extent = vertices.max(0) - vertices.min(0)
    assert 360 <= extent[2] <= 366 and 80 <= extent[0] <= 100  # long axis z, wide plateau
    sweep = simulate_sweep(BoneModel((vertices, faces)), SimulationConfig(n_points=2048),
                           np.random.default_rng(0))
    assert sweep.points.shape == (2048, 3)
    d = CTSurface((vertices, faces)).distance(sweep.points)
    assert np.median(d) < 0.5  # the sweep's points lie on the bone (false echoes aside)
