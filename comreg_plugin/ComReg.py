"""ComReg: the 3D Slicer scripted module (Module, ParameterNode, Widget, Logic, Test).

Registers intraoperative ultrasound (US) bone points to the patient's CT bone with ComReg (a
pose search, optionally with a network pretrained on sweeps simulated from this CT). Installing
it into 3D Slicer: docs/guide.md ("3D Slicer module").

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
"ReferenceToCT" (SlicerIGT naming: tracking reference -> CT; any linear transform node the user
picks) whose to-parent matrix maps the US points (its child) onto the CT.
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

from comreg_plugin.live import TICK_MS, LiveRegistration  # noqa: E402
from comreg_plugin.logic import ComRegLogic  # noqa: E402
from comreg_plugin.parameter_node import ComRegParameterNode  # noqa: E402
from comreg_plugin.slicer_compat import (ScriptedLoadableModule,  # noqa: E402
                                         ScriptedLoadableModuleTest,
                                         ScriptedLoadableModuleWidget, VTKObservationMixin,
                                         slicer)
from comreg_plugin.verdict_record import describeFigures  # noqa: E402

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
        self.parent.dependencies = ["Sequences"]  # the sweep is a Sequence browser
        self.parent.contributors = ["ComReg contributors"]
        self.parent.helpText = """
