"""The tibia-like bone the learning benchmark trains on besides the fibula: a closed, outward
mesh of tibia size that the simulator sweeps like a real bone."""

import numpy as np
import trimesh

from comreg_core.registration.geometry.surface import CTSurface
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


def _shaft_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Cross-section areas (mm^2) at 30, 45, 60 and 75 % of the length: VTK's cut of the
    mesh, its points ordered by angle (the sections are star-shaped), shoelace area."""
    import pyvista as pv

    mesh = pv.PolyData(vertices, np.hstack([np.full((len(faces), 1), 3), faces]).ravel())
    areas = []
    for share in (0.30, 0.45, 0.60, 0.75):
        cut = np.asarray(mesh.slice(normal="z", origin=(0.0, 0.0, 360.0 * share)).points)
        xy = cut[:, :2] - cut[:, :2].mean(axis=0)
        x, y = xy[np.argsort(np.arctan2(xy[:, 1], xy[:, 0]))].T
        areas.append(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    return np.array(areas)


def test_the_anatomical_variant_has_a_shaft_that_changes_along_its_length():
    """The default shaft is an extrusion (the same cross-section from 30 to 75 %); the
    anatomical one tapers to the distal third and twists, like a real tibia."""
    vertices, faces = tibia_like_mesh(anatomical=True)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    extent = vertices.max(0) - vertices.min(0)
    assert 360 <= extent[2] <= 366 and 80 <= extent[0] <= 105
    flat = _shaft_areas(*tibia_like_mesh())
    assert np.ptp(flat) / flat.mean() < 0.02  # one cross-section along the shaft
    varied = _shaft_areas(vertices, faces)
    assert varied[0] < varied[1] < varied[2]  # widening from the distal third
    assert np.ptp(varied) / varied.mean() > 0.25
