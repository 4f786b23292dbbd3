"""The ``comreg`` command itself: :data:`app` (its help, ``--version``, ``--verbose``) and
:func:`main`, the console script. The commands are registered on :data:`app` by the modules of
:mod:`comreg_core.cli`, one module per group of commands."""

from __future__ import annotations

import typer

from comreg_core import __version__
from comreg_core.cli.errors import CommandApp, set_verbose

app = CommandApp(
    name="comreg",
    help="ComReg: patient-specific CT-ultrasound bone surface registration.\n\n"
    "Extract the CT bone surface, register a real tracked-ultrasound bone surface to it by a "
    "pose search (optionally with a network pretrained on sweeps simulated from this CT), and "
    "get a verdict on the result. Every command prints what it "
    "wrote; errors you can fix exit with status 2 and say what to do.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"comreg {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print the version and exit."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details."),
) -> None:
    set_verbose(verbose)


def main() -> None:
    """Entry point of the ``comreg`` console script."""
    app()
