"""``comreg evaluate`` and ``comreg calibrate``: registration accuracy measured from random
initial poses, and the per-patient calibration of ``p_correct`` on simulated sweeps."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Any, Optional

import typer

from comreg_core import choices, runs
from comreg_core.cli.comreg import app
from comreg_core.cli.options import (DEVICE_OPTION, INPUTS, NETWORK, OUTPUT, SWEEPS, TRIALS,
                                     Device, progress_bar, refuse_the_older_form)

#: The panel of these commands in 'comreg --help'.
PANEL = "Evaluation"

Method = Enum("Method", {name: name for name in choices.METHODS + ("all",)}, type=str)


class Perturbation(str, Enum):
    paper = "paper"
    full = "full"


# --- comreg evaluate -----------------------------------------------------------------------------
EVALUATE_US_POINTS = typer.Argument(
    ..., metavar="US_POINTS|simulated", help="US bone points file, or the word 'simulated' for "
    "fresh simulated sweeps (seeds disjoint from training).")
EVALUATE_OUT = typer.Option(..., "--out", "-o", rich_help_panel=OUTPUT,
                            help="Output folder (metrics.json).")
EVALUATE_CT = typer.Option(None, "--ct", rich_help_panel=INPUTS, help="The CT bone mesh (mm); "
                           "default: the run's own.")
EVALUATE_GT = typer.Option(None, "--gt", rich_help_panel=INPUTS, help="Ground-truth T_ct_us "
                           "(.tfm/.h5); identity if omitted.")
EVALUATE_CONFIG = typer.Option(None, "--config", rich_help_panel=INPUTS, help="YAML with "
                               "sections 'search:' (the pose search), 'baselines:' "
                               "('ransac:', 'icp_gt:') and 'simulation:' (the sweeps of "
                               "'simulated').")
EVALUATE_MODEL = typer.Option(None, "--model", rich_help_panel=NETWORK, help="Run folder "
                              "written by 'comreg pretrain' (needed by 'comreg' and "
                              "'comreg-plain').")
EVALUATE_METHOD = typer.Option(
    None, "--method", rich_help_panel=TRIALS, help="What to evaluate; repeat to compare several "
    "in one run: 'search' (the pose search alone, no network), 'comreg' (the network, then the "
    "search), 'comreg-plain' (the paper's pipeline: the network alone), 'ransac', 'icp-gt', or "
    "'all' (every method). Default: 'comreg' with --model, else 'search'.")
EVALUATE_TRIALS = typer.Option(100, "--trials", min=1, rich_help_panel=TRIALS,
                               help="Random initial poses.")
EVALUATE_PERTURBATION = typer.Option(
    Perturbation.paper, rich_help_panel=TRIALS, help="Initial poses: 'paper' (one axis, +-90 "
    "deg, +-100 mm) or 'full' (any rotation up to 180 deg, up to 500 mm; a run trained with "
    "data.pose: full covers it).")
EVALUATE_SEED = typer.Option(0, "--seed", min=0, rich_help_panel=TRIALS,
                              help="Random seed; the same seed gives the same trials.")


@app.command("evaluate", rich_help_panel=PANEL)
def evaluate(
    inputs: list[str] = EVALUATE_US_POINTS,
    ct_mesh: Optional[Path] = EVALUATE_CT,
    gt: Optional[Path] = EVALUATE_GT,
    config: Optional[Path] = EVALUATE_CONFIG,
    model: Optional[Path] = EVALUATE_MODEL,
    device: Device = DEVICE_OPTION,
    method: Optional[list[Method]] = EVALUATE_METHOD,
    trials: int = EVALUATE_TRIALS,
    perturbation: Perturbation = EVALUATE_PERTURBATION,
    seed: int = EVALUATE_SEED,
    out: Path = EVALUATE_OUT,
) -> None:
    """Measure registration accuracy from random initial poses: RTE, RRE, CD, HD95, success and
    flip rates, runtime (and, for ComReg, how often it flags its result ambiguous), for ComReg
    with and without its pose search and the baselines (Open3D RANSAC+FPFH+ICP; ICP from
    the ground truth), written to metrics.json."""
    from comreg_core.evaluation.evaluate import summary_line, write_metrics

    refuse_the_older_form("evaluate", inputs[0])
    us_points = _us_points(inputs, model)
    ct, clouds, T_gt, methods, simulation = _evaluation_inputs(
        us_points, out, ct_mesh=ct_mesh, gt=gt, config=config, model=model,
        device=device.value, method=method, seed=seed)
    result = _run_trials(methods, clouds, ct, trials=trials, seed=seed,
                         perturbation=perturbation.value, T_gt=T_gt, simulation=simulation)
    path = write_metrics(result, Path(out) / runs.METRICS)
    typer.echo(f"wrote {path}")
    for name, summary in result["summary"].items():
        typer.echo(f"  {name}: {summary_line(summary)}")


def _us_points(inputs: list[str], model: Path | None) -> str:
    """The one positional argument of evaluate: a US points file or 'simulated'."""
    from comreg_core.errors import ComRegError

    if len(inputs) == 1:
        return inputs[0]
    raise ComRegError(f"Expected the US points (and --model RUN_DIR), got {len(inputs)} "
                      "arguments" + (" and --model" if model is not None else "") + ".",
                      "Write: US_POINTS --ct CT_MESH [--model RUN_DIR] --out OUT_DIR.")


def _evaluation_inputs(us_points: str, out: Path, *, ct_mesh, gt, config, model, device: str,
                       method, seed: int) -> tuple[Any, Any, Any, dict, Any]:
    """Check the output folder and read the inputs, the cheap ones first: ``(CT mesh, US cloud
    or 'simulated', T_gt or None, the methods by name, the simulation settings)``."""
    from comreg_core.errors import ComRegError
    from comreg_core.evaluation.methods import (load_evaluate_config, method_names,
                                                registration_methods)
    from comreg_core.io import load_transform, read_mesh, read_points
    from comreg_core.io._files import check_output_folder
    from comreg_core.registration.geometry.inputs import limit_us_points
    from comreg_core.training import run_ct_mesh

    if model is None and ct_mesh is None:
        raise ComRegError("No CT to register to.", "Give --ct CT_MESH (and --model RUN_DIR for "
                          "the network's methods).")
    simulated = us_points == "simulated"
    check_output_folder(out, inputs=[model, gt, config, ct_mesh]
                        + ([] if simulated else [us_points]))
    settings = load_evaluate_config(config)
    cloud = None if simulated else read_points(us_points)  # the cheap inputs first
    ct = run_ct_mesh(model) if ct_mesh is None else read_mesh(ct_mesh)
    T_gt = load_transform(gt, space=ct.space) if gt is not None else None
    clouds = "simulated" if simulated else limit_us_points(cloud.in_space(ct.space).points, seed)
    chosen = [m.value for m in method] if method else ["comreg" if model else "search"]
    methods = registration_methods(method_names(chosen), model, ct, device=device, seed=seed,
                                   search=settings.search,
                                   baseline_config=settings.baselines)
    if not simulated:
        _check_us_cloud(methods, clouds)
    return ct, clouds, T_gt, methods, settings.simulation


def _run_trials(methods: dict, clouds, ct, *, trials: int, seed: int, perturbation: str, T_gt,
                simulation) -> dict:
    """Every method from the same random initial poses; refused when every trial failed."""
    from comreg_core.errors import ComRegError
    from comreg_core.evaluation.evaluate import evaluate as run_evaluation

    with progress_bar(trials * len(methods), "evaluating") as advance:
        result = run_evaluation(methods, clouds, ct, trials=trials, seed=seed,
                                perturbation=perturbation, T_gt=T_gt,
                                simulation_config=simulation,
                                progress=lambda done, total, note="": advance(done))
    failed = [row["error"] for row in result["trials"] if row["error"] is not None]
    if result["trials"] and len(failed) == len(result["trials"]):
        raise ComRegError(f"Every trial failed, so there is nothing to measure; the first: "
                          f"{failed[0]}", "Fix the input above and run again.")
    return result


def _check_us_cloud(methods: dict, points) -> None:
    """The network's checks of the US cloud before any trial (a bad cloud fails them all)."""
    from comreg_core.register.registrar import Registrar

    for method in methods.values():
        owner = getattr(getattr(method, "func", method), "__self__", method)  # partial/bound
        if isinstance(owner, Registrar):
            owner.check_points(points)
            return


