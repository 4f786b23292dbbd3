"""Benchmark: the learning curve of per-patient pretraining against wall-clock minutes.

Run: ``.venv/bin/python -m tests.benchmarks.bench_learning [--minutes 30] [--preset cpu]
[--bone PATH|tibia-like] [--set model.pose.head=mlp ...] [--threads N] [--out DIR]``

Pretrains on ``--bone`` (default: the shared real fibula CT) for ``--minutes`` of wall clock and
prints, per validated epoch, on the run's fixed held-out simulated sweeps: completion CD (mm, the
evaluation's definition), coarse RRE / RTE (medians) and the success and flip rates of the
paper's plain pipeline (network + differentiable ICP, no pose search). Row ``min 0.0`` is the
**untrained-model control**: the same network before its first step. ``--set`` changes one
setting (dotted path into the run config) so a lever can be measured alone. The run folder is
a normal one: ``comreg evaluate simulated --model RUN ...`` can evaluate it afterwards; beside
it, ``RUN_untrained`` holds the same network as it was before its first step (same config, seed
and initial weights, 0 epochs), the untrained control for ``comreg evaluate``.
"""

from __future__ import annotations

import argparse
import csv
import logging
import shutil
import sys
import time
from pathlib import Path

import yaml

COLUMNS = (("min", "time_s", 60.0), ("epoch", "epoch", None), ("samples", "samples", None),
           ("CD_mm", "val_completion_CD_mm_median", None),
           ("coarseRRE", "val_coarse_RRE_deg_median", None),
           ("improved", "val_coarse_improved_share", None),
           ("coarseRTE", "val_coarse_RTE_mm_median", None),
           ("fineRRE", "val_RRE_deg_median", None), ("fineRTE", "val_RTE_mm_median", None),
           ("success", "val_success_rate", None), ("flips", "val_flip_rate", None))


def parse_setting(text: str) -> dict:
    """``a.b.c=value`` -> ``{"a": {"b": {"c": value}}}`` (value parsed as YAML)."""
    key, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"--set needs key=value, got {text!r}")
    out: dict = yaml.safe_load(value)
    for part in reversed(key.split(".")):
        out = {part: out}
    return out


def read_curve(log_csv: Path) -> list[dict[str, str]]:
    """The validated rows of a run's ``training_log.csv``."""
    with open(log_csv, newline="") as f:
        return [r for r in csv.DictReader(f) if r.get("val_RRE_deg_median")]


def print_curve(rows: list[dict[str, str]]) -> None:
    print("  ".join(f"{name:>9}" for name, _, _ in COLUMNS))
    for r in rows:
        cells = []
        for _, key, div in COLUMNS:
            value = float(r[key]) if r.get(key) else float("nan")
            cells.append(f"{value / div if div else value:>9.3g}")
        print("  ".join(cells))


def write_tibia_like(path: Path) -> Path:
    """The tibia-like bone of :func:`tests.helpers.tibia_like_mesh` as a mesh file."""
    from comreg_core.io.meshes import SurfaceMesh, write_mesh
    from tests.helpers import tibia_like_mesh

    path.parent.mkdir(parents=True, exist_ok=True)
    write_mesh(SurfaceMesh(*tibia_like_mesh()), path)
    return path


def write_untrained_control(run_dir: Path, out_dir: Path) -> Path:
    """``out_dir/checkpoint.pt``: the run's checkpoint with the network's weights as they were
    before the first step (the trainer seeds torch with the run seed right before building the
    network, so the same seed rebuilds the same initial weights), epoch 0, no validation."""
    import torch

    from comreg_core.model.comreg import ComRegNet
    from comreg_core.training.checkpoint import MODEL_ENTRIES, load_checkpoint, save_checkpoint
    from comreg_core.training.config import config_from_yaml

    state = load_checkpoint(run_dir)
    cfg = config_from_yaml(state["config_yaml"])
    torch.manual_seed(cfg.seed)
    untrained = {key: state[key] for key in MODEL_ENTRIES if key in state}
    for key in ("validation", "validation_epoch", "initial_error"):
        untrained.pop(key, None)
    untrained.update(model=ComRegNet(cfg.model).state_dict(), epoch=0, samples_seen=0,
                     elapsed_s=0.0)
    out_dir.mkdir(parents=True, exist_ok=True)
    return save_checkpoint(untrained, out_dir / "checkpoint.pt")


def main(argv: list[str] | None = None) -> None:
    import torch

    from comreg_core.config import deep_merge
    from comreg_core.training import pretrain
    from comreg_core.training.trainer import BudgetTooShortError
    from tests.helpers import FIBULA_STL

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--preset", default="cpu")
    p.add_argument("--bone", type=Path, default=FIBULA_STL,
                   help="CT bone mesh, or 'tibia-like' for tests.helpers.tibia_like_mesh()")
    p.add_argument("--set", type=parse_setting, action="append", default=[], dest="settings")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("out/bench_learning/run"))
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", stream=sys.stdout)
    if args.threads:
        torch.set_num_threads(args.threads)
    overrides: dict = {}
    for setting in args.settings:
        overrides = deep_merge(overrides, setting)
    if str(args.bone) == "tibia-like":
        args.bone = write_tibia_like(Path("out/bones/tibia_like.stl"))
    if args.out.exists():
        shutil.rmtree(args.out)
    start = time.perf_counter()
    try:
        result = pretrain(args.bone, args.out, preset=args.preset, config=overrides,
                          max_minutes=args.minutes, seed=args.seed, device="cpu")
    except BudgetTooShortError as error:
        result = error.result
    wall = time.perf_counter() - start
    print(f"\n{args.preset} {overrides or ''} on {args.bone.name}, {torch.get_num_threads()} "
          f"threads: {result.epochs} epochs, {result.samples_seen} samples in {wall / 60:.1f} "
          f"min wall ({result.samples_seen / wall:.2f} samples/s); run {result.run_dir}")
    print(f"initial misalignment of the validation set: "
          f"{ {k: round(v, 1) for k, v in result.initial_error.items()} }")
    print_curve(read_curve(result.log_csv))
    control = write_untrained_control(result.run_dir,
                                      result.run_dir.with_name(result.run_dir.name + "_untrained"))
    print(f"untrained control: {control.parent}")


if __name__ == "__main__":
    main()
