"""3D Slicer scripted module "ComReg" (Module, ParameterNode, Widget, Logic, Test).

- ``ComReg.py``: the file 3D Slicer loads (module metadata, Widget, self test ``ComRegTest``).
- ``logic.py``: ``ComRegParameterNode`` and ``ComRegLogic`` (no GUI, batch-capable); use it
  headless with ``from comreg_plugin.logic import ComRegLogic``.
- ``slicer_compat.py``: Slicer's scripted-module base classes inside the application, stand-ins
  on slicer-core's MRML outside it (never Qt).
- ``testing.py``: the self test's small data with a known transform and its checks.

Like the CLI it only calls ``comreg_core`` functions.
"""
