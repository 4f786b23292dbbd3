"""``comreg batch`` (registered on ``app`` in :mod:`comreg_core.cli`; its own module to keep the
CLI file short). Snakemake is imported only when the command runs."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from comreg_core import choices

Preset = Enum("Preset", {name: name for name in choices.PRESETS}, type=str)


def batch(
    manifest: Path = typer.Argument(..., help="The cohort: a CSV (or YAML) file with one case "
                                    "per row and the columns case, ct, us (required), label, "
                                    "segment, calibration, model, gt, init, init_tolerance, "
                                    "landmarks_ct, landmarks_us (docs/batch.md). Relative "
                                    "paths are read from the manifest's folder."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder: cases/<case>/ (each "
                             "case's files, status and logs), summary.csv, summary.html."),
    cores: Optional[int] = typer.Option(None, "--cores", min=1, help="Local CPU cores to use "
                                        "at once (default: all)."),
    pretrain_minutes: float = typer.Option(0.0, "--pretrain-minutes", min=0.0, help="Pretrain "
                                           "each case without a model for this many minutes "
                                           "first (a GPU job on a cluster); 0: register by the "
                                           "pose search alone."),
    preset: Preset = typer.Option(Preset.cpu, help="Network size of the pretraining."),
    profile: Optional[Path] = typer.Option(None, "--profile", help="A Snakemake profile: a "
                                           "folder with a config.yaml (executor, jobs, "
                                           "default-resources, ...), e.g. examples/slurm to "
                                           "run the jobs on a SLURM cluster."),
    dry_run: bool = typer.Option(False, "--dry-run", "-n", help="List the jobs that would run, "
                                 "with their threads and resources, and run nothing."),
) -> None:
    """Run a cohort: every case of the manifest through extract-ct, pretrain (with
    --pretrain-minutes, for cases without a model), extract-us (unless the case gives US
    points), register and report, then the cohort summary (summary.csv, summary.html).

    The workflow is a Snakefile shipped with ComReg, run by Snakemake: jobs run in parallel on
    the local cores, or on a cluster with --profile. A rerun redoes only what is missing or
    whose inputs changed. A case that fails is recorded with its one-line error in
    summary.csv and the others go on. The manifest is checked in full first: every problem is
    one line with its row number.
    """
    from comreg_core.batch.manifest import ManifestError
    from comreg_core.batch.runner import run_batch

    try:
        run = run_batch(manifest, out, cores=cores, pretrain_minutes=pretrain_minutes,
                        preset=preset.value, profile=profile, dry_run=dry_run)
    except ManifestError as exc:
        for line in exc.lines:
            typer.echo(f"error: {line}", err=True)
        raise typer.Exit(2) from None
    if dry_run:
        typer.echo(f"{len(run.jobs)} job(s) would run" + (":" if run.jobs else
                                                           " (everything is up to date)"))
        for job in run.jobs:
            typer.echo(f"  {job.line()}")
        return
    typer.echo(f"ran {len(run.jobs)} job(s)" if run.jobs else
               "nothing to do: everything is up to date")
    typer.echo(_summary_line(run.summary_csv))


def _summary_line(path: Path) -> str:
    """``wrote summary.csv: N of M cases registered (K failed: ...)``."""
    import csv

    with open(path, newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    failed = [row["case"] for row in rows if row["status"] != "ok"]
    return (f"{path}: {len(rows) - len(failed)} of {len(rows)} cases registered"
            + (f"; failed: {', '.join(failed)} (see the error column)" if failed else "")
            + f"; {path.with_suffix('.html')}")
