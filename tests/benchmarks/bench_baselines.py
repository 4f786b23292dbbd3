"""Baselines benchmark: Open3D RANSAC (FPFH) + ICP and the ICP pseudo ground truth on fresh
simulated sweeps of the real fibula, each moved by a random initial pose (paper sampler).

Run from the repository root::

    .venv/bin/python -m tests.benchmarks.bench_baselines [--sweeps 20] [--seed 0]
        [--perturbation paper|full] [--max-iterations 100000] [--confidence 0.999]
        [--voxel-mm 1.0] [--out metrics.json]

Prints per-trial errors and, per method, success rate (RTE < 2 mm and RRE < 2 deg), flip rate
(RRE > 90 deg), median RTE/RRE and mean runtime (runtime = the method's own time per cloud; the
one-off CT preparation is printed separately). Open3D uses all cores it sees (OpenMP); timings on
a shared machine are pessimistic.
"""

from __future__ import annotations

import argparse
import os
import time

from comreg_core.evaluation import (BaselineConfig, RansacConfig, baseline_methods, evaluate,
                                    simulated_us_clouds, write_metrics)
from comreg_core.registration.geometry.surface import CTSurface
from tests.helpers import FIBULA_STL


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sweeps", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--perturbation", default="paper", choices=["paper", "full"])
    parser.add_argument("--max-iterations", type=int, default=RansacConfig.max_iterations)
    parser.add_argument("--confidence", type=float, default=RansacConfig.confidence)
    parser.add_argument("--voxel-mm", type=float, default=RansacConfig.voxel_size_mm)
    parser.add_argument("--out", default=None, help="also write metrics.json here")
    args = parser.parse_args(argv)

    print(f"fibula ({FIBULA_STL.name}), {args.sweeps} simulated sweeps (seed {args.seed}, "
          f"evaluation streams), perturbation '{args.perturbation}'; "
          f"{os.cpu_count()} CPU cores visible (shared: timings pessimistic)")
    t0 = time.perf_counter()
    surface = CTSurface(FIBULA_STL)
    clouds = simulated_us_clouds(surface, args.sweeps, args.seed)
    print(f"  {args.sweeps} sweeps simulated in {time.perf_counter() - t0:.1f} s "
          f"({len(clouds[0])} points each)")
    config = BaselineConfig(ransac=RansacConfig(voxel_size_mm=args.voxel_mm,
                                                max_iterations=args.max_iterations,
                                                confidence=args.confidence))
    t0 = time.perf_counter()
    methods = baseline_methods(["ransac", "icp-gt"], surface, config, seed=args.seed)
    print(f"  CT preparation: RANSAC target (sampling, voxel {args.voxel_mm} mm, FPFH) "
          f"{methods['ransac'].prepare_s:.2f} s, icp-gt matcher "
          f"{methods['icp-gt'].prepare_s:.2f} s (total {time.perf_counter() - t0:.2f} s)")
    print(f"  RANSAC: max_iterations {args.max_iterations}, confidence {args.confidence}")

    def progress(done, total, note=""):
        if done % 10 == 0 or done == total:
            print(f"  {done}/{total} registrations, {time.perf_counter() - t0:.0f} s", flush=True)

    t0 = time.perf_counter()
    result = evaluate(methods, clouds, surface, trials=args.sweeps, seed=args.seed,
                      perturbation=args.perturbation, progress=progress)
    print(f"  evaluation: {time.perf_counter() - t0:.1f} s wall")
    print(f"\n{'trial':>5s} {'init RTE':>9s} {'init RRE':>9s} | {'RANSAC RTE':>10s} {'RRE':>8s} "
          f"{'time':>6s} | {'icp-gt RTE':>10s} {'RRE':>7s}")
    rows = {(r["trial"], r["method"]): r for r in result["trials"]}
    fmt = lambda v, w, p: f"{v:{w}.{p}f}" if v is not None else f"{'fail':>{w}s}"  # noqa: E731
    for k in range(args.sweeps):
        r, g = rows[k, "ransac"], rows[k, "icp-gt"]
        print(f"{k:5d} {r['initial_RTE_mm']:9.1f} {r['initial_RRE_deg']:9.1f} | "
              f"{fmt(r['RTE_mm'], 10, 2)} {fmt(r['RRE_deg'], 8, 2)} {fmt(r['runtime_s'], 6, 2)} | "
              f"{fmt(g['RTE_mm'], 10, 3)} {fmt(g['RRE_deg'], 7, 3)}")
    print(f"\n{'method':8s} {'success':>8s} {'flip':>6s} {'med RTE mm':>11s} {'med RRE deg':>12s} "
          f"{'mean RTE':>9s} {'mean RRE':>9s} {'mean CD':>8s} {'mean HD95':>9s} "
          f"{'mean time s':>11s} {'failures':>8s}")
    for name, s in result["summary"].items():
        print(f"{name:8s} {100 * s['success_rate']:7.0f}% {100 * s['flip_rate']:5.0f}% "
              f"{s['RTE_mm']['median']:11.3f} {s['RRE_deg']['median']:12.3f} "
              f"{s['RTE_mm']['mean']:9.2f} {s['RRE_deg']['mean']:9.2f} "
              f"{s['CD_mm']['mean']:8.3f} {s['HD95_mm']['mean']:9.3f} "
              f"{s['runtime_s']['mean']:11.2f} {s['failures']:8d}")
    if args.out:
        print(f"\nwrote {write_metrics(result, args.out)}")


if __name__ == "__main__":
    main()
