"""3D Slicer scripted module "ComReg" (Module, ParameterNode, Widget, Logic, Test).

- ``ComReg.py``: the file 3D Slicer loads (module metadata, Widget, self test ``ComRegTest``;
  it imports ``ComRegParameterNode`` and ``ComRegLogic``, whose template places it marks).
- ``Resources/UI/ComReg.ui``: the panel (Qt Designer), bound to the parameter node through
  ``SlicerParameterName``; ``Resources/Icons/ComReg.png``: the module icon.
- ``parameter_node.py``: ``ComRegParameterNode``, the module's typed state.
- ``logic.py``: ``ComRegLogic`` (no GUI, batch-capable); use it headless with
  ``from comreg_plugin.logic import ComRegLogic``.
- ``registration.py``: the registration methods the Logic runs and ``RegistrationSummary``.
- ``judged_registration.py``: "search" and "comreg" registered as ``comreg register --out``
  does (``result_folder.py``: the inputs as files, the registration folder, a saved copy) and
  shown from its ``result.json`` (``verdict_record.py``: the figures, the panel's lines, the
  node attributes; ``result_views.py``: points coloured by distance with a legend, the
  competing pose, the patch to scan next).
- ``logic_jobs.py``: the Logic's background jobs, ``comreg pretrain`` and ``comreg calibrate``
  (``calibration_job.py``).
- ``live_process.py``: the live session's second process (``python -m
  comreg_plugin.live_process``), for ``live.py``.
- ``scene_snapshot.py``: the 3D scene rendered off-screen, headless.
- ``panel_testing.py``: the self test's checks of the panel's result parts.
- ``bone_models.py``: the CT bone models and US points as model nodes, the ``ComReg.*``
  attribute prefix.
- ``result_nodes.py``: a registration's result in the scene (output transform, completed
  bone, its record).
- ``live.py``: the live mode (an OpenIGTLink connector's stream registered as it grows, in
  ``live_process.py``'s process).
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
