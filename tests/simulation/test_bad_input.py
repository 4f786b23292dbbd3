"""Bad input gives typed errors that say what to do."""

import numpy as np
import pytest
import trimesh

from comreg_core.config import ConfigError
from comreg_core.errors import ComRegError, InvalidGeometryError
from comreg_core.io.meshes import SurfaceMesh, write_mesh
from comreg_core.simulation import (BoneModel, SimulationConfig, SimulationError,
                                    load_simulation_config, simulate_from_poses, simulate_sweep,
                                    simulate_to_directory, simulation_config_from_dict)
from tests.simulation.support import with_trajectory


def test_open_mesh(capsule_mesh):
    open_mesh = capsule_mesh.copy()
    open_mesh.update_faces(np.arange(len(open_mesh.faces)) != 5)
    with pytest.raises(InvalidGeometryError, match="not closed.*3 boundary edges.*fill the holes"):
        BoneModel(open_mesh)


def test_mesh_in_metres(capsule_mesh):
    metres = capsule_mesh.copy()
    metres.apply_scale(0.001)
    with pytest.raises(InvalidGeometryError, match="metres.*Scale it by 1000"):
        BoneModel(metres)


def test_fibula_in_metres_from_file(fibula_bone, tmp_path):
    path = write_mesh(SurfaceMesh(fibula_bone.vertices / 1000.0, fibula_bone.faces),
                      tmp_path / "fibula_m.stl")
    with pytest.raises(InvalidGeometryError, match="metres"):
        simulate_to_directory(path, tmp_path / "out", count=1, seed=0)
    assert not (tmp_path / "out" / "config.yaml").exists()


def test_degenerate_meshes():
    line = np.array([[0, 0, 0], [10, 0, 0], [20, 0, 0], [30, 0, 0]], float)
    with pytest.raises(InvalidGeometryError, match="degenerate"):
        BoneModel((line, np.array([[0, 1, 2], [1, 2, 3], [0, 2, 3], [0, 1, 3]])))
    # a flat, doubled sheet: closed in the edge sense but enclosing no volume
    square = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]])
    with pytest.raises(InvalidGeometryError, match="no volume|not consistently|not closed"):
        BoneModel((square, faces))


def test_no_faces(tmp_path):
    with pytest.raises(InvalidGeometryError, match="no triangles"):
        BoneModel((np.random.default_rng(0).normal(size=(10, 3)), np.zeros((0, 3), int)))
    cloud = tmp_path / "points.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(10, 3)) * 30).export(cloud)
    with pytest.raises(ComRegError):
        simulate_to_directory(cloud, tmp_path / "out", count=1, seed=0)


def test_non_finite_vertices(capsule_mesh):
    vertices = np.array(capsule_mesh.vertices)
    vertices[3] = np.nan
    with pytest.raises(InvalidGeometryError, match="non-finite"):
        BoneModel((vertices, capsule_mesh.faces))


@pytest.mark.parametrize("data, message", [
    ({"n_points": 0}, "n_points"),
    ({"mode": "random"}, "not one of"),
    ({"probe": {"n_rays": 1}}, "probe.n_rays"),
    ({"probe": {"depth_mm": -5}}, "probe.depth_mm"),
    ({"trajectory": {"n_slices": [300, 100]}}, "min <= max"),
    ({"trajectory": {"face_distance_mm": [7, 500]}}, "face_distance_mm"),
    ({"trajectory": {"longitudinal_probability": 1.5}}, "longitudinal_probability"),
    ({"trajectory": {"side_reference": [0, 0, 0]}}, "non-zero"),
    ({"perturbation": {"tilt_x_max_deg": 120}}, "tilt_x_max_deg"),
    ({"perturbation": {"speed_clip": [2.0, 10.0]}}, "contain 1"),
    ({"perturbation": {"speed_noise": "sum"}}, "not one of"),
    ({"perturbation": {"false_hit_probability": -0.1}}, "false_hit_probability"),
    ({"perturbation": {"false_hit_depth": [0.5, 1.5]}}, "false_hit_depth"),
    ({"perturbation": {"drop_probability": 1.0}}, "drop_probability"),
    ({"perturbation": {"tilt_window": 0}}, "tilt_window"),
    ({"perturbation": {"tilt_windw": 3}}, "Unknown config key"),
])
def test_config_out_of_range(data, message):
    with pytest.raises(ConfigError, match=message):
        simulation_config_from_dict(data)


def test_config_file_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("n_points: [", encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_simulation_config(bad)
    listing = tmp_path / "list.yaml"
    listing.write_text("- 1\n- 2\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="mapping"):
        load_simulation_config(listing)


@pytest.mark.parametrize("count, seed, message", [(0, 0, "count"), (2.5, 0, "count"),
                                                  (1, -1, "seed"), (1, "x", "seed")])
def test_bad_count_or_seed(capsule_mesh, tmp_path, count, seed, message):
    path = tmp_path / "capsule.stl"
    capsule_mesh.export(path)
    with pytest.raises(ConfigError, match=message):
        simulate_to_directory(path, tmp_path / "out", count=count, seed=seed)


def test_probe_that_never_sees_the_bone(capsule_bone):
    far = with_trajectory(SimulationConfig(max_attempts=3), face_distance_mm=(100.0, 150.0))
    with pytest.raises(SimulationError, match="min_hits"):
        simulate_sweep(capsule_bone, far, np.random.default_rng(0))


def test_replay_with_bad_poses(capsule_bone):
    with pytest.raises(SimulationError, match=r"\(N, 4, 4\)"):
        simulate_from_poses(capsule_bone, np.eye(4))
    scaled = np.repeat(np.diag([2.0, 2.0, 2.0, 1.0])[None], 3, axis=0)
    with pytest.raises(ComRegError, match="not rigid"):
        simulate_from_poses(capsule_bone, scaled)
    away = np.repeat(np.eye(4)[None], 3, axis=0)
    away[:, :3, 3] = [1000.0, 0.0, 0.0]
    with pytest.raises(SimulationError, match="same frame"):
        simulate_from_poses(capsule_bone, away)
