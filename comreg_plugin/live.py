"""Live registration in 3D Slicer, on an OpenIGTLink connector's incoming nodes.

3D Slicer's OpenIGTLinkIF connector puts what PLUS Server streams into the scene and updates it
in place at every message: a scalar volume node per IMAGE device (``Image``, a 2D frame) and a
linear transform node per TRANSFORM device (``ImageToReference``). :class:`LiveRegistration`
observes the image node: each new image (``ImageDataModifiedEvent``) becomes a frame with the
pose its transform node holds at that moment. The registration runs in a second process
(:class:`comreg_plugin.live_process.LiveProcess`: :class:`comreg_core.live.session.LiveSession`,
the same update ``comreg live`` runs: warm from the last pose, the full search when the evidence
changes, the verdict, the advice), so the GUI thread
never waits for it: :meth:`LiveRegistration.tick` (the module's qt timer, every :data:`TICK_MS`
ms; any loop headless) hands the frames that came to the process and writes the newest update
it answered into the output transform node (``ReferenceToCT``, to parent, RAS; the figures as
``ComReg.*`` attributes) and the status line (:attr:`LiveRegistration.status`). Only the GUI
thread touches the scene.

Coordinates, as for the module's Sequence browser sweeps
(:func:`comreg_plugin.scene_inputs.trackedSweepFromBrowser`): a frame's pose in LPS is
``T_RAS_LPS @ ImageToReference @ IJKToRAS`` and the output node gets
``T_RAS_LPS @ T_ct_us @ T_RAS_LPS``. The pose is the transform node's to-parent matrix (or, with
no pose node, the image node's parent transform's); its time stamp is the moment the image
came.

Method names are camelCase here, as in 3D Slicer modules.
"""

import logging
import time
from pathlib import Path
from typing import Optional

import numpy as np
import vtk
from vtk.util import numpy_support

from comreg_core.errors import ComRegError
from comreg_core.io.sweeps import frames_to_grey
from comreg_core.live.background import RegistrarRecipe
from comreg_core.live.updates import LiveUpdate
from comreg_core.live.stream import Frame, pixel_pose
from comreg_core.transforms import T_RAS_LPS
from comreg_plugin.bone_models import ATTRIBUTE_PREFIX
from comreg_plugin.live_process import LiveProcess, LiveSetup
from comreg_plugin.registration import TRANSFORM_NODE_NAME
from comreg_plugin.result_nodes import recordVerdict
from comreg_plugin.result_folder import newRegistrationFolder
from comreg_plugin.scene_inputs import priorFromNodes
from comreg_plugin.scene_io import (arrayFromVtkMatrix, requireNode, surfaceMeshFromModel,
                                    uniqueName, vtkMatrixFromArray)
from comreg_plugin.slicer_compat import require_slicer

slicer = require_slicer()

log = logging.getLogger(__name__)

#: How often the module's timer ticks (ms): applies a finished update, starts the next.
TICK_MS = 50


