"""Live registration in 3D Slicer, on an OpenIGTLink connector's incoming nodes.

3D Slicer's OpenIGTLinkIF connector puts what PLUS Server streams into the scene and updates it
in place at every message: a scalar volume node per IMAGE device (``Image``, a 2D frame) and a
linear transform node per TRANSFORM device (``ImageToReference``). :class:`LiveRegistration`
observes the image node: each new image (``ImageDataModifiedEvent``) becomes a frame with the
pose its transform node holds at that moment. :meth:`LiveRegistration.tick` (the module's qt
timer, every :data:`TICK_MS` ms; any loop headless) starts one update of
:class:`comreg_core.live.session.LiveSession` in a worker thread, the same update ``comreg
live`` runs (warm from the last pose, the full search when the evidence changes, the verdict,
the advice), so the GUI stays responsive while it registers; a later tick, on the GUI thread,
writes its registration into the output transform node (``ReferenceToCT``, to parent, RAS) and
the status line (:attr:`LiveRegistration.status`), and starts the next. Only the GUI thread
touches the scene; frames that come meanwhile wait for the next update.

Coordinates, as for the module's Sequence browser sweeps
(:func:`comreg_plugin.scene_inputs.trackedSweepFromBrowser`): a frame's pose in LPS is
``T_RAS_LPS @ ImageToReference @ IJKToRAS`` and the output node gets
``T_RAS_LPS @ T_ct_us @ T_RAS_LPS``. The pose is the transform node's to-parent matrix (or, with
no pose node, the image node's parent transform's); its time stamp is the moment the image
came.

Method names are camelCase here, as in 3D Slicer modules.
"""

import logging
import threading
import time
from typing import Optional

import numpy as np
import vtk
from vtk.util import numpy_support

from comreg_core.errors import ComRegError
from comreg_core.io.sweeps import frames_to_grey
from comreg_core.live.session import LiveSession
from comreg_core.live.updates import LiveUpdate
from comreg_core.live.stream import Frame, pixel_pose
from comreg_core.transforms import T_RAS_LPS
from comreg_plugin.bone_models import ATTRIBUTE_PREFIX
from comreg_plugin.registration import TRANSFORM_NODE_NAME
from comreg_plugin.scene_inputs import priorFromNodes
from comreg_plugin.scene_io import (arrayFromVtkMatrix, requireNode, uniqueName,
                                    vtkMatrixFromArray)
from comreg_plugin.slicer_compat import require_slicer

slicer = require_slicer()

log = logging.getLogger(__name__)

#: How often the module's timer ticks (ms): applies a finished update, starts the next.
TICK_MS = 50