# --- comreg calibrate ----------------------------------------------------------------------------
CALIBRATE_CT_MESH = typer.Argument(..., help="The CT bone mesh (mm).")
CALIBRATE_OUT = typer.Option(..., "--out", "-o", rich_help_panel=OUTPUT,
                             help="Output folder (calibration.json).")
# comreg_core.evaluation.calibrate.CALIBRATION_SWEEPS (not imported: it pulls in numba and scipy)
CALIBRATE_SWEEPS = typer.Option(60, "--sweeps", min=4, rich_help_panel=SWEEPS,
                                help="Simulated sweeps to register.")
CALIBRATE_LENGTHS = typer.Option("30,80", "--lengths", rich_help_panel=SWEEPS, help="Shortest "
                                 "and longest sweep, mm: the lengths you expect to scan.")
CALIBRATE_SEED = typer.Option(0, "--seed", min=0, rich_help_panel=SWEEPS,
                               help="Random seed of the simulated sweeps.")
# comreg_core.registration.search.priors.PRIOR_KINDS
CALIBRATE_PRIOR = typer.Option("none", "--prior", rich_help_panel=SWEEPS, help="What your "
                               "registrations will know: none, init (an initial pose, "
                               "'register --init') or landmark ('register --landmarks'); each "
                               "sweep is registered within such a simulated prior. Use the "
                               "calibration of the kind you register with: register and live "
                               "refuse one made with more than they know.")