class LiveRegistration:
    """Live registration of the frames arriving in ``imageNode`` (module docstring).

    Args:
        logic: the module's :class:`~comreg_plugin.logic.ComRegLogic` (its scene, where the
            session's CT file goes).
        imageNode: the incoming 2D B-mode frame (``vtkMRMLScalarVolumeNode``).
        poseNode: its pose (``vtkMRMLLinearTransformNode``, e.g. ``ImageToReference``);
            default: the image node's parent transform.
        method: ``"search"`` (the pose search on ``ctModelNode``) or ``"comreg"`` (the run in
            ``runDirectory``, then the search, on ``ctModelNode``).
        outputTransformNode: where the registration goes (default: a new ``ReferenceToCT``).
        calibration: the verdict's ``calibration.json`` (a path) or None (the run's own).
        prior: a :class:`~comreg_core.registration.search.priors.Prior` (LPS; an initial pose, CT and
            US landmarks, the US ones in the stream's reference frame) bounding every update,
            or None (:func:`comreg_plugin.scene_inputs.priorFromNodes` makes one from nodes).
        background: the full searches in a third process, as ``comreg live`` (default: in
            the session's process, between its updates: inside 3D Slicer ``sys.executable`` is
            PythonSlicer, through which ``multiprocessing``'s spawn has been reported to hang,
            Slicer/Slicer#7445; either way none runs in Slicer's own process).
        python: the Python of the session's process (default ``sys.executable``).
    """

    def __init__(self, logic, imageNode, poseNode=None, *, method: str = "search",
                 ctModelNode=None, runDirectory=None, outputTransformNode=None,
                 calibration=None, prior=None, device: str = "auto", seed: int = 0,
                 maxFramesPerUpdate: int = 16, background: bool = False, python=None):
        requireNode(imageNode, "vtkMRMLScalarVolumeNode", "incoming image",
                    "Pick the image node the OpenIGTLink connector updates (e.g. 'Image').")
        poseNode = poseNode if poseNode is not None else imageNode.GetParentTransformNode()
        requireNode(poseNode, "vtkMRMLLinearTransformNode", "image pose",
                    "Pick the transform node the connector updates (e.g. 'ImageToReference'), "
                    "or put the image under it.")
        if method not in ("search", "comreg"):
            raise ComRegError(f"Live registration cannot use the '{method}' method.",
                              "Use 'search' or 'comreg'.")
        if ctModelNode is None:
            raise ComRegError(f"Live registration by the '{method}' method needs the CT bone "
                              "model.", "Load a CT segmentation or bone mesh first.")
        if method == "comreg" and not runDirectory:
            raise ComRegError("No pretrained run folder to register with.",
                              "Pretrain on this CT first, or choose the run folder.")
        requireNode(ctModelNode, "vtkMRMLModelNode", "CT bone model")
        if outputTransformNode is None:
            outputTransformNode = logic.scene.AddNewNodeByClass(
                "vtkMRMLLinearTransformNode", uniqueName(logic.scene, TRANSFORM_NODE_NAME))
        requireNode(outputTransformNode, "vtkMRMLLinearTransformNode", "output transform")
        self.logic, self.imageNode, self.poseNode = logic, imageNode, poseNode
        self.outputTransformNode = outputTransformNode
        self.method = method
        self.folder = newRegistrationFolder(Path(logic.resultBase()) / "live")
        ctPath = self.folder / "ct_bone.vtk"
        from comreg_core.io.meshes import write_mesh

        write_mesh(surfaceMeshFromModel(ctModelNode), ctPath)
        recipe = RegistrarRecipe(str(ctPath), None if method == "search" else
                                 str(runDirectory), device)
        self.setup = LiveSetup(recipe, None if not calibration else str(calibration), prior,
                               int(seed), int(maxFramesPerUpdate), bool(background))
        self.process = LiveProcess(self.setup, self.folder / "live_console.log", python)
        self.received = 0
        self.notes: list = []
        self.updates: list = []  # every update the process answered, in order
        self.figures: dict = {}  # the last update's (comreg_plugin.verdict_record)
        self.processId: Optional[int] = None  # once it is ready
        self.status = (f"live: preparing the CT side; then waiting for frames in "
                       f"'{imageNode.GetName()}' posed by '{poseNode.GetName()}'")
        self._frames: list = []
        self._sent = self._answered = 0  # batches sent, and answered by the process
        self._waiting = 0  # frames in the process's backlog
        self._stopped = False
        self._observer = imageNode.AddObserver(slicer.vtkMRMLVolumeNode.ImageDataModifiedEvent,
                                               self.onImageModified)

    @classmethod
    def fromNodeNames(cls, logic, imageName: str = "Image",
                      poseName: str = "ImageToReference") -> "LiveRegistration":
        """A live registration of the nodes named ``imageName`` and ``poseName`` in the logic's
        scene (the connector names them after the devices), with the parameter node's method,
        CT model, run folder, device, seed, output transform and prior (initial pose,
        landmarks: :func:`~comreg_plugin.scene_inputs.priorFromNodes`)."""
        p = logic.getParameterNode()
        nodes = []
        for name, what in ((imageName, "image"), (poseName, "pose")):
            node = logic.scene.GetFirstNodeByName(name) if name else None
            if name and node is None:
                raise ComRegError(f"There is no node '{name}' (the incoming {what}) in the "
                                  "scene.", "Connect the OpenIGTLink connector and start the "
                                  "stream first, or type the node's name.")
            nodes.append(node)
        live = cls(logic, nodes[0], nodes[1], method=p.method if p.method != "ransac"
                   else "search", ctModelNode=p.ctModel, runDirectory=p.runDirectory,
                   outputTransformNode=p.outputTransform, device=p.device, seed=p.seed,
                   prior=priorFromNodes(parameters=p),
                   calibration=p.verdictCalibration or None)
        p.outputTransform = live.outputTransformNode
        return live

    # -- frames ---------------------------------------------------------------------------------

    def onImageModified(self, caller=None, event=None) -> None:
        """A new image came: keep it with the pose of this moment (errors become notes)."""
        try:
            self._frames.append(self.captureFrame())
        except (ComRegError, ValueError) as exc:
            self.notes.append(f"frame {self.received - 1}: {exc}; skipped")
            log.warning("%s", self.notes[-1])

    def captureFrame(self) -> Frame:
        """The image node's current frame and the pose node's current pose as a
        :class:`~comreg_core.live.stream.Frame` (LPS)."""
        self.received += 1
        image = self.imageNode.GetImageData()
        if image is None or image.GetPointData().GetScalars() is None:
            raise ComRegError(f"'{self.imageNode.GetName()}' holds no image", "")
        W, H, depth = image.GetDimensions()
        if depth != 1:
            raise ComRegError(f"'{self.imageNode.GetName()}' is a 3D volume, not a 2D frame", "")
        pixels = numpy_support.vtk_to_numpy(image.GetPointData().GetScalars())
        components = image.GetNumberOfScalarComponents()
        pixels = frames_to_grey(pixels.reshape((1, H, W, components)))[0] if components > 1 \
            else pixels.reshape(H, W)
        ijk_to_ras = vtk.vtkMatrix4x4()
        self.imageNode.GetIJKToRASMatrix(ijk_to_ras)
        pose = vtk.vtkMatrix4x4()
        self.poseNode.GetMatrixTransformToParent(pose)
        T_ref_pixel = T_RAS_LPS @ arrayFromVtkMatrix(pose) @ arrayFromVtkMatrix(ijk_to_ras)
        spacing, T_ref_image = pixel_pose(T_ref_pixel)
        now = time.monotonic()
        return Frame(self.received - 1, np.array(pixels, copy=True), spacing, T_ref_image, now,
                     now)

    # -- updates --------------------------------------------------------------------------------

    @property
    def busy(self) -> bool:
        """Whether the process has frames it has not answered yet (or a backlog)."""
        return self._answered < self._sent or self._waiting > 0

    def tick(self, wait: bool = False, timeout_s: float = 300.0) -> Optional[LiveUpdate]:
        """On the GUI thread: apply the newest update the process answered (the output node,
        its figures and :attr:`status` follow it) and hand it the frames that came since.
        Returns the update applied now, or None. ``wait``: also wait until the process has
        answered every frame (headless scripts). An error of the process is raised here."""
        if self._stopped:
            return None
        applied = self._apply(self.process.messages())
        if self._frames:
            self._sent += 1
            self.process.send(self._sent, self._frames, self.received)
            self._frames = []
        deadline = time.monotonic() + timeout_s
        while wait and self.busy:
            if time.monotonic() > deadline:
                raise ComRegError(f"The live process answered nothing for {timeout_s:.0f} s.",
                                  f"See its console, '{self.process.logPath}'.")
            applied = self._apply(self.process.messages(timeout=0.5)) or applied
        return applied

    def _apply(self, messages: list) -> Optional[LiveUpdate]:
        """Take the process's answers; write the newest update into the scene."""
        newest = None
        for message in messages:
            kind = message[0]
            if kind == "ready":
                self.processId = message[1]
            elif kind in ("failed", "error"):
                self._answered, self._waiting = self._sent, 0
                raise ComRegError(f"Live registration stopped: {message[-1]}.",
                                  f"See the live console, '{self.process.logPath}'.")
            else:
                _, self._answered, update, self._waiting, notes, bone = message
                self.notes += notes
                if update is not None:
                    self.updates.append(update)
                    newest = update
                elif newest is None:
                    self.status = (f"live: waiting for bone ({bone[0]} of {bone[1]} frames "
                                   "show it)")
        if newest is not None:
            self._show(newest)
        return newest

    def _show(self, update: LiveUpdate) -> None:
        """The update on the output node (matrix, figures) and the status line."""
        node = self.outputTransformNode
        node.SetMatrixTransformToParent(vtkMatrixFromArray(
            T_RAS_LPS @ update.T_ct_us @ T_RAS_LPS))
        update.latency_s = time.monotonic() - update.newest_s
        node.SetAttribute(ATTRIBUTE_PREFIX + "method", f"live {self.method}")
        node.SetAttribute(ATTRIBUTE_PREFIX + "covered_mm", f"{update.covered_mm:.1f}")
        self.figures = {
            "verdict": update.verdict, "verdict_reasons": list(update.reasons),
            "p_correct": update.p_correct, "confidence": update.confidence,
            "advice": update.advice, "uncertainty": getattr(update, "uncertainty", None),
            "uncertainty_mm": (getattr(update, "uncertainty", None) or {}).get("bound_mm"),
            "scan_next": getattr(update, "scan_next", None)}
        recordVerdict(self.logic.getParameterNode(), node, self.figures)
        self.status = update.status_line()

    def stop(self) -> None:
        """Stop observing the image node and stop the process (after the update under way,
        whose answer is applied); the registration stays in the output node."""
        if self._observer is not None:
            self.imageNode.RemoveObserver(self._observer)
            self._observer = None
        try:
            self.tick(wait=True, timeout_s=60.0)
        except ComRegError as exc:  # stopping anyway; said in the notes
            self.notes.append(str(exc))
        self._stopped = True
        self.process.close()
