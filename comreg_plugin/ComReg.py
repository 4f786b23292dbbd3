"""ComReg: the 3D Slicer scripted module (Module, ParameterNode, Widget, Logic, Test).

Registers intraoperative ultrasound (US) bone points to the patient's CT bone with ComReg
(per-patient pretraining on simulated sweeps, then one forward pass).

Using it in 3D Slicer
---------------------
1. Install ComReg's library into Slicer's Python (once). Slicer ships its own VTK and numpy, so
   install ComReg without its pinned dependencies and add the pure-Python/torch ones, e.g. in
   Slicer's Python console::

       slicer.util.pip_install("--no-deps -e /path/to/comreg")
       slicer.util.pip_install("scipy pynrrd trimesh embreex pykdtree fpsample pyyaml typer torch")
       slicer.util.pip_install("open3d")   # only for the RANSAC baseline

2. Add the module folder ``/path/to/comreg/comreg_plugin`` in Edit > Application Settings >
   Modules > Additional module paths, and restart. The module appears under "Registration".

Slicer imports this file as the top-level module ``ComReg`` with only ``comreg_plugin/`` on
``sys.path``; the block below also puts the repository root on ``sys.path`` when ``comreg_core``
is not importable otherwise, so an uninstalled checkout works too (its dependencies must still be
installed). Background pretraining runs ``sys.executable -m comreg_core.cli pretrain`` (inside
Slicer ``sys.executable`` is its PythonSlicer).

Headless (pytest, batch scripts) the same file imports without Qt on slicer-core's MRML
(``pip install slicer-core``): :mod:`comreg_plugin.slicer_compat` supplies stand-ins for the
scripted-module base classes, and ``ComRegLogic(scene)`` does all the work. Only
``ComRegWidget`` touches Qt, and only inside ``setup()``.

Coordinates: Slicer's scene is RAS; ComReg's files and library are LPS (the CT's patient space);
the Logic converts at every boundary. The registration result is a ``vtkMRMLLinearTransformNode``
"ComReg US to CT" whose to-parent matrix maps the US points (its child) onto the CT.
"""

import importlib.util
import logging
import os
import sys

import vtk

if importlib.util.find_spec("comreg_core") is None:  # an uninstalled checkout
    _REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if os.path.isdir(os.path.join(_REPO_ROOT, "comreg_core")):
        sys.path.insert(0, _REPO_ROOT)

from comreg_core.choices import PRESETS  # noqa: E402
from comreg_plugin.logic import ComRegLogic  # noqa: E402
from comreg_plugin.parameter_node import ComRegParameterNode  # noqa: E402
from comreg_plugin.registration import METHODS  # noqa: E402
from comreg_plugin.slicer_compat import (ScriptedLoadableModule,  # noqa: E402
                                         ScriptedLoadableModuleTest,
                                         ScriptedLoadableModuleWidget, VTKObservationMixin,
                                         slicer)

log = logging.getLogger(__name__)

__all__ = ["ComReg", "ComRegParameterNode", "ComRegWidget", "ComRegLogic", "ComRegTest"]


#
# ComReg
#

class ComReg(ScriptedLoadableModule):
    """Module metadata (Slicer's ``ScriptedLoadableModule``)."""

    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = "ComReg"
        self.parent.categories = ["Registration"]
        self.parent.dependencies = []
        self.parent.contributors = ["ComReg contributors"]
        self.parent.helpText = """
Registers a tracked ultrasound (US) bone surface to the patient's CT bone with ComReg: extract the
CT bone from a segmentation, pretrain the network on US sweeps simulated from it (in the
background), extract the bone points from a tracked US sweep, and register them in one forward
pass. The result is the linear transform "ComReg US to CT" with the US points under it, and the
completed bone shape. Transforms are saved as ITK .tfm/.h5 (LPS), like Slicer does.
"""
        self.parent.acknowledgementText = """
Based on the method of the ComReg paper (shape completion + coarse pose + differentiable ICP).
The bundled sample CT is from the UltraBones100k dataset (Wu et al. 2025, CC BY 4.0).
"""


