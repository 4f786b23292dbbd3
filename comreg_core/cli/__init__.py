"""The ``comreg`` command line. Thin: every command calls library functions and prints results.

One module per group of commands, each registering its commands on :data:`app` with
``@app.command(NAME, rich_help_panel=PANEL)``:

- :mod:`~comreg_core.cli.surfaces`: ``extract-ct``, ``extract-us``, ``info``;
- :mod:`~comreg_core.cli.training`: ``simulate``, ``pretrain``;
- :mod:`~comreg_core.cli.registration`: ``register``, ``report``, ``demo``;
- :mod:`~comreg_core.cli.evaluation`: ``evaluate``, ``calibrate``;
- :mod:`~comreg_core.cli.live`: ``live``, ``replay``;
- :mod:`~comreg_core.cli.batch`: ``batch``.

:mod:`~comreg_core.cli.comreg` holds :data:`app` and :func:`main` (the console script),
:mod:`~comreg_core.cli.options` what commands share (help panels, option types, the prior's
options, the progress bar), :mod:`~comreg_core.cli.errors` the one-line errors and exit
statuses: errors a user can fix (:class:`comreg_core.errors.ComRegError`, and what the operating
system refuses) are printed as one line and exit with status 2, in one place for all commands.

Heavy imports (VTK, torch) happen inside commands so ``comreg --help`` stays fast; every command
checks its output places before any work.
"""

from comreg_core.cli.comreg import app, main

# The commands register themselves on app when imported, in the order 'comreg --help' lists them.
from comreg_core.cli import surfaces  # noqa: F401
from comreg_core.cli import training  # noqa: F401
from comreg_core.cli import registration  # noqa: F401
from comreg_core.cli import evaluation  # noqa: F401
from comreg_core.cli import live  # noqa: F401
from comreg_core.cli import batch  # noqa: F401

__all__ = ["app", "main"]
