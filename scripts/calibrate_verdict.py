"""Figures behind the verdict thresholds (comreg_core/registration/judgement/verdict.py).

    .venv/bin/python scripts/calibrate_verdict.py [--sims N] [--real-points FILE.npy]

Judges, on the shared fibula CT, simulated sweeps (seeds 100...) and the shared real fibula sweep
at their correct pose and with the failures the verdict must catch (slides along the long axis,
isotropic scale errors of the US cloud then the best rigid ICP fit), and prints every figure.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from comreg_core.registration.geometry.icp import point_to_plane_icp  # noqa: E402
from comreg_core.registration.geometry.surface import CTSurface  # noqa: E402
from comreg_core.registration.judgement.verdict import judge_registration  # noqa: E402
from comreg_core.transforms import apply_transform  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "ultrabones100k-fibula"


def long_axis(vertices: np.ndarray) -> np.ndarray:
    """First principal axis of the CT vertices (unit)."""
    centred = vertices - vertices.mean(0)
    return np.linalg.svd(centred, full_matrices=False)[2][0]


def slide(mm: float, axis: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = mm * axis
    return T


def scaled(points: np.ndarray, s: float) -> np.ndarray:
    c = points.mean(0)
    return c + s * (points - c)


def cases(points, T_correct, surface, matcher, axis):
    """(name, US points, transform) of the correct pose and the failures."""
    yield "correct", points, T_correct
    for mm in (10, 20, -20):
        yield f"slide {mm:+d} mm", points, slide(mm, axis) @ T_correct
    for s in (0.85, 0.9, 1.1, 1.15):
        moved = scaled(apply_transform(T_correct, points), s)
        T = point_to_plane_icp(moved, np.eye(4), matcher, iterations=100,
                               tolerance_mm=1e-5).T
        yield f"scale {s:.2f} + ICP", moved, T


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--sims", type=int, default=4)
    parser.add_argument("--real-points", type=Path, default=None,
                        help="the real sweep's extracted points (.npy), to skip the extraction")
    args = parser.parse_args()
    surface = CTSurface(SHARED / "fibula.stl")
    matcher = surface.matcher(5.0, n_samples=100_000)  # ICP pairs within 5 mm
    axis = long_axis(surface.vertices)
    sweeps = []
    if args.real_points is not None:
        real = np.load(args.real_points)
    else:
        from comreg_core.io.tracked_us import read_tracked_sweep
        from comreg_core.surfaces.us import extract_us_surface

        real = extract_us_surface(read_tracked_sweep(SHARED)).points.points
    sweeps.append(("real (recorded pose)", real, np.eye(4)))
    T_icp = point_to_plane_icp(real, np.eye(4), matcher, iterations=100, tolerance_mm=1e-5).T
    sweeps.append(("real (ICP from it)", real, T_icp))
    from comreg_core.simulation.bone import BoneModel
    from comreg_core.simulation.simulator import simulate_sweep

    bone = BoneModel((surface.vertices, surface.faces))
    for i in range(args.sims):
        sweep = simulate_sweep(bone, rng=np.random.default_rng(100 + i))
        sweeps.append((f"sim seed {100 + i}", sweep.points, np.eye(4)))
    print(f"{'sweep':22s} {'case':16s} verdict median  p90   <=2mm  cover shift  scale  gain")
    for name, points, T0 in sweeps:
        for case, pts, T in cases(points, T0, surface, matcher, axis):
            v = judge_registration(pts, T, surface)
            f = v.figures
            print(f"{name:22s} {case:16s} {v.verdict:7s} {f['median_mm']:5.2f} {f['p90_mm']:6.2f}"
                  f" {f['within_2mm']:6.3f} {f['coverage']:6.3f} {f['refit_shift_mm']:5.1f} "
                  f"{f['refit_scale']:6.3f} {f['refit_scale_gain']:5.2f}", flush=True)


if __name__ == "__main__":
    main()
