"""Benchmark: pretrain the ``cpu`` preset on the real fibula for a fixed time; print the epoch log.

Run: ``.venv/bin/python -m tests.benchmarks.bench_pretrain [--minutes 30] [--out DIR]
[--preset cpu] [--seed 0] [--device auto] [--workers 1] [--resume]``

Writes a normal run folder (default ``out/bench_pretrain/run``: config.yaml, ct_fingerprint.json,
checkpoint.pt, training_log.csv) that ``comreg register`` / ``comreg evaluate`` can use, logs each
epoch as it ends, and prints the whole epoch log and the held-out validation summary at the end.
Without ``--minutes`` the default 30-minute budget of issue 5 is used; ``--minutes 1`` is a quick
smoke run.
"""

from __future__ import annotations

import argparse
import csv
import logging
import shutil
import sys
import time
from pathlib import Path

COLUMNS = ("epoch", "samples", "time_s", "loss", "completion", "registration",
           "val_completion", "val_RTE_mm_median", "val_RRE_deg_median",
           "val_coarse_RTE_mm_median", "val_coarse_RRE_deg_median", "val_success_rate",
           "val_flip_rate")


def main(argv: list[str] | None = None) -> None:
    from comreg_core.training import pretrain
    from tests.helpers import FIBULA_STL

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--out", type=Path, default=Path("out/bench_pretrain/run"))
    p.add_argument("--preset", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto")
    p.add_argument("--workers", type=int, default=None, help="data worker processes")
    p.add_argument("--resume", action="store_true")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", stream=sys.stdout)
    if args.out.exists() and not args.resume:
        shutil.rmtree(args.out)
    config = {} if args.workers is None else {"data": {"workers": args.workers}}
    start = time.perf_counter()
    result = pretrain(FIBULA_STL, args.out, preset=args.preset, config=config,
                      max_minutes=args.minutes, resume=args.resume,
                      seed=None if args.resume else args.seed, device=args.device)
    wall = time.perf_counter() - start
    print(f"\npretrain {args.preset} on {FIBULA_STL.name}: {result.epochs} epochs, "
          f"{result.samples_seen} samples, {result.elapsed_s / 60:.1f} min training, "
          f"{wall / 60:.1f} min wall, stopped by {result.stopped}, device {result.device}")
    print(f"run folder: {result.run_dir}")
    print(f"initial misalignment of the validation set: {result.initial_error}")
    with open(result.log_csv, newline="") as f:
        rows = list(csv.DictReader(f))
    print("\n" + "  ".join(f"{c:>12.12}" for c in COLUMNS))
    for r in rows:
        print("  ".join(f"{_short(r.get(c, '')):>12}" for c in COLUMNS))
    if result.validation:
        print("\nlast validation:", {k: round(v, 4) for k, v in result.validation.items()})


def _short(text: str) -> str:
    try:
        return f"{float(text):.4g}"
    except ValueError:
        return text


if __name__ == "__main__":
    main()
