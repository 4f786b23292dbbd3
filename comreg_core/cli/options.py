"""What the ``comreg`` commands share: the help panels their options are grouped in, the option
types (device, network preset), the options several commands take (the device, the prior's), the
progress bar, and the pointer that answers the older ``RUN_DIR US_POINTS`` form."""

from __future__ import annotations

import contextlib
import sys
from enum import Enum
from pathlib import Path

import typer

from comreg_core import choices
from comreg_core.errors import ComRegError

# --- the panels of 'comreg --help' (commands) and of 'comreg COMMAND --help' (options) ----------
#: What a command reads (files, folders, settings).
INPUTS = "Inputs"
#: The pretrained network: the run folder, where it runs, its size.
NETWORK = "Network"
#: The pose search's settings and seed.
SEARCH = "Search"
#: The operating room's prior: an initial pose, landmarks, their tolerances.
PRIOR = "Prior"
#: What the verdict is judged with.
VERDICT = "Verdict"
#: Where and what a command writes.
OUTPUT = "Output"
#: OpenIGTLink: the server, its devices, the connection.
STREAM = "Stream"
#: Simulated sweeps: how many, how long, their seed.
SWEEPS = "Sweeps"
#: Random initial poses of an evaluation.
TRIALS = "Trials"

# --- option types --------------------------------------------------------------------------------
Device = Enum("Device", {name: name for name in choices.DEVICES}, type=str)
Preset = Enum("Preset", {name: name for name in choices.PRESETS}, type=str)

# --- options several commands take ---------------------------------------------------------------
#: ``--device`` of the commands that run a pretrained network.
DEVICE_OPTION = typer.Option(Device.auto, help="Where to run the network.",
                             rich_help_panel=NETWORK)

#: The prior's options (:func:`comreg_core.register.inputs.load_prior` reads them).
INIT_OPTION = typer.Option(
    None, "--init", metavar="TRANSFORM", rich_help_panel=PRIOR, help="A rough initial pose "
    "T_ct_us: an ITK transform file (.tfm, .h5, .txt) as 3D Slicer saves it (or a "
    "registration's transform.tfm). The search then tries only poses near it (--init-tolerance) "
    "and the verdict is CHECK when the result sits at the edge of that tolerance.")
INIT_TOLERANCE_OPTION = typer.Option(
    None, "--init-tolerance", metavar="DEG,MM", rich_help_panel=PRIOR, help="How far the pose "
    "may be from --init: its rotation by at most DEG degrees, and it places the US points' "
    "centroid at most MM from where --init places it. Default 30,30.")
LANDMARKS_OPTION = typer.Option(
    None, "--landmarks", metavar="CT_POINTS US_POINTS", rich_help_panel=PRIOR, help="Landmarks "
    "picked on the CT and in the US data (for live: in the tracker's reference frame, e.g. "
    "touched with a tracked pointer): two 3D Slicer markups files (.mrk.json or .fcsv, LPS or "
    "RAS as stored), paired by label. Only poses that put every US landmark within its "
    "tolerance of its CT landmark are kept; the search starts from poses that match them.")
LANDMARK_TOLERANCE_OPTION = typer.Option(
    None, "--landmark-tolerance", metavar="MM", min=0.001, rich_help_panel=PRIOR, help="Each "
    "landmark's tolerance (mm; default 10); a point's own 'tol=5' in its markups description "
    "overrides it.")


# --- helpers -------------------------------------------------------------------------------------
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


def refuse_the_older_form(command: str, first: str | Path) -> None:
    """Refuse ``comreg COMMAND RUN_DIR US_POINTS``, the form before ``--model``: a run folder
    (or its checkpoint, ``.pt``) given as the first positional argument is answered by a
    :class:`ComRegError` naming the form to use instead, before any work."""
    from comreg_core.io._files import is_run_folder

    path = Path(first)
    if is_run_folder(path) or path.suffix.lower() == ".pt":
        raise ComRegError(f"'comreg {command} RUN_DIR US_POINTS' is no longer accepted:",
                          f"use 'comreg {command} US_POINTS --model RUN_DIR' (see 'comreg "
                          f"{command} --help').")
