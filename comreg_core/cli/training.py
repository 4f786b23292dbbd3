"""``comreg simulate`` and ``comreg pretrain``: US sweeps simulated from the CT bone, and the
patient's network trained on them."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from comreg_core import runs
from comreg_core.cli.comreg import app
from comreg_core.cli.options import (INPUTS, NETWORK, OUTPUT, SWEEPS, VERDICT, Device, Preset,
                                     progress_bar)

#: The panel of these commands in 'comreg --help'.
PANEL = "Training"
#: The panel of pretrain's budget, epochs, resume and seed.
SCHEDULE = "Schedule"

# --- comreg simulate -----------------------------------------------------------------------------
SIMULATE_CT_MESH = typer.Argument(..., help="CT bone mesh (.stl, .ply, .obj, .vtk, .vtp), in mm.")
SIMULATE_OUT = typer.Option(..., "--out", "-o", rich_help_panel=OUTPUT, help="Output folder.")
SIMULATE_COUNT = typer.Option(1, "--count", "-n", min=1, rich_help_panel=SWEEPS,
                              help="Number of sweeps.")
SIMULATE_SEED = typer.Option(0, "--seed", min=0, rich_help_panel=SWEEPS, help="Random seed; the "
                             "same seed gives the same sweeps.")
SIMULATE_CONFIG = typer.Option(None, "--config", rich_help_panel=INPUTS, help="Simulation "
                               "config YAML (e.g. the config.yaml of an earlier run).")


@app.command("simulate", rich_help_panel=PANEL)
def simulate(
    ct_mesh: Path = SIMULATE_CT_MESH,
    config: Optional[Path] = SIMULATE_CONFIG,
    count: int = SIMULATE_COUNT,
    seed: int = SIMULATE_SEED,
    out: Path = SIMULATE_OUT,
) -> None:
    """Simulate tracked freehand US sweeps of a CT bone (paper, section 2).

    Rays are cast from a linear probe moving along trajectories drawn from the bone's geometry;
    only the first hit per ray is kept (acoustic shadowing), with the paper's probe tilts,
    non-uniform speed, dropped slices and false hits. Writes sweep_NNNN.ply (points in the mesh's
    frame), sweep_NNNN_slices.npy (slice index per point), sweep_NNNN_poses.npy (probe image
    poses) and config.yaml.
    """
    from comreg_core.simulation import simulate_to_directory

    with progress_bar(count, "simulating") as advance:
        paths = simulate_to_directory(ct_mesh, out, count=count, seed=seed, config=config,
                                      progress=lambda done, total, note="": advance(done))
    typer.echo(f"wrote {len(paths)} sweep(s) and config.yaml to {out}")


# --- comreg pretrain -----------------------------------------------------------------------------
PRETRAIN_CT_MESH = typer.Argument(..., help="The patient's CT bone mesh (mm), a closed surface.")
PRETRAIN_OUT = typer.Option(..., "--out", "-o", rich_help_panel=OUTPUT, help="Run folder "
                            "(checkpoint, config.yaml, training_log.csv, CT fingerprint).")
PRETRAIN_CONFIG = typer.Option(None, "--config", rich_help_panel=INPUTS, help="YAML overrides "
                               "of the preset (sections model, simulation, data, training).")
PRETRAIN_PRESET = typer.Option(Preset.cpu, rich_help_panel=NETWORK, help="Network size and "
                               "schedule: 'cpu' (small, fast on a laptop) or 'paper' (the "
                               "paper's, for a GPU).")
PRETRAIN_DEVICE = typer.Option(Device.auto, rich_help_panel=NETWORK, help="Where to train.")
PRETRAIN_MAX_MINUTES = typer.Option(None, "--max-minutes", min=0.1, rich_help_panel=SCHEDULE,
                                    help="Wall-clock budget of this whole command (set-up and "
                                    "validation included); less than one epoch in it is an "
                                    "error.")
PRETRAIN_EPOCHS = typer.Option(None, "--epochs", min=1, rich_help_panel=SCHEDULE,
                               help="Total epochs.")
PRETRAIN_RESUME = typer.Option(False, "--resume", rich_help_panel=SCHEDULE, help="Continue the "
                               "run in --out from its last checkpoint.")
PRETRAIN_SEED = typer.Option(None, "--seed", min=0, rich_help_panel=SCHEDULE,
                             help="Run seed (default 0).")
PRETRAIN_CALIBRATION_SWEEPS = typer.Option(
    0, "--calibration-sweeps", min=0, rich_help_panel=VERDICT, help="Then also calibrate the "
    "verdict on this many simulated sweeps (as 'comreg calibrate', at least 4; about 1.5 s each on "
    "2 cores) into the run folder; 0: not.")
# comreg_core.registration.search.priors.PRIOR_KINDS (imported when used: it pulls in numba)
PRETRAIN_CALIBRATION_PRIOR = typer.Option(
    "none", "--calibration-prior", rich_help_panel=VERDICT, help="What the registrations with "
    "this run will know, as 'comreg calibrate --prior': none, init or landmark. Needs "
    "--calibration-sweeps.")


@app.command("pretrain", rich_help_panel=PANEL)
def pretrain(
    ct_mesh: Path = PRETRAIN_CT_MESH,
    config: Optional[Path] = PRETRAIN_CONFIG,
    preset: Preset = PRETRAIN_PRESET,
    device: Device = PRETRAIN_DEVICE,
    max_minutes: Optional[float] = PRETRAIN_MAX_MINUTES,
    epochs: Optional[int] = PRETRAIN_EPOCHS,
    resume: bool = PRETRAIN_RESUME,
    seed: Optional[int] = PRETRAIN_SEED,
    calibration_sweeps: int = PRETRAIN_CALIBRATION_SWEEPS,
    calibration_prior: str = PRETRAIN_CALIBRATION_PRIOR,
    out: Path = PRETRAIN_OUT,
) -> None:
    """Pretrain ComReg for one patient on US sweeps simulated from their CT bone.

    Each sample is a simulated sweep moved by a random rigid transform; the network learns shape
    completion and the inverse transform end to end (paper, section 2). Checkpoints are written
    atomically; a killed run continues with --resume. On several GPUs or machines: start it with
    torchrun (README, "Training on several GPUs or machines").
    """
    from comreg_core.training import pretrain as run_pretraining

    _check_calibration_options(calibration_sweeps, calibration_prior)
    with progress_bar(1000, "pretraining") as advance:
        result = run_pretraining(
            ct_mesh, out, preset=preset.value, config=config, max_minutes=max_minutes,
            epochs=epochs, resume=resume, seed=seed, device=device.value,
            progress=lambda done, total, note="": advance(int(1000 * done / max(total, 1))))
    if result.rank:
        return  # rank 0 reports for the job
    _report_pretraining(result)
    if calibration_sweeps:
        from comreg_core.evaluation.calibrate import calibrate

        path = calibrate(ct_mesh, sweeps=calibration_sweeps, prior=calibration_prior).save(
            Path(result.run_dir) / runs.CALIBRATION)
        typer.echo(f"wrote {path}: register with this run judges by p_correct"
                   + ("" if calibration_prior == "none" else
                      f" (calibrated for registrations with a prior of kind "
                      f"'{calibration_prior}')"))


def _check_calibration_options(sweeps: int, prior: str) -> None:
    """Refuse, before any training, calibration options that would fail after it: 1-3 sweeps,
    an unknown kind of prior, or a prior without sweeps."""
    from comreg_core.errors import ComRegError
    from comreg_core.evaluation.calibrate import CALIBRATION_SWEEPS, MIN_SWEEPS
    from comreg_core.registration.search.priors import PRIOR_KINDS

    if 0 < sweeps < MIN_SWEEPS:
        raise ComRegError(f"--calibration-sweeps {sweeps}: a calibration needs at least "
                          f"{MIN_SWEEPS} sweeps.", f"Give 0 (no calibration) or {MIN_SWEEPS} or "
                          f"more ({CALIBRATION_SWEEPS} is the default of 'comreg calibrate').")
    if prior not in PRIOR_KINDS:
        raise ComRegError(f"Unknown --calibration-prior '{prior}'.",
                          f"Give one of {', '.join(PRIOR_KINDS)}.")
    if prior != "none" and not sweeps:
        raise ComRegError("--calibration-prior needs --calibration-sweeps.",
                          f"Add e.g. --calibration-sweeps {CALIBRATION_SWEEPS}, or calibrate "
                          f"later with 'comreg calibrate --prior {prior}'.")


def _report_pretraining(result) -> None:
    """What pretrain prints: the run, its epochs, time and validation; a warning when the
    network has not learned the pose."""
    from comreg_core.training.checkpoint import network_warning

    validation = result.validation or {}
    summary = ", ".join(f"{key} {value:.3g}" for key, value in validation.items()
                        if key in ("val_RTE_mm_median", "val_RRE_deg_median", "val_success_rate"))
    typer.echo(f"wrote {result.run_dir}: {result.epochs} epochs, {result.samples_seen} samples in "
               f"{result.elapsed_s / 60:.1f} min on {result.device}"
               + (f" x {result.world_size} processes" if result.world_size > 1 else "")
               + f" (stopped: {result.stopped})"
               + (f"; validation {summary}" if summary else ""))
    warning = network_warning({"epoch": result.epochs, "validation": result.validation,
                               "initial_error": result.initial_error})
    if warning:
        typer.echo(f"warning: {warning}", err=True)
