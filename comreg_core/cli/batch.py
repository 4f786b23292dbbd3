"""``comreg batch``: a cohort through the shipped Snakefile. Snakemake is imported only when the
command runs (in :mod:`comreg_core.batch`)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from comreg_core.cli.comreg import app
from comreg_core.cli.errors import USER_ERROR_EXIT
from comreg_core.cli.options import NETWORK, OUTPUT, Preset

#: The panel of this command in 'comreg --help'.
PANEL = "Cohorts"
#: The panel of where and how the jobs run.
JOBS = "Jobs"

BATCH_MANIFEST = typer.Argument(
    ..., help="The cohort: a CSV (or YAML) file with one case per row and the columns case, ct, "
    "us (required), label, segment, calibration, model, gt, init, init_tolerance, landmarks_ct, "
    "landmarks_us (docs/batch.md). Relative paths are read from the manifest's folder.")
BATCH_OUT = typer.Option(..., "--out", "-o", rich_help_panel=OUTPUT, help="Output folder: "
                         "cases/<case>/ (each case's files, status and logs), summary.csv, "
                         "summary.html.")
BATCH_CORES = typer.Option(None, "--cores", min=1, rich_help_panel=JOBS, help="Local CPU cores "
                           "to use at once (default: all).")
BATCH_PROFILE = typer.Option(None, "--profile", rich_help_panel=JOBS, help="A Snakemake "
                             "profile: a folder with a config.yaml (executor, jobs, "
                             "default-resources, ...), e.g. examples/slurm to run the jobs on a "
                             "SLURM cluster.")
BATCH_DRY_RUN = typer.Option(False, "--dry-run", "-n", rich_help_panel=JOBS, help="List the jobs "
                             "that would run, with their threads and resources, and run "
                             "nothing.")
BATCH_PRETRAIN_MINUTES = typer.Option(
    0.0, "--pretrain-minutes", min=0.0, rich_help_panel=NETWORK, help="Pretrain each case "
    "without a model for this many minutes first (a GPU job on a cluster); 0: register by the "
    "pose search alone.")
BATCH_PRESET = typer.Option(Preset.cpu, rich_help_panel=NETWORK,
                            help="Network size of the pretraining.")


@app.command("batch", rich_help_panel=PANEL)
def batch(
    manifest: Path = BATCH_MANIFEST,
    cores: Optional[int] = BATCH_CORES,
    profile: Optional[Path] = BATCH_PROFILE,
    dry_run: bool = BATCH_DRY_RUN,
    pretrain_minutes: float = BATCH_PRETRAIN_MINUTES,
    preset: Preset = BATCH_PRESET,
    out: Path = BATCH_OUT,
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
        raise typer.Exit(USER_ERROR_EXIT) from None
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
