"""simulate_to_directory (what `comreg simulate` calls) and the uniform-sampling mode."""

import numpy as np
import pytest
import yaml

from comreg_core.io.pointclouds import read_points
from comreg_core.simulation import (SimulationConfig, load_simulation_config, sample_uniform,
                                    simulate_sweep, simulate_to_directory, sweep_rng)
from tests.helpers import FIBULA_STL
from tests.simulation.support import vtk_distance, vtk_surface, with_perturbation

SMALL = SimulationConfig(n_points=3000)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, shared_data):
    out = tmp_path_factory.mktemp("sim") / "run"
    config = with_perturbation(SMALL, drop_probability=0.2)
    paths = simulate_to_directory(FIBULA_STL, out, count=3, seed=11, config=config)
    return out, paths, config


def test_files_written(run_dir, fibula_bone):
    out, paths, config = run_dir
    assert [p.name for p in paths] == ["sweep_0000.ply", "sweep_0001.ply", "sweep_0002.ply"]
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(["config.yaml"] + [f"sweep_{i:04d}{s}" for i in range(3)
                                              for s in (".ply", "_slices.npy", "_poses.npy")])
    for i, path in enumerate(paths):
        cloud = read_points(path)
        assert cloud.points.shape == (3000, 3) and cloud.space == "LPS"
        slices = np.load(out / f"sweep_{i:04d}_slices.npy")
        poses = np.load(out / f"sweep_{i:04d}_poses.npy")
        assert slices.dtype == np.int32 and slices.shape == (3000,)
        assert poses.ndim == 3 and poses.shape[1:] == (4, 4)
        dropped = np.isnan(poses).all(axis=(1, 2))
        assert dropped.any() and not np.isin(slices, np.flatnonzero(dropped)).any()
        # the files hold exactly what the library returns for sweep i of seed 11
        sweep = simulate_sweep(fibula_bone, config, sweep_rng(11, i))
        assert np.array_equal(cloud.points, sweep.points)
        assert np.array_equal(slices, sweep.slice_index)


def test_config_yaml_records_the_run_and_reloads(run_dir):
    out, _, config = run_dir
    record = yaml.safe_load((out / "config.yaml").read_text())
    assert record["run"]["seed"] == 11 and record["run"]["count"] == 3
    assert record["run"]["ct_mesh"] == str(FIBULA_STL.resolve())
    assert load_simulation_config(out / "config.yaml") == config


def test_config_file_path_is_accepted(run_dir, tmp_path):
    """A previous run's config.yaml passed back as the config reproduces sweep 0 exactly."""
    out, _, _ = run_dir
    simulate_to_directory(FIBULA_STL, tmp_path / "b", count=1, seed=11,
                          config=out / "config.yaml")
    assert (tmp_path / "b" / "sweep_0000.ply").read_bytes() == \
        (out / "sweep_0000.ply").read_bytes()
    partial = tmp_path / "partial.yaml"
    partial.write_text("n_points: 500\nperturbation:\n  drop_probability: 0.0\n")
    paths = simulate_to_directory(FIBULA_STL, tmp_path / "c", count=1, seed=0, config=partial)
    assert read_points(paths[0]).points.shape == (500, 3)


def test_same_seed_same_bytes_and_sweeps_independent_of_count(run_dir, tmp_path):
    out, _, config = run_dir
    again = tmp_path / "again"
    simulate_to_directory(FIBULA_STL, again, count=2, seed=11, config=config)
    for name in ["sweep_0000.ply", "sweep_0001_slices.npy", "sweep_0001_poses.npy"]:
        assert (again / name).read_bytes() == (out / name).read_bytes()
    other = tmp_path / "other"
    simulate_to_directory(FIBULA_STL, other, count=1, seed=12, config=config)
    assert (other / "sweep_0000.ply").read_bytes() != (out / "sweep_0000.ply").read_bytes()
    assert not [p for p in again.iterdir() if p.name.startswith(".")]  # no temp files left


def test_uniform_mode_samples_the_surface(fibula_bone, tmp_path):
    config = SimulationConfig(mode="uniform", n_points=4000)
    sweep = simulate_sweep(fibula_bone, config, np.random.default_rng(0))
    assert sweep.points.shape == (4000, 3) and sweep.trajectory is None
    assert np.all(sweep.slice_index == -1) and not sweep.is_false.any()
    surface = vtk_surface(fibula_bone.vertices, fibula_bone.faces)
    assert vtk_distance(surface, sweep.points[:500]).max() < 1e-6
    # area-uniform: the share of points along the long axis matches the share of area
    axial = (sweep.points - fibula_bone.centre) @ fibula_bone.axes[:, 0]
    tri = fibula_bone.vertices[fibula_bone.faces].mean(axis=1)
    tri_axial = (tri - fibula_bone.centre) @ fibula_bone.axes[:, 0]
    share_points = np.mean(axial < 0)
    share_area = fibula_bone.face_areas[tri_axial < 0].sum() / fibula_bone.face_areas.sum()
    assert abs(share_points - share_area) < 0.03
    # AdaPoinTr-style crop keeps the part nearest a viewpoint
    cropped = sample_uniform(fibula_bone, SimulationConfig(mode="uniform", n_points=4000,
                                                           uniform_keep_fraction=0.5),
                             np.random.default_rng(0))
    assert len(cropped) == 4000
    span = np.ptp((cropped.points - fibula_bone.centre) @ fibula_bone.axes, axis=0)
    assert span.max() < 0.9 * fibula_bone.length
    paths = simulate_to_directory(FIBULA_STL, tmp_path / "u", count=1, seed=0, config=config)
    assert np.all(np.load(tmp_path / "u" / "sweep_0000_slices.npy") == -1)
    assert not (tmp_path / "u" / "sweep_0000_poses.npy").exists() and paths
