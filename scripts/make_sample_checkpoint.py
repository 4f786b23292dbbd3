"""Rebuild resources/sample/fibula_cpu.pt: the model ``comreg demo`` registers with.

Extracts the sample's CT surface exactly as the demo does, pretrains the ``cpu`` preset on it for
``--minutes`` (default 30, the issue's budget on 2 CPU cores) into ``out/sample_run``, and exports
the weights (float16, no optimiser state) to resources/sample/fibula_cpu.pt. Run from the
repository root:

    .venv/bin/python scripts/make_sample_checkpoint.py [--minutes 30] [--seed 0]
"""

import argparse
import logging
import shutil
import sys
from pathlib import Path

from comreg_core.demo import SAMPLE_MODEL, write_sample_ct_surface
from comreg_core.training import export_model, pretrain

ROOT = Path(__file__).resolve().parents[1]
parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--minutes", type=float, default=30.0)
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--run", type=Path, default=ROOT / "out" / "sample_run")
args = parser.parse_args()
logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", stream=sys.stdout)

if args.run.exists():
    shutil.rmtree(args.run)
args.run.mkdir(parents=True)
ct_path = write_sample_ct_surface(args.run.parent / "sample_ct_bone.stl")
result = pretrain(ct_path, args.run, preset="cpu", max_minutes=args.minutes, seed=args.seed)
export_model(args.run, SAMPLE_MODEL)
print(f"trained {result.epochs} epochs in {result.elapsed_s / 60:.1f} min; validation "
      f"{result.validation}; wrote {SAMPLE_MODEL} ({SAMPLE_MODEL.stat().st_size / 1e6:.1f} MB)")
