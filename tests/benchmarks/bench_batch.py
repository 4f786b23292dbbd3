"""Benchmark: ``comreg batch`` on 8 cases with ``--cores 2`` against the same cases run one
after the other by the single commands (issue 36).

``.venv/bin/python -m tests.benchmarks.bench_batch [--cases 8] [--cores 2]``

The cohort: the real fibula sweep (frames + tracking + calibration; extract-us) and simulated
sweeps of a tibia-like bone (3,000 points each, moved by known transforms), all registered by
the pose search alone (no pretraining), with a report each. The one-after-the-other run types
each stage's command (``comreg extract-ct``, ``extract-us``, ``register``, ``report``; the
very argument lists the Snakefile's rules run) in its own process into another folder. Prints
both wall times, their ratio, and whether the results are the same (every case's
``result.json`` ``T_ct_us``, bit for bit, else the largest difference).
Writes under ``out/bench_batch/`` (removed first).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

OUT = Path("out/bench_batch")


def make_cohort(folder: Path, cases: int) -> Path:
    """The manifest of ``cases`` cases (module docstring) in ``folder``."""
    from tests.batch.cohort import HEADER, fibula_row, identity_truth, simulated_case, write_tibia

    folder.mkdir(parents=True)
    write_tibia(folder)
    identity_truth(folder)
    rows = [HEADER, fibula_row("fibula", "identity.tfm")]
    for k in range(1, cases):
        simulated_case(folder, f"tibia{k}", seed=k)
        rows.append(f"tibia{k},tibia.stl,tibia{k}_us.ply,,,tibia{k}_gt.tfm")
    manifest = folder / "cohort.csv"
    manifest.write_text("\n".join(rows) + "\n")
    return manifest


def main(argv: list[str] | None = None) -> None:
    from comreg_core.batch.plan import plan_cases

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=8)
    parser.add_argument("--cores", type=int, default=2)
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    shutil.rmtree(OUT, ignore_errors=True)
    manifest = make_cohort(OUT / "cohort", args.cases)

    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "comreg_core.cli", "batch", str(manifest),
                           "--out", str(OUT / "batch"), "--cores", str(args.cores)],
                          capture_output=True, text=True)
    batch_s = time.perf_counter() - started
    if done.returncode != 0:
        sys.exit(f"comreg batch failed:\n{done.stderr[-3000:]}")

    plans = plan_cases(manifest, OUT / "one_by_one")
    started = time.perf_counter()
    for plan in plans.values():
        for stage in plan.stages:
            step = subprocess.run([sys.executable, "-m", "comreg_core.cli",
                                   *plan.command(stage)], capture_output=True, text=True)
            if step.returncode != 0:
                sys.exit(f"{plan.case.name} {stage} failed: {step.stderr[-2000:]}")
    single_s = time.perf_counter() - started

    batch_plans = plan_cases(manifest, OUT / "batch")
    worst, same = 0.0, True
    for name, plan in plans.items():
        one = np.asarray(json.loads((plan.registration / "result.json").read_text())["T_ct_us"])
        both = np.asarray(json.loads((batch_plans[name].registration / "result.json")
                                     .read_text())["T_ct_us"])
        same &= bool(np.array_equal(one, both))
        worst = max(worst, float(np.abs(one - both).max()))
    print(f"{args.cases} cases (1 real fibula sweep, {args.cases - 1} simulated), pose search "
          f"alone, with reports:")
    print(f"  comreg batch --cores {args.cores}: {batch_s:7.1f} s wall")
    print(f"  single commands one after the other: {single_s:7.1f} s wall")
    print(f"  ratio (one after the other / batch): {single_s / batch_s:.2f}")
    print("  results: " + ("the same T_ct_us in every case (bit for bit)" if same else
                           f"T_ct_us differ by up to {worst:.3g} (matrix entries)"))


if __name__ == "__main__":
    main()