class LiveRegistration:
    """Live registration of the frames arriving in ``imageNode`` (module docstring).

    Args:
        logic: the module's :class:`~comreg_plugin.logic.ComRegLogic` (its scene, its prepared
            registration methods).
        imageNode: the incoming 2D B-mode frame (``vtkMRMLScalarVolumeNode``).
        poseNode: its pose (``vtkMRMLLinearTransformNode``, e.g. ``ImageToReference``);
            default: the image node's parent transform.
        method: ``"search"`` (the pose search on ``ctModelNode``) or ``"comreg"`` (the run in
            ``runDirectory``, then the search).
        outputTransformNode: where the registration goes (default: a new ``ReferenceToCT``).
        calibration: a :class:`~comreg_core.registration.judgement.calibration.Calibration` for the
            verdict, or None.
        prior: a :class:`~comreg_core.registration.search.priors.Prior` (LPS; an initial pose, CT and
            US landmarks, the US ones in the stream's reference frame) bounding every update,
            or None (:func:`comreg_plugin.scene_inputs.priorFromNodes` makes one from nodes).
    """

    def __init__(self, logic, imageNode, poseNode=None, *, method: str = "search",
                 ctModelNode=None, runDirectory=None, outputTransformNode=None,
                 calibration=None, prior=None, device: str = "auto", seed: int = 0,
                 maxFramesPerUpdate: int = 16):
        requireNode(imageNode, "vtkMRMLScalarVolumeNode", "incoming image",
                    "Pick the image node the OpenIGTLink connector updates (e.g. 'Image').")
        poseNode = poseNode if poseNode is not None else imageNode.GetParentTransformNode()
        requireNode(poseNode, "vtkMRMLLinearTransformNode", "image pose",
                    "Pick the transform node the connector updates (e.g. 'ImageToReference'), "
                    "or put the image under it.")
        if method == "search":
            if ctModelNode is None:
                raise ComRegError("Live registration by the pose search needs the CT bone "
                                  "model.", "Load a CT segmentation or bone mesh first.")
            registrar = logic._methods.searchRegistrar(ctModelNode)
        elif method == "comreg":
            if not runDirectory:
                raise ComRegError("No pretrained run folder to register with.",
                                  "Pretrain on this CT first, or choose the run folder.")
            registrar = logic._methods.registrar(runDirectory, device)
        else:
            raise ComRegError(f"Live registration cannot use the '{method}' method.",
                              "Use 'search' or 'comreg'.")
        if outputTransformNode is None:
            outputTransformNode = logic.scene.AddNewNodeByClass(
                "vtkMRMLLinearTransformNode", uniqueName(logic.scene, TRANSFORM_NODE_NAME))
        requireNode(outputTransformNode, "vtkMRMLLinearTransformNode", "output transform")
        self.logic, self.imageNode, self.poseNode = logic, imageNode, poseNode
        self.outputTransformNode = outputTransformNode
        self.method = method
        self.session = LiveSession(registrar, calibration=calibration, prior=prior, seed=seed,
                                   max_frames_per_update=maxFramesPerUpdate)
        self.received = 0
        self.notes: list = []
        self.status = (f"live: waiting for frames in '{imageNode.GetName()}' posed by "
                       f"'{poseNode.GetName()}'")
        self._frames: list = []
        self._worker: Optional[threading.Thread] = None
        self._outcome: dict = {}  # the worker's "update" or "error"
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
                   prior=priorFromNodes(parameters=p))
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
        """Whether an update is running in the worker thread."""
        return self._worker is not None

    def tick(self, wait: bool = False) -> Optional[LiveUpdate]:
        """On the GUI thread: apply the update that finished in the worker thread (the output
        node and :attr:`status` follow it), then start the next one with the frames that came
        since (or the backlog). Returns the update applied now, or None. ``wait``: also wait
        for the update just started and apply it (headless scripts). An error of the update
        is raised here."""
        applied = self._finish(block=False)
        if self._worker is None:
            frames, self._frames = self._frames, []
            if frames or self.session.backlog:
                self._outcome = {}
                self._worker = threading.Thread(target=self._update, args=(frames,
                                                self.received), name="ComReg live", daemon=True)
                self._worker.start()
        if wait and self._worker is not None:
            applied = self._finish(block=True) or applied
        return applied

    def _update(self, frames: list, received: int) -> None:
        """The worker thread: one session update (no scene access)."""
        try:
            self._outcome["update"] = self.session.update(frames, received=received)
        except Exception as exc:  # noqa: BLE001 - raised again on the GUI thread by tick()
            self._outcome["error"] = exc

    def _finish(self, block: bool) -> Optional[LiveUpdate]:
        """Apply the worker's update when it is done (waiting for it with ``block``)."""
        if self._worker is None or (self._worker.is_alive() and not block):
            return None
        self._worker.join()
        self._worker = None
        self.notes += self.session.take_notes()
        if "error" in self._outcome:
            raise self._outcome["error"]
        update = self._outcome.get("update")
        if update is None:
            self.status = (f"live: waiting for bone ({self.session.points.frames_with_bone} of "
                           f"{self.session.points.frames_used} frames show it)")
            return None
        node = self.outputTransformNode
        node.SetMatrixTransformToParent(vtkMatrixFromArray(
            T_RAS_LPS @ update.T_ct_us @ T_RAS_LPS))
        update.latency_s = self.session.clock() - update.newest_s
        for key, value in (("method", f"live {self.method}"), ("verdict", update.verdict),
                           ("advice", update.advice), ("covered_mm", f"{update.covered_mm:.1f}"),
                           ("p_correct", "" if update.p_correct is None
                            else f"{update.p_correct:.4f}")):
            node.SetAttribute(ATTRIBUTE_PREFIX + key, value)
        self.status = update.status_line()
        return update

    def stop(self) -> None:
        """Stop observing the image node, after the update under way (applied); the
        registration stays in the output node."""
        try:
            self._finish(block=True)
        except Exception as exc:  # noqa: BLE001 - stopping anyway; said in the notes
            self.notes.append(f"the last update failed: {exc}")
        if self._observer is not None:
            self.imageNode.RemoveObserver(self._observer)
            self._observer = None
