"""``python -m comreg_core.cli``: the ``comreg`` command (torchrun and the Slicer plugin's
background pretraining start it this way)."""

from comreg_core.cli import main

main()
