"""What the ``comreg`` commands share: the device choice and the progress bar."""

from __future__ import annotations

import contextlib
import sys
from enum import Enum

import typer

from comreg_core import choices

Device = Enum("Device", {name: name for name in choices.DEVICES}, type=str)


@contextlib.contextmanager
def progress_bar(total: int, label: str):
    """A progress bar on stderr; yields ``advance(done)`` taking the number of items done. The
    bar appears at the first progress, so an error found before the work stays one line."""
    with contextlib.ExitStack() as stack:
        state = {"done": 0, "bar": None}

        def advance(done: int) -> None:
            if state["bar"] is None:
                state["bar"] = stack.enter_context(
                    typer.progressbar(length=total, label=label, file=sys.stderr))
            state["bar"].update(done - state["done"])
            state["done"] = done

        yield advance
