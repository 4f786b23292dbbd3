"""Cohort cases built from shared data for the batch tests and benchmark: the real fibula sweep
(frames + tracking + calibration, truth = identity: CT and tracking share one frame) and
simulated sweeps of a tibia-like bone moved by a known rigid transform (truth = its inverse)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.helpers import FIBULA_STL, SHARED_DATA, random_rigid, tibia_like_mesh

FIBULA_SWEEP = SHARED_DATA / "ultrabones100k-fibula"


def write_tibia(folder: Path) -> Path:
    """The anatomical tibia-like bone as ``folder/tibia.stl`` (LPS)."""
    from comreg_core.io import SurfaceMesh, write_mesh

    vertices, faces = tibia_like_mesh(anatomical=True)
    return write_mesh(SurfaceMesh(vertices, faces), folder / "tibia.stl")


def simulated_case(folder: Path, name: str, seed: int, n_points: int = 3000
                   ) -> tuple[Path, Path, np.ndarray]:
    """A simulated sweep of the tibia-like bone (``n_points`` points), moved by a random rigid
    ``T_us_ct`` (seeded): writes ``folder/<name>_us.ply`` and ``folder/<name>_gt.tfm`` (the true
    ``T_ct_us``); returns ``(points file, truth file, the US points (n, 3))``."""
    from comreg_core.io import PointCloud, save_transform, write_points
    from comreg_core.simulation.bone import BoneModel
    from comreg_core.simulation.config import SimulationConfig
    from comreg_core.simulation.simulator import simulate_sweep
    from comreg_core.transforms import apply_transform, invert_rigid

    vertices, faces = tibia_like_mesh(anatomical=True)
    rng = np.random.default_rng(seed)
    sweep = simulate_sweep(BoneModel((vertices, faces)), SimulationConfig(n_points=n_points), rng)
    T_us_ct = random_rigid(rng, 50.0)
    points = apply_transform(T_us_ct, sweep.points)
    us = write_points(PointCloud(points), folder / f"{name}_us.ply")
    gt = save_transform(invert_rigid(T_us_ct), folder / f"{name}_gt.tfm")
    return us, gt, points


def identity_truth(folder: Path) -> Path:
    """``folder/identity.tfm``: the fibula sweep's truth (its tracking is in the CT frame)."""
    from comreg_core.io import save_transform

    return save_transform(np.eye(4), folder / "identity.tfm")


def fibula_row(name: str, truth: str) -> str:
    """A manifest row of the real fibula sweep (absolute paths into the shared data)."""
    return (f"{name},{FIBULA_STL},{FIBULA_SWEEP},{FIBULA_SWEEP / 'calibration.json'},,{truth}")


#: The manifest header of these cohorts.
HEADER = "case,ct,us,calibration,model,gt"