#
# ComRegParameterNode: defined in comreg_plugin/parameter_node.py (imported above) so that batch
# code can use the Logic without this file; decorated with Slicer's @parameterNodeWrapper inside
# the application.
#


#
# ComRegWidget
#

class ComRegWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
    """The module's panel: the only class that uses Qt (imported in :meth:`setup`).

    Headless, constructing it raises :class:`~comreg_core.errors.ComRegError` (no Qt).
    """

    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._timer = None

    def setup(self):
        import ctk
        import qt

        ScriptedLoadableModuleWidget.setup(self)
        self.logic = ComRegLogic()

        def section(title):
            button = ctk.ctkCollapsibleButton()
            button.text = title
            self.layout.addWidget(button)
            return qt.QFormLayout(button)

        def pathEdit(filters, tooltip):
            edit = ctk.ctkPathLineEdit()
            edit.filters = filters
            edit.toolTip = tooltip
            return edit

        def nodeSelector(classes, tooltip):
            selector = slicer.qMRMLNodeComboBox()
            selector.nodeTypes = classes
            selector.addEnabled = False
            selector.removeEnabled = False
            selector.noneEnabled = True
            selector.setMRMLScene(slicer.mrmlScene)
            selector.toolTip = tooltip
            return selector

        files = ctk.ctkPathLineEdit.Files | ctk.ctkPathLineEdit.Readable
        dirs = ctk.ctkPathLineEdit.Dirs

        # Inputs
        form = section("Inputs")
        self.segmentationPath = pathEdit(files, "CT label map (.nrrd, .mha) or .seg.nrrd")
        self.loadSegmentationButton = qt.QPushButton("Load CT segmentation")
        form.addRow("CT segmentation:", self.segmentationPath)
        form.addRow(self.loadSegmentationButton)
        self.meshPath = pathEdit(files, "CT bone mesh (.stl, .ply, .obj, .vtk, .vtp)")
        self.loadMeshButton = qt.QPushButton("Load bone mesh")
        form.addRow("or bone mesh:", self.meshPath)
        form.addRow(self.loadMeshButton)
        self.sweepPath = pathEdit(files | dirs, "Tracked US sweep: PLUS sequence or frame folder")
        self.calibrationPath = pathEdit(files, "Calibration (PLUS XML or calibration.json), "
                                        "if not beside the sweep")
        self.loadSweepButton = qt.QPushButton("Extract US bone points")
        form.addRow("US sweep:", self.sweepPath)
        form.addRow("Calibration:", self.calibrationPath)
        form.addRow(self.loadSweepButton)
        self.usPointsPath = pathEdit(files, "US bone points (.ply, .pcd, .xyz, .npy)")
        self.loadUSPointsButton = qt.QPushButton("Load US points")
        form.addRow("or US points:", self.usPointsPath)
        form.addRow(self.loadUSPointsButton)
        self.ctModelSelector = nodeSelector(["vtkMRMLModelNode"], "CT bone model")
        self.usPointsSelector = nodeSelector(["vtkMRMLModelNode"], "US bone points")
        form.addRow("CT bone model:", self.ctModelSelector)
        form.addRow("US points:", self.usPointsSelector)

        # Pretraining
        form = section("Pretraining (per patient)")
        self.runDirectory = pathEdit(dirs, "Run folder (checkpoint, logs)")
        self.presetCombo = qt.QComboBox()
        self.presetCombo.addItems(list(PRESETS))
        self.maxMinutesSpin = qt.QDoubleSpinBox()
        self.maxMinutesSpin.setRange(0.0, 100000.0)
        self.maxMinutesSpin.suffix = " min"
        self.startButton = qt.QPushButton("Start pretraining")
        self.cancelButton = qt.QPushButton("Cancel")
        self.progressBar = qt.QProgressBar()
        self.progressBar.setRange(0, 1000)
        self.pretrainingLabel = qt.QLabel("idle")
        form.addRow("Run folder:", self.runDirectory)
        form.addRow("Preset:", self.presetCombo)
        form.addRow("Time budget:", self.maxMinutesSpin)
        buttons = qt.QHBoxLayout()
        buttons.addWidget(self.startButton)
        buttons.addWidget(self.cancelButton)
        form.addRow(buttons)
        form.addRow(self.progressBar)
        form.addRow(self.pretrainingLabel)

        # Registration
        form = section("Registration")
        self.methodCombo = qt.QComboBox()
        self.methodCombo.addItems(list(METHODS))
        self.registerButton = qt.QPushButton("Register")
        self.resultLabel = qt.QLabel("")
        self.resultLabel.wordWrap = True
        form.addRow("Method:", self.methodCombo)
        form.addRow(self.registerButton)
        form.addRow(self.resultLabel)

        # Saving
        form = section("Save")
        self.transformPath = pathEdit(ctk.ctkPathLineEdit.Files, "Transform file (.tfm, .h5)")
        self.saveTransformButton = qt.QPushButton("Save transform")
        self.scenePath = pathEdit(ctk.ctkPathLineEdit.Files, "Scene file (.mrml)")
        self.saveSceneButton = qt.QPushButton("Save scene")
        form.addRow("Transform file:", self.transformPath)
        form.addRow(self.saveTransformButton)
        form.addRow("Scene file:", self.scenePath)
        form.addRow(self.saveSceneButton)
        self.layout.addStretch(1)

        self.loadSegmentationButton.connect("clicked(bool)", self.onLoadSegmentation)
        self.loadMeshButton.connect("clicked(bool)", self.onLoadMesh)
        self.loadSweepButton.connect("clicked(bool)", self.onLoadSweep)
        self.loadUSPointsButton.connect("clicked(bool)", self.onLoadUSPoints)
        self.startButton.connect("clicked(bool)", self.onStartPretraining)
        self.cancelButton.connect("clicked(bool)", self.onCancelPretraining)
        self.registerButton.connect("clicked(bool)", self.onRegister)
        self.saveTransformButton.connect("clicked(bool)", self.onSaveTransform)
        self.saveSceneButton.connect("clicked(bool)", self.onSaveScene)
        self.ctModelSelector.connect("currentNodeChanged(vtkMRMLNode*)",
                                     self.updateParameterNodeFromGUI)
        self.usPointsSelector.connect("currentNodeChanged(vtkMRMLNode*)",
                                      self.updateParameterNodeFromGUI)
        self.methodCombo.connect("currentIndexChanged(int)", self.updateParameterNodeFromGUI)
        self.presetCombo.connect("currentIndexChanged(int)", self.updateParameterNodeFromGUI)
        self.maxMinutesSpin.connect("valueChanged(double)", self.updateParameterNodeFromGUI)

        self._timer = qt.QTimer()
        self._timer.setInterval(1000)
        self._timer.connect("timeout()", self.onPollPretraining)

        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        self.initializeParameterNode()

    # -- parameter node <-> GUI ---------------------------------------------------------------

    def cleanup(self):
        if self._timer is not None:
            self._timer.stop()
        self.removeObservers()

    def enter(self):
        self.initializeParameterNode()

    def exit(self):
        if self._parameterNode is not None:
            self.removeObserver(self._parameterNode.parameterNode, vtk.vtkCommand.ModifiedEvent,
                                self.updateGUIFromParameterNode)

    def onSceneStartClose(self, caller, event):
        self.setParameterNode(None)

    def onSceneEndClose(self, caller, event):
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self):
        self.setParameterNode(self.logic.getParameterNode())

    def setParameterNode(self, parameterNode):
        if self._parameterNode is not None:
            self.removeObserver(self._parameterNode.parameterNode, vtk.vtkCommand.ModifiedEvent,
                                self.updateGUIFromParameterNode)
        self._parameterNode = parameterNode
        if parameterNode is not None:
            self.addObserver(parameterNode.parameterNode, vtk.vtkCommand.ModifiedEvent,
                             self.updateGUIFromParameterNode)
        self.updateGUIFromParameterNode()

    def updateGUIFromParameterNode(self, caller=None, event=None):
        p = self._parameterNode
        if p is None:
            return
        self._updating = True
        try:
            self.ctModelSelector.setCurrentNode(p.ctModel)
            self.usPointsSelector.setCurrentNode(p.usPoints)
            self.methodCombo.currentText = p.method
            self.presetCombo.currentText = p.preset
            self.maxMinutesSpin.value = p.maxMinutes
            if p.runDirectory and not self.runDirectory.currentPath:
                self.runDirectory.currentPath = p.runDirectory
            self.progressBar.value = int(1000 * p.pretrainingProgress)
            running = p.pretrainingState == "running"
            self.startButton.enabled = not running
            self.cancelButton.enabled = running
            self.registerButton.enabled = p.usPoints is not None and not running
        finally:
            self._updating = False

    def updateParameterNodeFromGUI(self, *args):
        p = self._parameterNode
        if p is None or getattr(self, "_updating", False):
            return
        p.ctModel = self.ctModelSelector.currentNode()
        p.usPoints = self.usPointsSelector.currentNode()
        p.method = self.methodCombo.currentText
        p.preset = self.presetCombo.currentText
        p.maxMinutes = float(self.maxMinutesSpin.value)

    # -- actions ------------------------------------------------------------------------------

    def _run(self, message, action):
        with slicer.util.tryWithErrorDisplay(message, waitCursor=True):
            action()

    def onLoadSegmentation(self):
        self._run("Could not load the CT segmentation.",
                  lambda: self.logic.loadSegmentation(self.segmentationPath.currentPath))

    def onLoadMesh(self):
        self._run("Could not load the bone mesh.",
                  lambda: self.logic.loadBoneMesh(self.meshPath.currentPath))

    def onLoadSweep(self):
        calibration = self.calibrationPath.currentPath or None
        self._run("Could not extract the US bone points.",
                  lambda: self.logic.loadTrackedSweep(self.sweepPath.currentPath,
                                                      calibration=calibration))

    def onLoadUSPoints(self):
        self._run("Could not load the US points.",
                  lambda: self.logic.loadUSPoints(self.usPointsPath.currentPath))

    def onStartPretraining(self):
        def start():
            self.logic.startPretraining(runDirectory=self.runDirectory.currentPath or None)
            self._timer.start()
        self._run("Could not start the pretraining.", start)

    def onCancelPretraining(self):
        self._run("Could not cancel the pretraining.", self.logic.cancelPretraining)
        self.onPollPretraining()

    def onPollPretraining(self):
        if self.logic.pretrainingJob is None:
            self._timer.stop()
            return
        status = self.logic.pollPretraining()
        self.pretrainingLabel.text = status.describe()
        if status.state != "running":
            self._timer.stop()

    def onRegister(self):
        def register():
            summary = self.logic.register()
            p = self._parameterNode
            self.resultLabel.text = summary.describe(p.ambiguous, p.confidence)
        self._run("Registration failed.", register)

    def onSaveTransform(self):
        self._run("Could not save the transform.", lambda: self.logic.saveTransform(
            self._parameterNode.outputTransform, self.transformPath.currentPath))

    def onSaveScene(self):
        self._run("Could not save the scene.",
                  lambda: self.logic.saveScene(self.scenePath.currentPath))


