"""``comreg evaluate`` (registered on ``app`` in :mod:`comreg_core.cli`; its own module to keep
the CLI file short)."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Any, Optional

import typer

from comreg_core import choices, runs
from comreg_core.cli_shared import Device, progress_bar


Method = Enum("Method", {name: name for name in choices.METHODS + ("all",)}, type=str)


class Perturbation(str, Enum):
    paper = "paper"
    full = "full"


def evaluate(
    inputs: list[str] = typer.Argument(..., help="US bone points file, or the word 'simulated' "
                                       "for fresh simulated sweeps (seeds disjoint from "
                                       "training). (The older form RUN_DIR US_POINTS is still "
                                       "accepted.)", metavar="US_POINTS|simulated"),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (metrics.json)."),
    ct_mesh: Optional[Path] = typer.Option(None, "--ct", help="The CT bone mesh (mm); default: "
                                           "the run's own."),
    model: Optional[Path] = typer.Option(None, "--model", help="Run folder written by 'comreg "
                                         "pretrain' (needed by 'comreg' and 'comreg-plain')."),
    trials: int = typer.Option(100, "--trials", min=1, help="Random initial poses."),
    seed: int = typer.Option(0, "--seed", min=0),
    perturbation: Perturbation = typer.Option(Perturbation.paper, help="Initial poses: 'paper' "
                                              "(one axis, +-90 deg, +-100 mm) or 'full' (any "
                                              "rotation up to 180 deg, up to 500 mm; a run "
                                              "trained with data.pose: full covers it)."),
    gt: Optional[Path] = typer.Option(None, "--gt", help="Ground-truth T_ct_us (.tfm/.h5); "
                                      "identity if omitted."),
    method: Optional[list[Method]] = typer.Option(
        None, "--method", help="What to evaluate; repeat to compare several in one run: "
        "'search' (the pose search alone, no network), 'comreg' (the network, then the search), "
        "'comreg-plain' (the paper's pipeline: the network alone), 'ransac', 'icp-gt', or 'all' "
        "(every method). Default: 'comreg' with --model, else 'search'."),
    device: Device = typer.Option(Device.auto, help="Where to run the network."),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML with sections "
                                          "'hypotheses:' (the pose search), 'baselines:' "
                                          "('ransac:', 'icp_gt:') and 'simulation:' (the sweeps "
                                          "of 'simulated')."),
) -> None:
    """Measure registration accuracy from random initial poses: RTE, RRE, CD, HD95, success and
    flip rates, runtime (and, for ComReg, how often it flags its result ambiguous), for ComReg
    with and without its hypotheses stage and the baselines (Open3D RANSAC+FPFH+ICP; ICP from
    the ground truth), written to metrics.json."""
    from comreg_core.evaluation.evaluate import evaluate as run_evaluation
    from comreg_core.evaluation.evaluate import summary_line, write_metrics
    from comreg_core.evaluation.methods import (load_evaluate_config, method_names,
                                                registration_methods)
    from comreg_core.registration.inputs import limit_us_points
    from comreg_core.errors import ComRegError
    from comreg_core.io import load_transform, read_mesh, read_points
    from comreg_core.io._files import check_output_folder
    from comreg_core.training import run_ct_mesh

    run_dir, us_points = _run_and_points(inputs, model)
    if run_dir is None and ct_mesh is None:
        raise ComRegError("No CT to register to.", "Give --ct CT_MESH (and --model RUN_DIR for "
                          "the network's methods).")
    simulated = us_points == "simulated"
    check_output_folder(out, inputs=[run_dir, gt, config, ct_mesh]
                        + ([] if simulated else [us_points]))
    settings = load_evaluate_config(config)
    cloud = None if simulated else read_points(us_points)  # the cheap inputs first
    ct = run_ct_mesh(run_dir) if ct_mesh is None else read_mesh(ct_mesh)
    T_gt = load_transform(gt, space=ct.space) if gt is not None else None
    clouds = "simulated" if simulated else limit_us_points(cloud.in_space(ct.space).points, seed)
    chosen = [m.value for m in method] if method else ["comreg" if run_dir else "search"]
    names = method_names(chosen)
    methods = registration_methods(names, run_dir, ct, device=device.value, seed=seed,
                                   hypotheses=settings.hypotheses,
                                   baseline_config=settings.baselines)
    if not simulated:
        _check_us_cloud(methods, clouds)
    with progress_bar(trials * len(methods), "evaluating") as advance:
        result = run_evaluation(methods, clouds, ct, trials=trials, seed=seed,
                                perturbation=perturbation.value, T_gt=T_gt,
                                simulation_config=settings.simulation,
                                progress=lambda done, total, note="": advance(done))
    failed = [row["error"] for row in result["trials"] if row["error"] is not None]
    if result["trials"] and len(failed) == len(result["trials"]):
        raise ComRegError(f"Every trial failed, so there is nothing to measure; the first: "
                          f"{failed[0]}", "Fix the input above and run again.")
    path = write_metrics(result, Path(out) / runs.METRICS)
    typer.echo(f"wrote {path}")
    for name, summary in result["summary"].items():
        typer.echo(f"  {name}: {summary_line(summary)}")


def _run_and_points(inputs: list, model: Path | None) -> tuple[Path | None, Any]:
    """``(run folder or None, US points)`` from the positional arguments: ``US_POINTS`` (the run,
    if any, from ``--model``) or the older ``RUN_DIR US_POINTS``."""
    from comreg_core.errors import ComRegError

    if len(inputs) == 1:
        return model, inputs[0]
    if len(inputs) == 2 and model is None:
        return Path(inputs[0]), inputs[1]
    raise ComRegError(f"Expected the US points (and --model RUN_DIR), got {len(inputs)} "
                      "arguments" + (" and --model" if model is not None else "") + ".",
                      "Write: US_POINTS --ct CT_MESH [--model RUN_DIR] --out OUT_DIR.")


def _check_us_cloud(methods: dict, points) -> None:
    """The network's checks of the US cloud before any trial (a bad cloud fails them all)."""
    from comreg_core.inference import Registrar

    for method in methods.values():
        owner = getattr(getattr(method, "func", method), "__self__", method)  # partial/bound
        if isinstance(owner, Registrar):
            owner.check_points(points)
            return
