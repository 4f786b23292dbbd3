"""3D Slicer scripted module "ComReg" (Module, ParameterNode, Widget, Logic, Test).

- ``ComReg.py``: the file 3D Slicer loads (module metadata, Widget, self test ``ComRegTest``;
  it imports ``ComRegParameterNode`` and ``ComRegLogic``, whose template places it marks).
- ``Resources/UI/ComReg.ui``: the panel (Qt Designer), bound to the parameter node through
  ``SlicerParameterName``; ``Resources/Icons/ComReg.png``: the module icon.
- ``parameter_node.py``: ``ComRegParameterNode``, the module's typed state.
- ``logic.py``: ``ComRegLogic`` (no GUI, batch-capable); use it headless with
  ``from comreg_plugin.logic import ComRegLogic``.
- ``registration.py``: the registration methods the Logic runs and ``RegistrationSummary``.
- ``bone_models.py``: the CT bone models and US points as model nodes, the ``ComReg.*``
  attribute prefix.
- ``result_nodes.py``: a registration's result in the scene (output transform, completed
  bone, its record).
- ``live.py``: the live mode (an OpenIGTLink connector's stream registered as it grows).
- ``scene_inputs.py``: inputs from the scene: a Sequence browser sweep -> ``TrackedSweep`` (and
  back), points of a model or markups node, a segmentation node -> ``Segmentation``.
- ``pretraining_job.py``: ``comreg pretrain`` in a background process (``PretrainingJob``).
- ``scene_io.py``: numpy <-> VTK/MRML helpers, node builders, transform and scene files.
- ``slicer_compat.py``: Slicer's scripted-module base classes inside the application, stand-ins
  on slicer-core's MRML outside it (never Qt).
- ``testing.py``: the self test's small data with a known transform and its checks.

Imports only go down: ``ComReg`` -> ``logic`` -> ``parameter_node`` -> ``registration`` /
``scene_inputs`` -> ``pretraining_job`` / ``scene_io`` -> ``slicer_compat`` -> ``comreg_core``.
Like the CLI it only calls ``comreg_core`` functions.
"""
