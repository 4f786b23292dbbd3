"""``comreg register``, ``comreg report`` and ``comreg demo``: a US bone surface registered to
the CT, its report, and the whole job on the bundled sample."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from comreg_core.cli.comreg import app
from comreg_core.cli.options import (DEVICE_OPTION, INIT_OPTION, INIT_TOLERANCE_OPTION, INPUTS,
                                     LANDMARK_TOLERANCE_OPTION, LANDMARKS_OPTION, NETWORK, OUTPUT,
                                     SEARCH, TRIALS, VERDICT, Device, refuse_the_older_form)

#: The panel of these commands in 'comreg --help'.
PANEL = "Registration"

# --- comreg register -----------------------------------------------------------------------------
REGISTER_US_POINTS = typer.Argument(
    ..., metavar="US_POINTS...", help="US bone surface points (.ply, .pcd, .xyz, .npy, ...), "
    "e.g. from 'comreg extract-us'; several files (sweeps in one tracker frame) are joined and "
    "registered as one.")
REGISTER_OUT = typer.Option(..., "--out", "-o", rich_help_panel=OUTPUT, help="Output folder.")
REGISTER_CT = typer.Option(None, "--ct", rich_help_panel=INPUTS, help="The CT bone mesh (mm). "
                           "Alone: register by the pose search, no network. With --model: "
                           "checked to be the run's CT.")
REGISTER_SWEEP = typer.Option(None, "--sweep", rich_help_panel=INPUTS, help="The tracked sweep "
                              "the points came from (one US points file only): the report shows "
                              "its frames with the registered CT contour.")
REGISTER_CALIBRATION = typer.Option(None, "--probe-calibration", "--calibration",
                                    rich_help_panel=INPUTS, help="The sweep's probe calibration "
                                    "(--calibration: its former name).")
REGISTER_MODEL = typer.Option(None, "--model", rich_help_panel=NETWORK, help="Run folder written "
                              "by 'comreg pretrain': the network's pose first, then the search "
                              "around it.")
REGISTER_SEARCH = typer.Option(
    True, "--search/--no-search", rich_help_panel=SEARCH, help="The pose search: many start "
    "poses (flipped end to end, turned about the shaft, slid along it; with --model the "
    "network's poses too) refined by ICP and scored against the CT; the best is kept and the "
    "result flagged ambiguous when another pose fits about as well. --no-search (with --model "
    "only) is the paper's plain pipeline: the network alone.")
#: ``--hypotheses/--no-hypotheses``: the former name of ``--search/--no-search``, still accepted.
REGISTER_HYPOTHESES = typer.Option(None, "--hypotheses/--no-hypotheses", hidden=True,
                                   help="Former name of --search/--no-search.")
REGISTER_CONFIG = typer.Option(None, "--config", rich_help_panel=SEARCH, help="YAML with a "
                               "'search:' section (the pose search's settings), e.g. the "
                               "config.yaml of an earlier registration.")
REGISTER_SEED = typer.Option(0, "--seed", min=0, rich_help_panel=SEARCH,
                              help="Random seed; the same seed gives the same result.")
REGISTER_VERDICT_CALIBRATION = typer.Option(
    None, "--verdict-calibration", rich_help_panel=VERDICT, help="calibration.json from 'comreg "
    "calibrate' (default: the run folder's own, if pretrain wrote one): result.json then gets "
    "p_correct and the verdict is OK only when p_correct >= 0.95.")


@app.command("register", rich_help_panel=PANEL)
def register(
    inputs: list[Path] = REGISTER_US_POINTS,
    ct_mesh: Optional[Path] = REGISTER_CT,
    sweep: Optional[Path] = REGISTER_SWEEP,
    calibration: Optional[Path] = REGISTER_CALIBRATION,
    model: Optional[Path] = REGISTER_MODEL,
    device: Device = DEVICE_OPTION,
    search: bool = REGISTER_SEARCH,
    hypotheses: Optional[bool] = REGISTER_HYPOTHESES,
    config: Optional[Path] = REGISTER_CONFIG,
    seed: int = REGISTER_SEED,
    init: Optional[Path] = INIT_OPTION,
    init_tolerance: Optional[str] = INIT_TOLERANCE_OPTION,
    landmarks: Optional[tuple[Path, Path]] = LANDMARKS_OPTION,
    landmark_tolerance: Optional[float] = LANDMARK_TOLERANCE_OPTION,
    verdict_calibration: Optional[Path] = REGISTER_VERDICT_CALIBRATION,
    out: Path = REGISTER_OUT,
) -> None:
    """Register a US bone surface to the CT: with --ct alone by the pose search (principal axes,
    flips, turns and slides of the US cloud, refined by ICP and scored against the CT); with
    --model the same search, then the pretrained network's poses (completion, coarse pose, ICP)
    as further starts, kept only when clearly better (--no-search: the network alone).

    Writes result.json (T_ct_us 4x4 in mm, the coarse transform, timings, residuals, the
    search's chosen pose, confidence and the ambiguous flag), transform.tfm (ITK, LPS, as 3D Slicer
    reads it), registered_us.ply and completion_ct.ply in the CT frame. A cloud of more than
    100,000 points is registered as a seeded uniform subset of 100,000 (said in a warning).
    --out must not be the run folder or inside it.
    """
    from comreg_core.register.folder import register_to_directory, summary_lines
    from comreg_core.register.inputs import load_prior
    from comreg_core.registration.search.config import load_register_config

    refuse_the_older_form("register", inputs[0])
    us_points = inputs[0] if len(inputs) == 1 else inputs
    prior = load_prior(init, init_tolerance, landmarks, landmark_tolerance)
    off = not search or hypotheses is False
    settings = load_register_config(config, {"search": {"enabled": False}} if off else None)
    result = register_to_directory(model, us_points, out, device=device.value, seed=seed,
                                   ct_mesh=ct_mesh, search=settings.search, sweep=sweep,
                                   sweep_calibration=calibration,
                                   calibration=verdict_calibration, prior=prior)
    for line in summary_lines(result, out, with_network=model is not None):
        typer.echo(line)


# --- comreg report -------------------------------------------------------------------------------
REPORT_FOLDER = typer.Argument(..., help="Folder written by 'comreg register'.")
REPORT_CT = typer.Option(None, "--ct", rich_help_panel=INPUTS, help="CT mesh (default: the one "
                         "the run was trained on).")
REPORT_TRANSFORM = typer.Option(
    None, "--transform", rich_help_panel=INPUTS, help="Judge and show this T_ct_us (ITK "
    ".tfm/.h5, e.g. edited or from another tool) on the folder's US points and CT instead of "
    "the registration's.")
REPORT_SWEEP = typer.Option(None, "--sweep", rich_help_panel=INPUTS, help="The points' tracked "
                            "sweep (default: register's): frames with the CT contour.")
REPORT_CALIBRATION = typer.Option(None, "--probe-calibration", "--calibration",
                                  rich_help_panel=INPUTS, help="The sweep's probe calibration "
                                  "(--calibration: its former name).")
REPORT_EMBED_IMAGES = typer.Option(False, "--embed-images", rich_help_panel=OUTPUT,
                                   help="One self-contained HTML.")


@app.command("report", rich_help_panel=PANEL)
def report(
    out_dir: Path = REPORT_FOLDER,
    ct_mesh: Optional[Path] = REPORT_CT,
    transform: Optional[Path] = REPORT_TRANSFORM,
    sweep: Optional[Path] = REPORT_SWEEP,
    calibration: Optional[Path] = REPORT_CALIBRATION,
    embed_images: bool = REPORT_EMBED_IMAGES,
) -> None:
    """Judge the registration (Verdict: OK or CHECK, from the US points, the transform and the
    CT alone), render off-screen screenshots (US points coloured by distance to the CT, before
    and after, completion) and write report.html with the verdict, metrics, inputs, versions."""
    from comreg_core.report import write_report_for_registration

    path = write_report_for_registration(out_dir, ct_mesh=ct_mesh, transform=transform,
                                         embed_images=embed_images, sweep=sweep,
                                         sweep_calibration=calibration)
    typer.echo(f"wrote {path}")


# --- comreg demo ---------------------------------------------------------------------------------
DEMO_OUT = typer.Option(Path("out/demo"), "--out", "-o", rich_help_panel=OUTPUT,
                        help="Output folder.")
DEMO_TRAIN_MINUTES = typer.Option(10.0, "--train-minutes", min=0.1, rich_help_panel=NETWORK,
                                  help="Pretraining budget if the bundled model does not fit.")
DEMO_TRIALS = typer.Option(10, "--trials", min=0, rich_help_panel=TRIALS, help="Extra random "
                           "starts evaluated into metrics.json.")
DEMO_SEED = typer.Option(0, "--seed", min=0, rich_help_panel=TRIALS, help="Seed of the "
                         "misalignment and trials.")


@app.command("demo", rich_help_panel=PANEL)
def demo(
    device: Device = DEVICE_OPTION,
    train_minutes: float = DEMO_TRAIN_MINUTES,
    trials: int = DEMO_TRIALS,
    seed: int = DEMO_SEED,
    out: Path = DEMO_OUT,
) -> None:
    """Run the whole job on the bundled sample (a cadaver fibula, CC BY 4.0): extract the CT and
    US bone surfaces, move the US points by a known misalignment, register them with the bundled
    pretrained model, evaluate, and write an HTML report with screenshots.

    The errors are measured against ICP from the recorded tracking (the paper's pseudo ground
    truth; the recording itself lies a little off the CT bone, and the summary says how far)."""
    from comreg_core.demo import run_demo, summary_lines

    result = run_demo(out, device=device.value, train_minutes=train_minutes, trials=trials,
                      seed=seed, step=lambda line: typer.echo(f"- {line}"))
    for line in summary_lines(result, trials):
        typer.echo(line)
