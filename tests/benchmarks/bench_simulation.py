"""Simulator benchmark: sweeps per second on the real fibula (44k triangles), and realism
statistics of simulated versus the real tracked sweep.

Run from the repository root::

    .venv/bin/python -m tests.benchmarks.bench_simulation [--sweeps 40] [--no-pinned]

Threads for BLAS/OpenMP/torch are set to 1. The ray queries run on the calling thread (embree's
``rtcIntersect1`` per ray); embree may use worker threads to build the BVH, once per mesh. The
script measures in this process as launched, then again in a child pinned to one core with
``taskset -c 0`` (Linux), which is the "one core" figure. Timings on a shared machine are
pessimistic.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402

from comreg_core.simulation import (BoneModel, SimulationConfig, cast_sweep,  # noqa: E402
                                    resample, sample_trajectory, simulate_sweep, sweep_rng)
from tests.helpers import FIBULA_STL, SHARED_DATA  # noqa: E402


def _set_torch_threads() -> None:
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass


def measure(n_sweeps: int) -> dict[str, float]:
    """Build the bone once, then time ``n_sweeps`` default sweeps (20,000 points each)."""
    t0 = time.perf_counter()
    bone = BoneModel(FIBULA_STL)
    _ = bone.scene  # build the BVH
    build = time.perf_counter() - t0
    config = SimulationConfig()
    simulate_sweep(bone, config, sweep_rng(999, 0))  # warm-up
    t0 = time.perf_counter()
    rays = 0
    for i in range(n_sweeps):
        rays += simulate_sweep(bone, config, sweep_rng(0, i), resample_points=False).n_rays_cast
    raw_time = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in range(n_sweeps):
        simulate_sweep(bone, config, sweep_rng(0, i))
    full = time.perf_counter() - t0
    # breakdown of one sweep's stages, averaged
    stages = {"trajectory": 0.0, "cast+noise": 0.0, "resample": 0.0}
    for i in range(n_sweeps):
        rng = sweep_rng(1, i)
        t = time.perf_counter()
        traj = sample_trajectory(bone, config, rng)
        stages["trajectory"] += time.perf_counter() - t
        t = time.perf_counter()
        raw = cast_sweep(bone, traj, config, rng)
        stages["cast+noise"] += time.perf_counter() - t
        t = time.perf_counter()
        resample(raw, config.n_points, rng)
        stages["resample"] += time.perf_counter() - t
    uniform = replace(config, mode="uniform")
    t0 = time.perf_counter()
    for i in range(n_sweeps):
        simulate_sweep(bone, uniform, sweep_rng(0, i))
    uniform_time = time.perf_counter() - t0
    out = {"bone_build_s": build, "sweeps_per_s": n_sweeps / full,
           "raw_sweeps_per_s": n_sweeps / raw_time, "mrays_per_s": rays / raw_time / 1e6,
           "rays_per_sweep": rays / n_sweeps, "uniform_per_s": n_sweeps / uniform_time}
    out.update({f"ms_{k}": 1000 * v / n_sweeps for k, v in stages.items()})
    return out


def realism(n_sweeps: int = 10) -> None:
    from comreg_core.simulation.realism import (load_tracked_sweep_poses, real_sweep_statistics,
                                                sweep_statistics)

    bone = BoneModel(FIBULA_STL)
    real = load_tracked_sweep_poses(SHARED_DATA / "ultrabones100k-fibula")
    columns = {"real": real_sweep_statistics(bone, real)}
    base = SimulationConfig()
    base = replace(base, trajectory=replace(base.trajectory, longitudinal_probability=0.0))
    for noise in ("mean", "standardized"):
        config = replace(base, perturbation=replace(base.perturbation, speed_noise=noise))
        stats = []
        for i in range(n_sweeps):
            s = simulate_sweep(bone, config, sweep_rng(0, i))
            stats.append(sweep_statistics(bone, s.trajectory.T_ct_image, s.points,
                                          s.slice_index, config.probe.width_mm))
        short = "std" if noise == "standardized" else noise
        for label, fn in (("med", np.median), ("min", np.min), ("max", np.max)):
            columns[f"{short} {label}"] = {k: float(fn([s[k] for s in stats])) for k in stats[0]}
    print(f"\nRealism: the real sweep (trajectory; cloud = clean replay of its poses on the CT) "
          f"vs {n_sweeps} simulated transverse sweeps for each speed_noise reading (mean = the "
          "paper as written, std = standardized): median/min/max over sweeps")
    print(f"{'statistic':26s}" + "".join(f"{c:>10s}" for c in columns))
    for k in columns["real"]:
        print(f"{k:26s}" + "".join(f"{columns[c][k]:10.2f}" for c in columns))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sweeps", type=int, default=40)
    parser.add_argument("--no-pinned", action="store_true", help="skip the taskset child")
    parser.add_argument("--no-realism", action="store_true")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    _set_torch_threads()
    label = "pinned to one core (taskset -c 0)" if args.child else \
        f"as launched (affinity: {len(os.sched_getaffinity(0))} cores)"
    r = measure(args.sweeps)
    print(f"[{label}] fibula, {args.sweeps} sweeps, default config (20,000 points)")
    print(f"  bone build (checks, PCA, tables, BVH): {r['bone_build_s']:.2f} s")
    print(f"  sweeps/s: {r['sweeps_per_s']:.1f}   (raw, no resampling: "
          f"{r['raw_sweeps_per_s']:.1f}; {r['rays_per_sweep']:.0f} rays/sweep, "
          f"{r['mrays_per_s']:.2f} Mrays/s end to end)")
    print(f"  per sweep: trajectory {r['ms_trajectory']:.1f} ms, cast+noise "
          f"{r['ms_cast+noise']:.1f} ms, resample {r['ms_resample']:.1f} ms")
    print(f"  uniform mode: {r['uniform_per_s']:.1f} clouds/s")
    print(f"  target >= 10 sweeps/s on one core: {'met' if r['sweeps_per_s'] >= 10 else 'NOT met'}")
    if args.child:
        return
    if not args.no_pinned and shutil.which("taskset"):
        sys.stdout.flush()
        subprocess.run(["taskset", "-c", "0", sys.executable, "-m",
                        "tests.benchmarks.bench_simulation", "--child",
                        "--sweeps", str(args.sweeps)], check=False)
    if not args.no_realism:
        realism()


if __name__ == "__main__":
    main()
