"""The names users choose from, in one place: presets, registration methods, devices.

A light module (no imports), so the command line can offer these choices without importing
torch; the packages that implement them check their tables against these names
(``tests/test_architecture.py``).
"""

#: Pretraining presets (``comreg pretrain --preset``): the network size and schedule.
PRESETS = ("cpu", "paper")
#: The pose search alone, no network (needs only the CT mesh).
SEARCH_METHODS = ("search",)
#: The pretrained network, with and without the pose search.
COMREG_METHODS = ("comreg", "comreg-plain")
#: The paper's baselines: Open3D RANSAC + ICP, and ICP from the ground truth.
BASELINES = ("ransac", "icp-gt")
#: Every registration method ``comreg evaluate --method`` offers (plus ``all``).
METHODS = SEARCH_METHODS + COMREG_METHODS + BASELINES
#: Where the network runs.
DEVICES = ("auto", "cpu", "cuda")