Registers a tracked ultrasound (US) bone surface to the patient's CT bone with ComReg: pick the
tracked sweep (a Sequence browser: frames + ImageToReference transforms) and extract its bone
points, pick the CT segmentation (or bone model), and register, either with ComReg's pose search
on the CT alone (method "search", no pretraining) or with a network pretrained on sweeps
simulated from this CT (method "comreg", pretraining runs in the background). The result goes
into the chosen linear transform (default "ReferenceToCT") with the US points under it.
Optionally (section "Prior"), a rough initial pose (a transform node, US -> CT) with its
tolerances and landmarks picked on the CT and in the US data (two point lists, paired by label)
restrict the search to poses near them; a result at the edge of a tolerance is flagged.
Section "Live (OpenIGTLink)" registers the frames an OpenIGTLink connector brings in (image and
pose nodes, e.g. from PLUS Server) as they come, with the verdict and where to scan next.
Transforms are saved as ITK .tfm/.h5 (LPS), like Slicer does.
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
    """The module's panel: ``Resources/UI/ComReg.ui`` (Qt Designer), its widgets bound to the
    parameter node through their ``SlicerParameterName`` properties (``connectGui``). The only
    class that uses Qt (imported in :meth:`setup`).

    Headless, constructing it raises :class:`~comreg_core.errors.ComRegError` (no Qt).
    """

    def __init__(self, parent=None):
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._parameterNodeGuiTag = None
        self._timer = self._lastJob = None
        self._live = None
        self._liveTimer = None

    def setup(self):
        import ctk
        import qt

        ScriptedLoadableModuleWidget.setup(self)
        uiWidget = slicer.util.loadUI(self.resourcePath("UI/ComReg.ui"))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        self.logic = ComRegLogic()

        ui = self.ui
        for button, action in ((ui.extractPointsButton, self.onExtractPoints),
                               (ui.extractVolumeButton, self.onExtractFromVolume),
                               (ui.boneModelButton, self.onBoneModel),
                               (ui.loadSegmentationButton, self.onLoadSegmentation),
                               (ui.loadMeshButton, self.onLoadMesh),
                               (ui.loadSweepButton, self.onLoadSweep),
                               (ui.loadUSPointsButton, self.onLoadUSPoints),
                               (ui.startButton, self.onStartPretraining),
                               (ui.cancelButton, self.onCancelPretraining),
                               (ui.registerButton, self.onRegister),
                               (ui.saveTransformButton, self.onSaveTransform),
                               (ui.saveSceneButton, self.onSaveScene),
                               (ui.saveResultFolderButton, self.onSaveResultFolder),
                               (ui.writeReportButton, self.onWriteReport),
                               (ui.calibrateButton, self.onCalibrate),
                               (ui.cancelCalibrationButton, self.onCancelCalibration)):
            button.connect("clicked(bool)", action)
        readable = ctk.ctkPathLineEdit.Files | ctk.ctkPathLineEdit.Readable
        for edit in (ui.segmentationPath, ui.meshPath, ui.calibrationPath, ui.usPointsPath):
            edit.filters = readable
        ui.sweepPath.filters = readable | ctk.ctkPathLineEdit.Dirs
        ui.transformPath.filters = ui.scenePath.filters = ctk.ctkPathLineEdit.Files
        ui.resultFolderPath.filters = ctk.ctkPathLineEdit.Dirs
        ui.showCompetitorCheckBox.connect("toggled(bool)", self.logic.setCompetitorVisible)
        self._timer = qt.QTimer()
        self._timer.setInterval(1000)
        self._timer.connect("timeout()", self.onPollJobs)
        ui.liveButton.connect("toggled(bool)", self.onLiveToggled)
        self._liveTimer = qt.QTimer()
        self._liveTimer.setInterval(TICK_MS)
        self._liveTimer.connect("timeout()", self.onLiveTick)

        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        self.initializeParameterNode()

    # -- parameter node <-> GUI (connectGui) ----------------------------------------------------

    def cleanup(self):
        if self._timer is not None:
            self._timer.stop()
        self.onLiveToggled(False)
        self.removeObservers()

    def enter(self):
        self.initializeParameterNode()

    def exit(self):
        self.setParameterNode(None)

    def onSceneStartClose(self, caller, event):
        self.setParameterNode(None)

    def onSceneEndClose(self, caller, event):
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self):
        self.setParameterNode(self.logic.getParameterNode())

    def setParameterNode(self, parameterNode):
        if self._parameterNode is not None:
            if self._parameterNodeGuiTag is not None:
                self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
                self._parameterNodeGuiTag = None
            self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent,
                                self.updateButtons)
        self._parameterNode = parameterNode
        if parameterNode is not None:
            self._parameterNodeGuiTag = parameterNode.connectGui(self.ui)
            self.addObserver(parameterNode, vtk.vtkCommand.ModifiedEvent, self.updateButtons)
            self.updateButtons()

    def updateButtons(self, caller=None, event=None):
        p, ui = self._parameterNode, self.ui
        running = p.pretrainingState == "running"
        ui.extractPointsButton.enabled = p.sweep is not None
        ui.extractVolumeButton.enabled = p.usVolume is not None
        ui.boneModelButton.enabled = p.segmentation is not None
        ui.startButton.enabled = p.ctModel is not None and not running
        ui.cancelButton.enabled = running
        ui.registerButton.enabled = p.usPoints is not None and not running and (
            p.method == "comreg" or p.ctModel is not None)
        calibrating = p.calibrationState == "running"
        ui.calibrateButton.enabled = p.ctModel is not None and not calibrating
        ui.cancelCalibrationButton.enabled = calibrating
        judged = p.outputTransform is not None and bool(
            p.outputTransform.GetAttribute("ComReg.result_folder"))
        ui.saveResultFolderButton.enabled = ui.writeReportButton.enabled = judged

    # -- actions ------------------------------------------------------------------------------

    def _run(self, message, action):
        with slicer.util.tryWithErrorDisplay(message, waitCursor=True):
            action()

    def onExtractPoints(self):
        self._run("Could not extract the US bone points.", self.logic.usPointsFromSequence)

    def onExtractFromVolume(self):
        p = self._parameterNode
        self._run("Could not extract the US bone points from the volume.",
                  lambda: self.logic.usPointsFromVolume(p.usVolume, p.beamDirection))

    def onBoneModel(self):
        self._run("Could not make the bone model.", self.logic.boneModelsFromSegmentation)

    def onLoadSegmentation(self):
        self._run("Could not load the CT segmentation.",
                  lambda: self.logic.loadSegmentation(self.ui.segmentationPath.currentPath))

    def onLoadMesh(self):
        self._run("Could not load the bone mesh.",
                  lambda: self.logic.loadBoneMesh(self.ui.meshPath.currentPath))

    def onLoadSweep(self):
        calibration = self.ui.calibrationPath.currentPath or None
        self._run("Could not load the US sweep.", lambda: self.logic.addSweepSequence(
            self.ui.sweepPath.currentPath, calibration=calibration))

    def onLoadUSPoints(self):
        self._run("Could not load the US points.",
                  lambda: self.logic.loadUSPoints(self.ui.usPointsPath.currentPath))

    def onStartPretraining(self):
        def start():
            self._lastJob = self.logic.startPretraining()
            self._timer.start()
        self._run("Could not start the pretraining.", start)

    def onCancelPretraining(self):
        self._run("Could not cancel the pretraining.", self.logic.cancelPretraining)
        self.onPollJobs()

    def onPollJobs(self):
        """The pretraining's and the verdict calibration's progress (the timer, every s)."""
        lines = []
        for job, poll in ((self.logic.pretrainingJob, self.logic.pollPretraining),
                          (self.logic.calibrationJob, self.logic.pollCalibration)):
            if job is not None and (job.running or job is self._lastJob):
                status = poll()
                lines.append(status.describe())
                self._lastJob = job if status.state == "running" else None
        if lines:
            self.ui.resultLabel.text = "\n".join(lines)
        if not any(j is not None and j.running for j in (self.logic.pretrainingJob,
                                                        self.logic.calibrationJob)):
            self._timer.stop()

    def onCalibrate(self):
        def start():
            self._lastJob = self.logic.startCalibration()
            self._timer.start()
        self._run("Could not start the verdict calibration.", start)

    def onCancelCalibration(self):
        self._run("Could not cancel the calibration.", self.logic.cancelCalibration)
        self.onPollJobs()

    def onRegister(self):
        def register():
            p = self._parameterNode
            more = [n for n in self.ui.moreSweepsSelector.checkedNodes() if n is not p.usPoints]
            summary = self.logic.register([p.usPoints, *more] if more else None)
            lines = summary.describe(p.ambiguous, p.confidence).split("\n")
            self.ui.resultLabel.text = lines[0]
            self.ui.verdictLabel.text = "\n".join(lines[1:])
        self._run("Registration failed.", register)

    def onLiveToggled(self, on):
        """Start or stop the live mode (:mod:`comreg_plugin.live`) on the named nodes."""
        if self._live is not None:
            self._liveTimer.stop()
            self._live.stop()
            self._live = None
        if on:
            def start():
                self._live = LiveRegistration.fromNodeNames(
                    self.logic, self.ui.liveImageLineEdit.text, self.ui.livePoseLineEdit.text)
                self.ui.liveStatusLabel.text = self._live.status
                self._liveTimer.start()
            self._run("Could not start the live registration.", start)
            self.ui.liveButton.checked = self._live is not None

    def onLiveTick(self):
        if self._live is None:
            return
        ticked = []
        self._run("Live registration stopped.", lambda: ticked.append(self._live.tick()))
        if not ticked:  # the error was shown once; stop rather than repeat it every tick
            self.ui.liveButton.checked = False
            return
        self.ui.liveStatusLabel.text = self._live.status
        if ticked[0] is not None:  # the update's verdict, reasons, p_correct, advice
            self.ui.verdictLabel.text = "\n".join(describeFigures(self._live.figures))

    def onSaveTransform(self):
        self._run("Could not save the transform.", lambda: self.logic.saveTransform(
            self._parameterNode.outputTransform, self.ui.transformPath.currentPath))

    def onSaveResultFolder(self):
        self._run("Could not save the result folder.", lambda: self.logic.saveResultFolder(
            self.ui.resultFolderPath.currentPath))

    def onWriteReport(self):
        import qt

        def write():  # then opened in the browser
            page = self.logic.writeReport(self.ui.resultFolderPath.currentPath or None)
            qt.QDesktopServices.openUrl(qt.QUrl.fromLocalFile(str(page)))
        self._run("Could not write the report.", write)

    def onSaveScene(self):
        self._run("Could not save the scene.",
                  lambda: self.logic.saveScene(self.ui.scenePath.currentPath))


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
    and degrees, the saved transform files and a scene save/reload, then the panel's result parts
    on the bundled sample. Runs inside 3D Slicer (Reload & Test) and headless under pytest
    (``tests/plugin``). It registers by ComReg's pose search (``method="search"``), so it needs
    no pretrained network."""

    def setUp(self):
        import tempfile

        self.logic = ComRegLogic()
        self.logic.scene.Clear(0)
        self._tmp = tempfile.TemporaryDirectory(prefix="ComRegTest-")
        self.workDir = self._tmp.name

    def tearDown(self):
        if getattr(self, "_tmp", None) is not None:
            self._tmp.cleanup()
            self._tmp = None

    def runTest(self):
        """Run as few or as many tests as needed here."""
        for test in (self.test_ComRegEndToEnd, self.test_ComRegPanel, self.test_ComRegBadInputs):
            self.setUp()
            try:
                test()
            finally:
                self.tearDown()

    def test_ComRegEndToEnd(self):
        """Segmentation, sweep and points in; registration within 2 mm / 2 deg of the truth;
        transform files; scene save and reload (:func:`comreg_plugin.testing.endToEnd`)."""
        from comreg_plugin import testing

        self.endToEnd = testing.endToEnd(self, self.logic, self.workDir, ComRegLogic)

    def test_ComRegPanel(self):
        """The verdict and its figures, several sweeps, the result folder, the report, the
        verdict calibration and the live mode's second process on the bundled sample
        (:func:`comreg_plugin.panel_testing.checkPanel`)."""
        from comreg_plugin import panel_testing

        panel_testing.checkPanel(self, self.logic, self.workDir)

    def test_ComRegBadInputs(self):
        from comreg_plugin import testing

        testing.checkBadInputs(self, self.logic, self.workDir)
