"""``comreg calibrate``: the per-patient calibration of ``p_correct`` (registered on ``app`` in
:mod:`comreg_core.cli`; its own module to keep the CLI file short)."""

from __future__ import annotations

from pathlib import Path

import typer


def calibrate(
    ct_mesh: Path = typer.Argument(..., help="The CT bone mesh (mm)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (calibration.json)."),
    sweeps: int = typer.Option(60, "--sweeps", min=4, help="Simulated sweeps to register."),
    lengths: str = typer.Option("30,80", "--lengths", help="Shortest and longest sweep, mm: "
                                "the lengths you expect to scan."),
    seed: int = typer.Option(0, "--seed", min=0),
) -> None:
    """Calibrate the verdict for this CT: register simulated one-face sweeps of it by the pose
    search, see which come out within 4 mm / 5 deg of the truth, and fit how the margin over
    the best clinically different pose and the sweep's length map to that. 'comreg register
    --verdict-calibration DIR/calibration.json' then reports p_correct, the estimated
    probability that its pose is correct, and says OK only at 0.95 or more. About 3 s a sweep
    on 2 CPU cores; no network needed.
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
                                               progress=progress)
    typer.echo(f"Wrote {path}: {calibration.sweeps} simulated sweeps, "
               f"{100 * calibration.correct_share:.0f} % registered within 4 mm / 5 deg.")
    for row in calibration.reliability:
        typer.echo(f"  p_correct {row['p_low']:.2f}-{row['p_high']:.2f}: {row['count']} sweeps, "
                   f"predicted {row['predicted']:.2f}, observed {row['observed']:.2f}")
