"""What the ``comreg`` commands share: the device choice, the prior's options (``register``,
``live``) and the progress bar."""

from __future__ import annotations

import contextlib
import sys
from enum import Enum

import typer

from comreg_core import choices

Device = Enum("Device", {name: name for name in choices.DEVICES}, type=str)

#: The prior's options (:func:`comreg_core.register_output.load_prior` reads them).
INIT_OPTION = typer.Option(
    None, "--init", metavar="TRANSFORM", help="A rough initial pose T_ct_us: an ITK "
    "transform file (.tfm, .h5, .txt) as 3D Slicer saves it (or a registration's "
    "transform.tfm). The search then tries only poses near it (--init-tolerance) and the "
    "verdict is CHECK when the result sits at the edge of that tolerance.")
INIT_TOLERANCE_OPTION = typer.Option(
    None, "--init-tolerance", metavar="DEG,MM", help="How far the pose may be from --init: "
    "its rotation by at most DEG degrees, and it places the US points' centroid at most MM "
    "from where --init places it. Default 30,30.")
LANDMARKS_OPTION = typer.Option(
    None, "--landmarks", metavar="CT_POINTS US_POINTS", help="Landmarks picked on the CT and "
    "in the US data (for live: in the tracker's reference frame, e.g. touched with a tracked "
    "pointer): two 3D Slicer markups files (.mrk.json or .fcsv, LPS or RAS as stored), paired "
    "by label. Only poses that put every US landmark within its tolerance of its CT landmark "
    "are kept; the search starts from poses that match them.")
LANDMARK_TOLERANCE_OPTION = typer.Option(
    None, "--landmark-tolerance", metavar="MM", min=0.001, help="Each landmark's tolerance "
    "(mm; default 10); a point's own 'tol=5' in its markups description overrides it.")


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
