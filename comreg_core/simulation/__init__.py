"""Patient-specific synthetic US bone surfaces (paper, section 2) and random initial poses.

From a CT bone mesh alone: sweep trajectories from the bone's principal axes, rays cast from the
probe face with embree keeping only the first hit (acoustic shadowing), the paper's perturbations
(bounded + smoothed probe tilts, lognormal sweep speed, dropped slices, false intersections), and
a fixed-size point cloud in the CT frame with a per-point slice index.

Typical use::

    bone = BoneModel("fibula.stl")
    sweep = simulate_sweep(bone, SimulationConfig(), np.random.default_rng(0))
    T_us_ct = paper_initial_pose(rng, center=bone.centre)
"""

from comreg_core.simulation.bone import BoneModel
from comreg_core.simulation.config import (PerturbationConfig, ProbeConfig, SimulationConfig,
                                           TrajectoryConfig, load_simulation_config,
                                           simulation_config_from_dict)
from comreg_core.simulation.poses import (full_rotation_pose, paper_initial_pose,
                                          sample_initial_pose)
from comreg_core.simulation.simulator import (SimulatedSweep, SimulationError, cast_sweep,
                                              resample, sample_uniform, simulate_from_poses,
                                              simulate_sweep, simulate_sweeps,
                                              simulate_to_directory, sweep_rng)
from comreg_core.simulation.trajectory import SweepTrajectory, ray_grid, sample_trajectory

__all__ = [
    "BoneModel", "PerturbationConfig", "ProbeConfig", "SimulationConfig", "TrajectoryConfig",
    "load_simulation_config", "simulation_config_from_dict", "full_rotation_pose",
    "paper_initial_pose", "sample_initial_pose", "SimulatedSweep", "SimulationError",
    "cast_sweep", "resample", "sample_uniform", "simulate_from_poses", "simulate_sweep",
    "simulate_sweeps", "simulate_to_directory", "sweep_rng", "SweepTrajectory", "ray_grid",
    "sample_trajectory",
]