@app.command("calibrate", rich_help_panel=PANEL)
def calibrate(
    ct_mesh: Path = CALIBRATE_CT_MESH,
    sweeps: int = CALIBRATE_SWEEPS,
    lengths: str = CALIBRATE_LENGTHS,
    seed: int = CALIBRATE_SEED,
    out: Path = CALIBRATE_OUT,
    prior: str = CALIBRATE_PRIOR,
) -> None:
    """Calibrate the verdict for this CT: register simulated one-face sweeps of it by the pose
    search, see which come out within 4 mm / 5 deg of the truth, and fit how the verdict's
    p_raw (from the pose's uncertainty) maps to that. 'comreg register
    --verdict-calibration DIR/calibration.json' then reports p_correct, the estimated
    probability that its pose is correct, and says OK only at 0.95 or more. About 1.5 s a sweep
    on an idle 2-core machine; no network needed.
    """
    from comreg_core.errors import ComRegError
    from comreg_core.evaluation.calibrate import calibrate_to_directory

    try:
        low, high = (float(x) for x in lengths.split(","))
    except ValueError:
        raise ComRegError(f"--lengths '{lengths}' is not two numbers.",
                          "Give the shortest and longest sweep in mm, e.g. --lengths 30,80."
                          ) from None

    def progress(done: int, total: int, message: str) -> None:
        typer.echo(message, err=True)

    path, calibration = calibrate_to_directory(ct_mesh, out, sweeps=sweeps,
                                               lengths_mm=(low, high), seed=seed,
                                               progress=progress, prior=prior)
    typer.echo(f"Wrote {path}: {calibration.sweeps} simulated sweeps, "
               f"{100 * calibration.correct_share:.0f} % registered within 4 mm / 5 deg.")
    for row in calibration.reliability:
        typer.echo(f"  p_correct {row['p_low']:.2f}-{row['p_high']:.2f}: {row['count']} sweeps, "
                   f"predicted {row['predicted']:.2f}, observed {row['observed']:.2f}")