#
# ComRegLogic: defined in comreg_plugin/logic.py (imported above); batch code can use it
# without this file: ``from comreg_plugin.logic import ComRegLogic``.
#


#
# ComRegTest
#

class ComRegTest(ScriptedLoadableModuleTest):
    """The module's self test: builds its own small data from the bundled sample CT (a simulated
    US sweep moved by a known transform), runs the Logic end to end and asserts the errors in mm
    and degrees, the saved transform files and a scene save/reload. Runs inside 3D Slicer
    (Reload & Test) and headless under pytest (``tests/plugin``).

    The registration uses the RANSAC + ICP baseline (no pretrained network needed; requires
    Open3D in Slicer's Python).
    """

    def setUp(self):
        import tempfile

        self.logic = ComRegLogic()
        self.logic.scene.Clear(0)
        self._tmp = tempfile.TemporaryDirectory(prefix="ComRegTest-")
        self.workDir = self._tmp.name

    def tearDown(self):
        tmp = getattr(self, "_tmp", None)
        if tmp is not None:
            tmp.cleanup()
            self._tmp = None

    def runTest(self):
        """Run as few or as many tests as needed here."""
        for test in (self.test_ComRegEndToEnd, self.test_ComRegBadInputs):
            self.setUp()
            try:
                test()
            finally:
                self.tearDown()

    def test_ComRegEndToEnd(self):
        from pathlib import Path

        import numpy as np

        from comreg_core.io import load_transform
        from comreg_core.transforms import T_RAS_LPS
        from comreg_plugin import testing
        from comreg_plugin.scene_io import arrayFromModelPoints, transformToParentRAS

        self.delayDisplay("Building the test data (sample CT, simulated sweep, known transform)")
        case = testing.buildSyntheticCase(self.workDir)
        logic = self.logic

        self.delayDisplay("CT segmentation -> bone model")
        segNode, models = logic.loadSegmentation(case.segmentationPath)
        self.assertEqual(len(models), 1)
        vertices = arrayFromModelPoints(models[0])
        expected = case.ctMesh.in_space("RAS").vertices
        self.assertEqual(vertices.shape, expected.shape)
        self.assertLess(np.abs(vertices - expected).max(), 1e-6)

        self.delayDisplay("US points -> model")
        usNode = logic.loadUSPoints(case.usPointsPath)
        self.assertEqual(usNode.GetPolyData().GetNumberOfPoints(), len(case.usPoints))

        self.delayDisplay("Registration (RANSAC + ICP)")
        summary = logic.register(usNode, "ransac", ctModelNode=models[0])
        self.assertIs(usNode.GetParentTransformNode(), summary.transformNode)
        errors = testing.checkRegistrationAccuracy(summary.transformNode, case)
        self.delayDisplay(f"Registration error: {errors['translation_mm']:.3f} mm, "
                          f"{errors['rotation_deg']:.3f} deg (mean point "
                          f"{errors['mean_point_mm']:.3f} mm)")

        self.delayDisplay("Transform files (.tfm, .h5)")
        T_ras = transformToParentRAS(summary.transformNode)
        for ext in (".tfm", ".h5"):
            path = logic.saveTransform(summary.transformNode, Path(self.workDir) / f"T{ext}")
            readBack = testing.readTransformWithSlicer(path)
            self.assertLess(np.abs(readBack - T_ras).max(), 1e-6)
            self.assertLess(np.abs(load_transform(path) - T_RAS_LPS @ T_ras @ T_RAS_LPS).max(),
                            1e-6)

        self.delayDisplay("Scene save and reload")
        scenePath = logic.saveScene(Path(self.workDir) / "scene" / "ComRegTest.mrml")
        reloaded = ComRegLogic(slicer.vtkMRMLScene())
        reloaded.loadScene(scenePath)
        testing.checkScenesMatch(logic.scene, reloaded.scene)
        errors2 = testing.checkRegistrationAccuracy(
            reloaded.getParameterNode().outputTransform, case)
        self.assertAlmostEqual(errors2["translation_mm"], errors["translation_mm"], places=5)
        self.delayDisplay("Test passed")

    def test_ComRegBadInputs(self):
        from pathlib import Path

        from comreg_core.errors import ComRegError

        logic = self.logic
        missing = Path(self.workDir) / "missing.seg.nrrd"
        with self.assertRaisesRegex(ComRegError, "does not exist"):
            logic.loadSegmentation(missing)
        wrong = Path(self.workDir) / "notes.txt"
        wrong.write_text("not a segmentation")
        with self.assertRaisesRegex(ComRegError, "Use one of"):
            logic.loadSegmentation(wrong)
        with self.assertRaisesRegex(ComRegError, "nothing to cancel"):
            logic.cancelPretraining()
        with self.assertRaisesRegex(ComRegError, "no US points"):
            logic.register(method="ransac")
        self.delayDisplay("Bad inputs give clear errors")
