"""Benchmark: a pretrained run against the baselines on the same cases (issue 5, benchmarks b–d).

Run after ``bench_pretrain`` (or on any run folder):
``.venv/bin/python -m tests.benchmarks.bench_evaluate [--run out/bench_pretrain/run] [--trials 100]``

Prints, for ComReg with its pose search (``comreg``), the paper's plain pipeline
(``comreg-plain``), Open3D RANSAC+FPFH+ICP and ICP from the ground truth (the pseudo ground
truth): success and flip rates, median/mean RTE and RRE, CD, HD95 and mean runtime on ``--trials``
fresh simulated sweeps of the fibula with the paper's initial poses, and the same cases with the
full-rotation perturbation (``--full-trials``, ComReg only); registration latency with ICP on 4096
points, with and without the pose search; and the same evaluation on the real fibula sweep's bone
points (extracted from its B-mode frames; CT and tracking share one frame, so the ground truth is
the identity).
Writes metrics.json files under ``out/bench_evaluate/``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

OUT = Path("out/bench_evaluate")


def _print_summary(title: str, result: dict) -> None:
    print(f"\n{title}")
    print(f"{'method':>12} {'success':>8} {'flips':>6} {'RTE med':>8} {'RTE mean':>9} "
          f"{'RRE med':>8} {'RRE mean':>9} {'CD':>6} {'HD95':>6} {'time s':>7} {'ambiguous':>9}")
    for name, s in result["summary"].items():
        print(f"{name:>12} {s['success_rate']:8.1%} {s['flip_rate']:6.1%} "
              f"{s['RTE_mm']['median']:8.2f} {s['RTE_mm']['mean']:9.2f} "
              f"{s['RRE_deg']['median']:8.2f} {s['RRE_deg']['mean']:9.2f} "
              f"{s['CD_mm']['mean']:6.2f} {s['HD95_mm']['mean']:6.2f} "
              f"{s['runtime_s']['mean']:7.3f} "
              + ("" if s.get("ambiguous_rate") is None else f"{s['ambiguous_rate']:9.1%}"))


def main(argv: list[str] | None = None) -> None:
    from comreg_core.evaluation.methods import registration_methods
    from comreg_core.evaluation.evaluate import evaluate, simulated_us_clouds, write_metrics
    from comreg_core.register import Registrar
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import extract_us_surface
    from comreg_core.training import run_ct_mesh
    from tests.helpers import SHARED_DATA

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", type=Path, default=Path("out/bench_pretrain/run"))
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--full-trials", type=int, default=100)
    p.add_argument("--real-trials", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if not (args.run / "checkpoint.pt").is_file():
        print(f"no run at {args.run}: run `python -m tests.benchmarks.bench_pretrain` first")
        return
    ct = run_ct_mesh(args.run)
    methods = registration_methods("all", args.run, ct, seed=args.seed)

    start = time.perf_counter()
    simulated = evaluate(methods, "simulated", ct, trials=args.trials, seed=args.seed)
    write_metrics(simulated, OUT / "simulated" / "metrics.json")
    _print_summary(f"{args.trials} simulated fibula sweeps, paper initial poses "
                   f"({time.perf_counter() - start:.0f} s)", simulated)
    if args.full_trials:
        start = time.perf_counter()
        ours = {name: methods[name] for name in ("comreg", "comreg-plain")}
        full = evaluate(ours, "simulated", ct, trials=args.full_trials, seed=args.seed,
                        perturbation="full")
        write_metrics(full, OUT / "simulated_full" / "metrics.json")
        _print_summary(f"{args.full_trials} simulated fibula sweeps, full-rotation initial "
                       f"poses ({time.perf_counter() - start:.0f} s)", full)

    latency = Registrar.from_run(args.run, "auto", icp_points=4096)
    cloud = simulated_us_clouds(ct, 1, seed=args.seed)[0]
    for search in (True, False):
        times = [latency.register(cloud, seed=i, search=search).timings
                 for i in range(10)]
        totals = [t["total"] for t in times]
        stages = {k: float(np.median([t[k] for t in times])) for k in times[0]}
        print(f"\nregistration latency ({'with' if search else 'without'} the pose search, ICP "
              f"on 4096 points, {latency.device}): median {np.median(totals):.3f} s, max "
              f"{np.max(totals):.3f} s; stages (median s): "
              + ", ".join(f"{k} {v:.3f}" for k, v in stages.items()))

    sweep = read_tracked_sweep(SHARED_DATA / "ultrabones100k-fibula")
    real = extract_us_surface(sweep).points.points
    real_result = evaluate(methods, real, ct, trials=args.real_trials, seed=args.seed)
    write_metrics(real_result, OUT / "real" / "metrics.json")
    _print_summary(f"real fibula sweep ({len(real)} bone points from the B-mode frames), "
                   f"{args.real_trials} paper initial poses", real_result)


if __name__ == "__main__":
    main()
