"""The ComReg module's parameter node and Logic: no GUI, batch-capable, on real MRML nodes.

``ComRegLogic(scene)`` works inside 3D Slicer (default scene: ``slicer.mrmlScene``) and headless
on slicer-core (default: a new ``vtkMRMLScene``). It only calls ``comreg_core``:

- :meth:`ComRegLogic.loadSegmentation`: a CT label map (``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd``)
  or 3D Slicer ``.seg.nrrd`` -> a ``vtkMRMLSegmentationNode`` and one closed-surface bone model
  (``vtkMRMLModelNode``) per segment, extracted by :func:`comreg_core.surfaces.ct.extract_bone_surface`;
  :meth:`~ComRegLogic.loadBoneMesh` loads a bone mesh file as a model directly.
- :meth:`ComRegLogic.loadTrackedSweep`: a tracked US sweep (PLUS sequence, frame folder, Slicer
  volume sequence) -> US bone points (:func:`comreg_core.surfaces.us.extract_us_surface`) as a
  model node of vertices; :meth:`~ComRegLogic.loadUSPoints` takes a point cloud file.
- :meth:`ComRegLogic.startPretraining`: ``comreg pretrain`` in a background process
  (:class:`PretrainingJob`: ``poll()`` reads the run's ``training_log.csv``, ``cancel()``); the
  scene is never blocked.
- :meth:`ComRegLogic.register`: ``"comreg"`` (a pretrained run folder,
  :class:`comreg_core.inference.Registrar`), ``"ransac"`` (the Open3D RANSAC + ICP baseline) or
  any callable ``points -> result with T_ct_us``; makes the US->CT ``vtkMRMLLinearTransformNode``
  (to parent, RAS), puts the US points under it and adds the completed bone as a model.
- :meth:`ComRegLogic.saveTransform` (ITK ``.tfm``/``.h5``, LPS, as Slicer writes them),
  :meth:`~ComRegLogic.saveScene` (``.mrml`` plus one data file per node, written by the nodes'
  storage nodes) and :meth:`~ComRegLogic.loadScene`.

Coordinates: the scene is RAS (Slicer's convention); files are in the patient space they declare
(LPS unless tagged) and ComReg's library works in the CT's space (LPS by default). Every crossing
goes through :func:`comreg_core.transforms.space_change`.

Method names are camelCase here, as in 3D Slicer modules.
"""

import csv
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from comreg_core.errors import ComRegError, CorruptFileError, UnsupportedFormatError
from comreg_core.io._files import (atomic_output, check_output_file, check_output_folder,
                                   file_extension, require_input_file)
from comreg_core.transforms import apply_transform, check_rigid, space_change
from comreg_plugin.slicer_compat import (IN_SLICER_APP, ScriptedLoadableModuleLogic,
                                         _StandInLogic, parameterNodeWrapper,
                                         register_segmentation_converters, require_slicer)

slicer = require_slicer()
import vtk  # noqa: E402  (after the clear error above when slicer is missing)
from vtkmodules.util import numpy_support  # noqa: E402

log = logging.getLogger(__name__)

#: The repository root (holds comreg_core/ and comreg_plugin/).
REPO_ROOT = Path(__file__).resolve().parents[1]
#: Node attribute prefix for values ComReg stores on nodes.
ATTRIBUTE_PREFIX = "ComReg."
TRANSFORM_NODE_NAME = "ComReg US to CT"
COMPLETED_BONE_NODE_NAME = "ComReg completed bone"
US_POINTS_NODE_NAME = "US bone points"
BONE_COLOR = (0.95, 0.9, 0.75)
US_POINTS_COLOR = (0.1, 0.55, 1.0)
COMPLETION_COLOR = (0.2, 0.8, 0.3)
METHODS = ("comreg", "ransac")
SCENE_EXTENSIONS = [".mrml"]
# Data file extension per storable node class when saving a scene (Slicer's defaults, except
# models: .vtk, whose header carries SPACE=LPS).
_SCENE_FILE_EXTENSIONS = {
    "vtkMRMLSegmentationNode": ".seg.nrrd",
    "vtkMRMLModelNode": ".vtk",
    "vtkMRMLLinearTransformNode": ".h5",
    "vtkMRMLTransformNode": ".h5",
}


# --------------------------------------------------------------------------------------------
# Parameter node
# --------------------------------------------------------------------------------------------

@parameterNodeWrapper
class ComRegParameterNode:
    """The module's state, saved with the scene.

    segmentation: the CT segmentation. ctModel: the CT bone model registered to.
    usPoints: the US bone points (a model of vertices). outputTransform: US->CT (to parent, RAS).
    completedBone: the network's completed bone in the CT frame.
    method: "comreg" (pretrained run) or "ransac" (RANSAC + ICP baseline).
    runDirectory: the pretraining run folder. preset, maxMinutes, epochs (0 = preset's), seed,
    device: pretraining settings. pretrainingState: idle/running/finished/failed/cancelled;
    pretrainingProgress: 0..1. ambiguous, confidence (-1 = not reported), runtimeSeconds: of
    the last registration.
    """

    segmentation: slicer.vtkMRMLSegmentationNode
    ctModel: slicer.vtkMRMLModelNode
    usPoints: slicer.vtkMRMLModelNode
    outputTransform: slicer.vtkMRMLLinearTransformNode
    completedBone: slicer.vtkMRMLModelNode
    method: str = "comreg"
    runDirectory: str = ""
    preset: str = "cpu"
    maxMinutes: float = 30.0
    epochs: int = 0
    seed: int = 0
    device: str = "auto"
    pretrainingState: str = "idle"
    pretrainingProgress: float = 0.0
    ambiguous: bool = False
    confidence: float = -1.0
    runtimeSeconds: float = 0.0


# --------------------------------------------------------------------------------------------
# numpy <-> VTK / MRML helpers
# --------------------------------------------------------------------------------------------

def vtkMatrixFromArray(T: np.ndarray) -> "vtk.vtkMatrix4x4":
    """A ``vtkMatrix4x4`` holding the ``(4, 4)`` array ``T``."""
    matrix = vtk.vtkMatrix4x4()
    T = np.asarray(T, dtype=np.float64)
    for i in range(4):
        for j in range(4):
            matrix.SetElement(i, j, float(T[i, j]))
    return matrix


def arrayFromVtkMatrix(matrix) -> np.ndarray:
    """The ``(4, 4)`` float64 array of a ``vtkMatrix4x4``."""
    return np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])


def requireNode(node, className: str, what: str, hint: str = ""):
    """``node`` if it is an MRML node of ``className`` (or a subclass), else a
    :class:`ComRegError` naming what was given instead (never an AttributeError later)."""
    if node is None or not hasattr(node, "IsA") or not node.IsA(className):
        given = "nothing" if node is None else (
            f"the {node.GetClassName()} '{node.GetName()}'" if hasattr(node, "GetName")
            else f"a {type(node).__name__}")
        kind = _NODE_KINDS.get(className, className)
        raise ComRegError(f"The {what} must be {kind}, but {given} was given.",
                          hint or f"Pick {kind}.")
    return node


#: How :func:`requireNode` names the node classes it asks for.
_NODE_KINDS = {"vtkMRMLModelNode": "a model node (vtkMRMLModelNode)",
               "vtkMRMLLinearTransformNode": "a linear transform node "
                                              "(vtkMRMLLinearTransformNode)"}


def transformToParentRAS(transformNode) -> np.ndarray:
    """The ``(4, 4)`` to-parent matrix (RAS) of a linear transform node."""
    requireNode(transformNode, "vtkMRMLLinearTransformNode", "transform")
    matrix = vtk.vtkMatrix4x4()
    transformNode.GetMatrixTransformToParent(matrix)
    return arrayFromVtkMatrix(matrix)


def _cells(n_cells: int, size: int, connectivity: np.ndarray) -> "vtk.vtkCellArray":
    cells = vtk.vtkCellArray()
    offsets = np.arange(0, size * n_cells + 1, size, dtype=np.int64)
    cells.SetData(numpy_support.numpy_to_vtkIdTypeArray(offsets, deep=True),
                  numpy_support.numpy_to_vtkIdTypeArray(
                      np.ascontiguousarray(connectivity, dtype=np.int64).ravel(), deep=True))
    return cells


def polyDataFromArrays(points: np.ndarray, faces: Optional[np.ndarray] = None):
    """A ``vtkPolyData`` with double-precision ``points`` ``(N, 3)`` and triangles ``faces``
    ``(M, 3)``, or one vertex cell per point when ``faces`` is None."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    vtk_points = vtk.vtkPoints()
    vtk_points.SetDataTypeToDouble()
    vtk_points.SetData(numpy_support.numpy_to_vtk(points, deep=True))
    polydata = vtk.vtkPolyData()
    polydata.SetPoints(vtk_points)
    if faces is None:
        polydata.SetVerts(_cells(len(points), 1, np.arange(len(points))))
    else:
        polydata.SetPolys(_cells(len(faces), 3, faces))
    return polydata


def arrayFromModelPoints(modelNode) -> np.ndarray:
    """``(N, 3)`` float64 point coordinates of a model node (its own frame, RAS, without the
    parent transform)."""
    requireNode(modelNode, "vtkMRMLModelNode", "points or bone model")
    polydata = modelNode.GetPolyData()
    if polydata is None or polydata.GetPoints() is None or polydata.GetNumberOfPoints() == 0:
        raise ComRegError(f"The model '{modelNode.GetName()}' has no points.",
                          "Load the data again (its file may be missing or empty).")
    return numpy_support.vtk_to_numpy(polydata.GetPoints().GetData()).astype(np.float64)


def arraysFromModelMesh(modelNode) -> tuple:
    """``(vertices (N, 3), faces (M, 3))`` of a triangle model node (RAS, its own frame)."""
    vertices = arrayFromModelPoints(modelNode)
    polys = modelNode.GetPolyData().GetPolys()
    if polys is None or polys.GetNumberOfCells() == 0:
        raise ComRegError(f"The model '{modelNode.GetName()}' has no surface (no triangles).",
                          "Pick the CT bone model, not a point set.")
    offsets = numpy_support.vtk_to_numpy(polys.GetOffsetsArray())
    connectivity = numpy_support.vtk_to_numpy(polys.GetConnectivityArray())
    if not np.all(np.diff(offsets) == 3):
        triangulate = vtk.vtkTriangleFilter()
        triangulate.SetInputData(modelNode.GetPolyData())
        triangulate.PassVertsOff()
        triangulate.PassLinesOff()
        triangulate.Update()
        polys = triangulate.GetOutput().GetPolys()
        vertices = numpy_support.vtk_to_numpy(
            triangulate.GetOutput().GetPoints().GetData()).astype(np.float64)
        connectivity = numpy_support.vtk_to_numpy(polys.GetConnectivityArray())
    return vertices, connectivity.reshape(-1, 3).astype(np.int64)


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    return str(value)


# --------------------------------------------------------------------------------------------
# Pretraining in a background process
# --------------------------------------------------------------------------------------------

@dataclass
class PretrainingStatus:
    """What :meth:`PretrainingJob.poll` saw.

    Attributes:
        state: "running", "finished", "failed" or "cancelled".
        progress: 0..1 (epochs done of the total, or the time budget spent, whichever is
            further; 1 when finished).
        epoch, totalEpochs: epochs written to ``training_log.csv`` so far, and planned.
        loss: the last epoch's training loss (None before the first epoch).
        validation: the last ``val_*`` values of the log (median RTE mm, RRE deg, ...).
        elapsedSeconds: since the process started.
        returnCode: the process exit status (None while it runs).
        message: a line for the user (the CLI's error when it failed).
        runDirectory: the run folder.
    """

    state: str
    progress: float
    epoch: int
    totalEpochs: Optional[int]
    loss: Optional[float]
    validation: dict
    elapsedSeconds: float
    returnCode: Optional[int]
    message: str
    runDirectory: Path


class PretrainingJob:
    """``comreg pretrain`` running in a background process; nothing here blocks.

    The process writes its console output to ``RUN_DIR/pretrain_console.log``; progress comes from
    the run's ``training_log.csv`` (one row per epoch, flushed) and ``config.yaml``. The trainer
    writes every checkpoint atomically (temporary file, then rename); :meth:`cancel` interrupts it
    with SIGINT (the temporary file of a checkpoint being written is removed by the interrupted
    writer), then removes any temporary file left if it had to be killed, so the run folder holds
    either the previous complete checkpoint or none, never a half-written one.
    """

    LOG_NAME = "training_log.csv"
    CONFIG_NAME = "config.yaml"
    CHECKPOINT_NAME = "checkpoint.pt"
    CONSOLE_NAME = "pretrain_console.log"

    def __init__(self, command: list, runDirectory: Path, *, totalEpochs: Optional[int] = None,
                 maxMinutes: Optional[float] = None, env: Optional[dict] = None):
        self.command = [str(c) for c in command]
        self.runDirectory = Path(runDirectory)
        self.runDirectory.mkdir(parents=True, exist_ok=True)
        self.consolePath = self.runDirectory / self.CONSOLE_NAME
        self._totalEpochs = totalEpochs
        self._maxMinutes = maxMinutes
        self._cancelled = False
        self._start = time.monotonic()
        self._end: Optional[float] = None
        console = open(self.consolePath, "w", encoding="utf-8")
        kwargs: dict = {}
        if os.name == "nt":  # pragma: no cover - Windows
            kwargs["creationflags"] = subprocess.CREATE_NEW_PROCESS_GROUP
        else:
            kwargs["start_new_session"] = True  # its own process group: signals reach only it
        try:
            self.process = subprocess.Popen(self.command, stdout=console, stderr=subprocess.STDOUT,
                                            stdin=subprocess.DEVNULL, env=env,
                                            cwd=str(self.runDirectory), **kwargs)
        except OSError as exc:
            console.close()
            raise ComRegError(f"Cannot start the pretraining process ({exc}).",
                              "Check that the Python executable exists and that ComReg is "
                              "installed for it.") from None
        finally:
            console.close()  # the child holds its own handle
        log.info("Pretraining started (pid %d): %s", self.process.pid, " ".join(self.command))

    # -- state ------------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self.process.poll() is None

    def _rows(self) -> list:
        path = self.runDirectory / self.LOG_NAME
        if not path.is_file():
            return []
        try:
            with path.open(newline="", encoding="utf-8") as f:
                rows = list(csv.DictReader(f))
        except (OSError, csv.Error):
            return []
        good = []
        for row in rows:  # the last line may be half-written while the trainer appends
            try:
                int(row.get("epoch") or "")
            except ValueError:
                continue
            good.append(row)
        return good

    def _planned(self) -> tuple:
        epochs, minutes = self._totalEpochs, self._maxMinutes
        path = self.runDirectory / self.CONFIG_NAME
        if path.is_file():
            try:
                import yaml

                training = (yaml.safe_load(path.read_text(encoding="utf-8")) or {}).get(
                    "training", {})
                epochs = int(training.get("epochs", epochs or 0)) or epochs
                budget = float(training.get("max_minutes", 0) or 0)
                minutes = budget if budget > 0 else minutes
            except Exception:  # a config being replaced: keep what we knew
                pass
        return epochs, minutes

    def _message(self) -> str:
        try:
            lines = [line.strip() for line in
                     self.consolePath.read_text(encoding="utf-8", errors="replace").splitlines()
                     if line.strip()]
        except OSError:
            return ""
        errors = [line for line in lines if line.startswith("error:")]
        if errors:
            return errors[-1][len("error:"):].strip()
        return lines[-1] if lines else ""

    def poll(self) -> PretrainingStatus:
        """The job's state now (reads two small files; returns at once)."""
        code = self.process.poll()
        if code is not None and self._end is None:
            self._end = time.monotonic()
        elapsed = (self._end or time.monotonic()) - self._start
        rows = self._rows()
        last = rows[-1] if rows else {}
        epoch = int(last["epoch"]) if last else 0
        loss = float(last["loss"]) if last.get("loss") else None
        validation = {k: float(v) for row in rows for k, v in row.items()
                      if k.startswith("val_") and v}
        epochs, minutes = self._planned()
        fraction = epoch / epochs if epochs else 0.0
        if minutes:
            fraction = max(fraction, elapsed / (60.0 * minutes))
        if code is None:
            state, progress, message = "running", min(fraction, 0.99), f"epoch {epoch}"
        elif self._cancelled:
            state, progress, message = "cancelled", min(fraction, 1.0), "cancelled"
        elif code == 0 and (self.runDirectory / self.CHECKPOINT_NAME).is_file():
            state, progress, message = "finished", 1.0, self._message()
        else:
            state, progress = "failed", min(fraction, 1.0)
            message = self._message() or f"the process exited with status {code}"
        return PretrainingStatus(state, float(progress), epoch, epochs, loss, validation,
                                 elapsed, code, message, self.runDirectory)

    def wait(self, timeoutSeconds: Optional[float] = None, intervalSeconds: float = 0.5,
             callback: Optional[Callable[[PretrainingStatus], None]] = None) -> PretrainingStatus:
        """Poll until the job ends (for batch scripts); ``callback(status)`` after each poll.
        Raises :class:`ComRegError` after ``timeoutSeconds`` (the job keeps running)."""
        deadline = None if timeoutSeconds is None else time.monotonic() + timeoutSeconds
        while True:
            status = self.poll()
            if callback is not None:
                callback(status)
            if status.state != "running":
                return status
            if deadline is not None and time.monotonic() > deadline:
                raise ComRegError(f"Pretraining is still running after {timeoutSeconds:.0f} s.",
                                  "Wait longer or cancel it.")
            time.sleep(intervalSeconds)

    def cancel(self, timeoutSeconds: float = 20.0) -> PretrainingStatus:
        """Stop the process: SIGINT (Python unwinds, the atomic writer removes its temporary
        file), then SIGKILL after ``timeoutSeconds``; then remove any leftover temporary file.
        Raises :class:`ComRegError` if the job is not running."""
        if not self.running:
            status = self.poll()
            raise ComRegError(f"The pretraining in '{self.runDirectory}' is not running (it has "
                              f"{status.state}).", "Start a new pretraining to cancel it.")
        self._cancelled = True
        try:
            if os.name == "nt":  # pragma: no cover - Windows
                self.process.send_signal(signal.CTRL_BREAK_EVENT)
            else:
                os.killpg(self.process.pid, signal.SIGINT)
            self.process.wait(timeoutSeconds)
        except subprocess.TimeoutExpired:
            log.warning("Pretraining did not stop on interrupt within %.0f s; killing it",
                        timeoutSeconds)
            if os.name == "nt":  # pragma: no cover
                self.process.kill()
            else:
                os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()
        except ProcessLookupError:
            self.process.wait()
        for leftover in self.temporaryFiles():
            leftover.unlink(missing_ok=True)
        return self.poll()

    def temporaryFiles(self) -> list:
        """Temporary files of unfinished atomic writes in the run folder (``.NAME.*.tmp*``)."""
        return sorted(p for p in self.runDirectory.glob(".*.tmp*") if p.is_file())


# --------------------------------------------------------------------------------------------
# Registration summary
# --------------------------------------------------------------------------------------------

@dataclass
class RegistrationSummary:
    """What :meth:`ComRegLogic.register` made.

    Attributes:
        transformNode: the US->CT ``vtkMRMLLinearTransformNode`` (to parent, RAS).
        completedBoneNode: the completed bone model (CT frame), or None (method without one).
        T_ct_us: ``(4, 4)`` the estimate as the library returned it (in ``space``).
        T_ct_us_ras: ``(4, 4)`` the same in RAS (= the node's to-parent matrix).
        space: the patient space the method worked in ("LPS" unless the run says otherwise).
        method: "comreg", "ransac" or the callable's name.
        runtimeSeconds: the method's own registration time.
        info: the method's extras (residuals, fitness, "ambiguous", "confidence", ...).
    """

    transformNode: Any
    completedBoneNode: Any
    T_ct_us: np.ndarray
    T_ct_us_ras: np.ndarray
    space: str
    method: str
    runtimeSeconds: float
    info: dict = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Logic
# --------------------------------------------------------------------------------------------

class ComRegLogic(ScriptedLoadableModuleLogic):
    """All ComReg computations on MRML nodes, without GUI (batch-capable).

    Args:
        scene: the ``vtkMRMLScene`` to work in; default ``slicer.mrmlScene`` inside 3D Slicer,
            a new empty scene headless.
    """

    def __init__(self, scene=None):
        ScriptedLoadableModuleLogic.__init__(self)
        if scene is None:
            scene = slicer.mrmlScene if IN_SLICER_APP else slicer.vtkMRMLScene()
        self.scene = scene
        register_segmentation_converters()
        self.pretrainingJob: Optional[PretrainingJob] = None
        self._registrars: dict = {}
        self._baselines: dict = {}

    # -- parameter node ---------------------------------------------------------------------

    def getParameterNode(self) -> ComRegParameterNode:
        """The module's singleton parameter node in this logic's scene, typed."""
        # Slicer's base class looks in slicer.mrmlScene; this logic may own another scene.
        return ComRegParameterNode(_StandInLogic.getParameterNode(self))

    # -- nodes ------------------------------------------------------------------------------

    def _uniqueName(self, name: str) -> str:
        return self.scene.GenerateUniqueName(name) if self.scene.GetFirstNodeByName(name) \
            else name

    def addModel(self, points_ras: np.ndarray, faces: Optional[np.ndarray], name: str,
                 color=BONE_COLOR, pointSize: float = 3.0, node=None):
        """A model node (with display node) of RAS ``points`` and triangle ``faces`` (or of
        vertices only when ``faces`` is None); ``node`` is updated in place if given."""
        if node is not None:
            requireNode(node, "vtkMRMLModelNode", "node to update")
        polydata = polyDataFromArrays(points_ras, faces)
        if node is None:
            node = self.scene.AddNewNodeByClass("vtkMRMLModelNode", self._uniqueName(name))
        node.SetAndObservePolyData(polydata)
        if node.GetDisplayNode() is None:
            node.CreateDefaultDisplayNodes()
        display = node.GetDisplayNode()
        display.SetColor(*[float(c) for c in color])
        if faces is None:
            display.SetRepresentation(display.PointsRepresentation)
            display.SetPointSize(pointSize)
        return node

    def addBoneModel(self, mesh, name: str, color=BONE_COLOR):
        """A closed-surface model node of a :class:`~comreg_core.io.SurfaceMesh` (any space)."""
        ras = mesh.in_space("RAS")
        node = self.addModel(ras.vertices, ras.faces, name, color)
        node.SetAttribute(ATTRIBUTE_PREFIX + "role", "ct_bone")
        return node

    def addPointsModel(self, points: np.ndarray, space: str, name: str = US_POINTS_NODE_NAME,
                       color=US_POINTS_COLOR, node=None):
        """A model node of vertices from ``(N, 3)`` points given in ``space``."""
        ras = apply_transform(space_change(space, "RAS"), np.asarray(points, dtype=np.float64))
        return self.addModel(ras, None, name, color, node=node)

    # -- CT ---------------------------------------------------------------------------------

    def loadSegmentation(self, path, segmentNames=None, options=None,
                         progress: Optional[Callable[[float, str], None]] = None) -> tuple:
        """Load a CT segmentation and make one closed-surface bone model per segment.

        Args:
            path: a label map (``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd``; each label value is a
                segment) or a 3D Slicer ``.seg.nrrd`` (read by Slicer's own storage node).
            segmentNames: only these segments get models (default: all).
            options: :class:`comreg_core.surfaces.ct.SurfaceExtractionOptions`.
            progress: ``progress(fraction, message)``.

        Returns:
            ``(segmentationNode, [modelNode, ...])``; the first model becomes the parameter
            node's ``ctModel``.

        Raises:
            InputFileNotFoundError, UnsupportedFormatError, CorruptFileError,
            LabelNotFoundError, EmptyMaskError (from comreg_core).
        """
        from comreg_core.io import SEGMENTATION_READ_EXTENSIONS, read_segmentation
        from comreg_core.surfaces.ct import extract_bone_surface

        path = require_input_file(path, "CT segmentation")
        ext = file_extension(path)
        if ext not in SEGMENTATION_READ_EXTENSIONS:
            raise UnsupportedFormatError(path, "CT segmentation", SEGMENTATION_READ_EXTENSIONS)
        report = progress or (lambda fraction, message: None)
        report(0.0, "reading")
        seg = read_segmentation(path)
        segments = seg.segments
        if segmentNames is not None:
            segments = [seg.find_segment(name=name) for name in segmentNames]
        base = Path(path).name[: -len(ext)] or "CT"
        if ext == ".seg.nrrd":
            segNode = self._readSlicerSegmentation(path, base)
        else:
            segNode = self._segmentationFromArrays(seg, base)
        segNode.CreateDefaultDisplayNodes()
        models = []
        for i, segment in enumerate(segments):
            report(0.1 + 0.9 * i / len(segments), f"surface of '{segment.name}'")
            mesh = extract_bone_surface(seg, segment=segment, options=options)
            model = self.addBoneModel(mesh, f"{segment.name} bone",
                                      segment.color or BONE_COLOR)
            model.SetAttribute(ATTRIBUTE_PREFIX + "segment", segment.name)
            model.SetAttribute(ATTRIBUTE_PREFIX + "source", str(path))
            models.append(model)
        report(1.0, "done")
        p = self.getParameterNode()
        p.segmentation = segNode
        if models:
            p.ctModel = models[0]
        log.info("Loaded '%s': %d segment(s), %d bone model(s)", path, len(seg.segments),
                 len(models))
        return segNode, models

    def _readSlicerSegmentation(self, path: Path, name: str):
        segNode = self.scene.AddNewNodeByClass("vtkMRMLSegmentationNode", self._uniqueName(name))
        storage = self.scene.AddNewNodeByClass("vtkMRMLSegmentationStorageNode")
        storage.SetFileName(str(Path(path).resolve()))
        if not storage.ReadData(segNode):
            self.scene.RemoveNode(storage)
            self.scene.RemoveNode(segNode)
            raise CorruptFileError(path, "3D Slicer's segmentation reader rejected it")
        segNode.SetAndObserveStorageNodeID(storage.GetID())
        return segNode

    def _segmentationFromArrays(self, seg, name: str):
        """A segmentation node (binary labelmaps) built from a comreg_core Segmentation."""
        segNode = self.scene.AddNewNodeByClass("vtkMRMLSegmentationNode", self._uniqueName(name))
        ijk_to_ras = space_change(seg.space, "RAS") @ seg.ijk_to_space
        image = None
        for segment in seg.segments:
            mask = np.asarray(seg.mask(segment), dtype=np.uint8)
            image = slicer.vtkOrientedImageData()
            image.SetDimensions(*mask.shape)
            image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(
                np.ascontiguousarray(mask.ravel(order="F")), deep=True,
                array_type=vtk.VTK_UNSIGNED_CHAR))
            image.SetImageToWorldMatrix(vtkMatrixFromArray(ijk_to_ras))
            segNode.AddSegmentFromBinaryLabelmapRepresentation(
                image, segment.name, [float(c) for c in (segment.color or BONE_COLOR)])
        if image is not None:  # Slicer's writer wants the reference geometry
            segmentation = segNode.GetSegmentation()
            segmentation.SetConversionParameter(
                slicer.vtkSegmentationConverter.GetReferenceImageGeometryParameterName(),
                slicer.vtkSegmentationConverter.SerializeImageGeometry(image))
        return segNode

    def loadBoneMesh(self, path, name: Optional[str] = None):
        """Load a bone mesh file (``.stl``, ``.ply``, ``.obj``, ``.vtk``, ``.vtp``; LPS unless
        its ``SPACE=`` tag says otherwise) as the CT bone model."""
        from comreg_core.io import read_mesh

        mesh = read_mesh(path)
        model = self.addBoneModel(mesh, name or Path(path).stem)
        model.SetAttribute(ATTRIBUTE_PREFIX + "source", str(path))
        self.getParameterNode().ctModel = model
        return model

    # -- US ---------------------------------------------------------------------------------

    def loadTrackedSweep(self, path, calibration=None, config=None, name=US_POINTS_NODE_NAME,
                         progress: Optional[Callable[[int, int], None]] = None) -> tuple:
        """Read a tracked US sweep, extract its bone surface points and add them as a model.

        Args:
            path: PLUS sequence (``.igs.mha``, ``.seq.nrrd``, ...), frame folder or Slicer volume
                sequence (:func:`comreg_core.io.read_tracked_sweep`).
            calibration: PLUS device-set XML or ``calibration.json`` (if not beside the data).
            config: :class:`comreg_core.surfaces.us_config.USExtractionConfig` or its YAML file.
            progress: ``progress(done_frames, total_frames)``.

        Returns:
            ``(pointsNode, USExtractionResult)``; the node becomes the parameter node's
            ``usPoints``.
        """
        from comreg_core.io import read_tracked_sweep
        from comreg_core.surfaces.us import extract_us_surface
        from comreg_core.surfaces.us_config import USExtractionConfig, load_us_extraction_config

        if not isinstance(config, USExtractionConfig):
            config = load_us_extraction_config(config)
        sweep = read_tracked_sweep(path, calibration=calibration, reference=config.reference)
        result = extract_us_surface(sweep, config, progress=progress)
        node = self.addPointsModel(result.points.points, "LPS", name)
        node.SetAttribute(ATTRIBUTE_PREFIX + "role", "us_points")
        node.SetAttribute(ATTRIBUTE_PREFIX + "source", str(path))
        node.SetAttribute(ATTRIBUTE_PREFIX + "extraction", result.summary())
        self.getParameterNode().usPoints = node
        log.info("US sweep '%s': %s", path, result.summary())
        return node, result

    def loadUSPoints(self, path, name=US_POINTS_NODE_NAME):
        """Load US bone points from a point cloud file (``.ply``, ``.pcd``, ``.xyz``, ``.npy``,
        ...; LPS unless tagged) as the parameter node's ``usPoints``."""
        from comreg_core.io import read_points

        cloud = read_points(path)
        node = self.addPointsModel(cloud.points, cloud.space, name)
        node.SetAttribute(ATTRIBUTE_PREFIX + "role", "us_points")
        node.SetAttribute(ATTRIBUTE_PREFIX + "source", str(path))
        self.getParameterNode().usPoints = node
        return node

    # -- pretraining ------------------------------------------------------------------------

    def startPretraining(self, ctModel=None, runDirectory=None, *, preset: Optional[str] = None,
                         maxMinutes: Optional[float] = None, epochs: Optional[int] = None,
                         seed: Optional[int] = None, device: Optional[str] = None,
                         config=None, resume: bool = False,
                         python: Optional[str] = None) -> PretrainingJob:
        """Start ``comreg pretrain`` in the background and return the :class:`PretrainingJob`.

        Args:
            ctModel: the CT bone model node (written to ``RUN_DIR/ct_bone.vtk``, LPS) or a mesh
                file path; default the parameter node's ``ctModel``.
            runDirectory: the run folder; default the parameter node's ``runDirectory``.
            preset, maxMinutes, epochs, seed, device: as ``comreg pretrain`` (defaults from the
                parameter node; ``epochs`` 0 = the preset's).
            config: YAML overrides file (or a dict, written to ``RUN_DIR/overrides.yaml``).
            resume: continue the run in ``runDirectory``.
            python: the Python to run ComReg with (default ``sys.executable``, which inside 3D
                Slicer is its PythonSlicer).

        Raises:
            ComRegError: another pretraining is running, no CT model, or the folder already
            holds a run (without ``resume``).
        """
        if self.pretrainingJob is not None and self.pretrainingJob.running:
            raise ComRegError("A pretraining is already running "
                              f"('{self.pretrainingJob.runDirectory}').",
                              "Wait for it to finish or cancel it first.")
        p = self.getParameterNode()
        runDirectory = runDirectory or p.runDirectory
        if not runDirectory:
            raise ComRegError("No run folder for the pretraining.",
                              "Choose an (empty) output folder.")
        runDirectory = check_output_folder(Path(runDirectory).resolve(), what="run folder",
                                           run_folder_ok=True)
        checkpoint = runDirectory / PretrainingJob.CHECKPOINT_NAME
        if checkpoint.exists() and not resume:
            raise ComRegError(f"'{runDirectory}' already holds a training run.",
                              "Resume it, register with it, or choose an empty folder.")
        ctModel = ctModel if ctModel is not None else p.ctModel
        if ctModel is None:
            raise ComRegError("No CT bone model to pretrain on.",
                              "Load a CT segmentation or bone mesh first.")
        # every check before the run folder is made, so a refusal leaves nothing behind
        if isinstance(ctModel, (str, Path)):
            meshPath, mesh = require_input_file(ctModel, "CT mesh file"), None
        else:
            requireNode(ctModel, "vtkMRMLModelNode", "CT bone model",
                        "Pick the CT bone model (loaded from a segmentation or mesh).")
            meshPath, mesh = runDirectory / "ct_bone.vtk", self._modelMesh(ctModel)
        if config is not None and not isinstance(config, dict):
            require_input_file(config, "pretraining config")
        created = not runDirectory.exists()
        runDirectory.mkdir(parents=True, exist_ok=True)
        try:
            job = self._launchPretraining(
                mesh, meshPath, runDirectory, preset=preset or p.preset,
                device=device or p.device,
                maxMinutes=p.maxMinutes if maxMinutes is None else maxMinutes,
                epochs=(p.epochs or None) if epochs is None else epochs,
                seed=p.seed if seed is None else seed, config=config, resume=resume,
                python=python)
        except BaseException:
            if created:  # a failed start leaves no folder of its own behind
                shutil.rmtree(runDirectory, ignore_errors=True)
            raise
        self.pretrainingJob = job
        p.runDirectory = str(runDirectory)
        p.pretrainingState = "running"
        p.pretrainingProgress = 0.0
        return job

    def _launchPretraining(self, mesh, meshPath: Path, runDirectory: Path, *, preset, device,
                           maxMinutes, epochs, seed, config, resume, python) -> "PretrainingJob":
        """Write the CT mesh and overrides into the run folder and start the process."""
        if mesh is not None:
            from comreg_core.io.meshes import write_mesh

            write_mesh(mesh, meshPath)
        command = [python or sys.executable, "-m", "comreg_core.cli", "pretrain", str(meshPath),
                   "--out", str(runDirectory), "--device", device]
        if resume:
            command.append("--resume")
        else:
            command += ["--preset", preset, "--seed", str(int(seed))]
        if maxMinutes:
            command += ["--max-minutes", repr(float(maxMinutes))]
        if epochs:
            command += ["--epochs", str(int(epochs))]
        if isinstance(config, dict):
            import yaml

            with atomic_output(runDirectory / "overrides.yaml") as tmp:
                tmp.write_text(yaml.safe_dump(config, sort_keys=False), encoding="utf-8")
            config = runDirectory / "overrides.yaml"
        if config is not None:
            command += ["--config", str(require_input_file(config, "pretraining config"))]
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(
            [str(REPO_ROOT)] + [x for x in env.get("PYTHONPATH", "").split(os.pathsep) if x])
        env["PYTHONUNBUFFERED"] = "1"
        return PretrainingJob(command, runDirectory, totalEpochs=epochs or None,
                              maxMinutes=maxMinutes or None, env=env)

    def _modelMesh(self, modelNode):
        """The triangle mesh of a model node as a LPS :class:`~comreg_core.io.SurfaceMesh`."""
        from comreg_core.io.meshes import SurfaceMesh

        vertices, faces = arraysFromModelMesh(modelNode)
        return SurfaceMesh(vertices, faces, "RAS").in_space("LPS")

    def pollPretraining(self) -> PretrainingStatus:
        """The running (or last) pretraining's status, also stored in the parameter node."""
        if self.pretrainingJob is None:
            raise ComRegError("No pretraining was started.", "Start one first.")
        status = self.pretrainingJob.poll()
        p = self.getParameterNode()
        p.pretrainingState = status.state
        p.pretrainingProgress = status.progress
        if status.state == "finished":
            p.runDirectory = str(status.runDirectory)
        return status

    def cancelPretraining(self) -> PretrainingStatus:
        """Cancel the running pretraining (:meth:`PretrainingJob.cancel`)."""
        if self.pretrainingJob is None:
            raise ComRegError("No pretraining is running, so there is nothing to cancel.",
                              "Start a pretraining first.")
        self.pretrainingJob.cancel()
        return self.pollPretraining()

    # -- registration -----------------------------------------------------------------------

    def registrar(self, runDirectory, device: str = "auto"):
        """The :class:`comreg_core.inference.Registrar` of a run folder (cached while its
        checkpoint is unchanged)."""
        from comreg_core.inference import Registrar

        run = Path(runDirectory)
        checkpoint = run / PretrainingJob.CHECKPOINT_NAME if run.is_dir() else run
        key = (str(run.resolve()), device)
        stamp = checkpoint.stat().st_mtime_ns if checkpoint.is_file() else None
        cached = self._registrars.get(key)
        if cached is None or cached[0] != stamp or stamp is None:
            self._registrars[key] = (stamp, Registrar.from_run(run, device))
        return self._registrars[key][1]

    def ransacBaseline(self, ctModelNode, seed: int = 0):
        """The RANSAC + ICP baseline prepared for a CT model node (cached while it is
        unchanged)."""
        from comreg_core.evaluation.baselines import RansacIcpBaseline

        requireNode(ctModelNode, "vtkMRMLModelNode", "CT bone model",
                    "Pick the CT bone model (loaded from a segmentation or mesh).")
        polydata = ctModelNode.GetPolyData()
        key = (ctModelNode.GetID(), polydata.GetMTime() if polydata else 0, int(seed))
        if key not in self._baselines:
            vertices, faces = arraysFromModelMesh(ctModelNode)
            lps = apply_transform(space_change("RAS", "LPS"), vertices)
            self._baselines = {key: RansacIcpBaseline((lps, faces), seed=seed)}
        return self._baselines[key]

    def register(self, usPointsNode=None, method=None, *, runDirectory=None, ctModelNode=None,
                 seed: int = 0, device: Optional[str] = None) -> RegistrationSummary:
        """Register the US points to the CT and show the result in the scene.

        Args:
            usPointsNode: the US points model (default: the parameter node's ``usPoints``); its
                own coordinates (without any parent transform) are the US frame.
            method: ``"comreg"`` (needs ``runDirectory``), ``"ransac"`` (needs the CT model),
                or a callable taking ``(N, 3)`` LPS points and returning a result with
                ``T_ct_us`` (a :class:`~comreg_core.inference.RegistrationResult`,
                :class:`~comreg_core.evaluation.outputs.RegistrationOutput`, a dict or a 4x4
                array). Default: the parameter node's ``method``.
            runDirectory: the pretrained run (default: the parameter node's).
            ctModelNode: the CT bone model (default: the parameter node's ``ctModel``).
            seed: registration seed. device: torch device for "comreg".

        Creates or updates the ``vtkMRMLLinearTransformNode`` "ComReg US to CT" holding
        ``T_ct_us`` as its to-parent matrix in RAS, places the US points under it and adds the
        completed bone (when the method returns one) as a model in the CT frame. Values the
        method reports under ``info["ambiguous"]`` / ``info["confidence"]`` are stored on the
        transform node (attributes ``ComReg.ambiguous`` / ``ComReg.confidence``) and in the
        parameter node.
        """
        from comreg_core.evaluation.outputs import as_registration_output

        p = self.getParameterNode()
        usPointsNode = usPointsNode if usPointsNode is not None else p.usPoints
        if usPointsNode is None:
            raise ComRegError("There are no US points to register.",
                              "Load a tracked sweep or a US point cloud first.")
        requireNode(usPointsNode, "vtkMRMLModelNode", "US points",
                    "Pick the US bone points model (from a sweep or a point cloud file).")
        if ctModelNode is not None:
            requireNode(ctModelNode, "vtkMRMLModelNode", "CT bone model",
                        "Pick the CT bone model (loaded from a segmentation or mesh).")
        method = method if method is not None else p.method
        seed = int(seed)
        device = device or p.device
        if callable(method):
            space, run = "LPS", method
            methodName = getattr(method, "name", getattr(method, "__name__", "custom"))
        elif method == "comreg":
            runDirectory = runDirectory or p.runDirectory
            if not runDirectory:
                raise ComRegError("No pretrained run folder to register with.",
                                  "Pretrain on this CT first, or choose the run folder.")
            registrar = self.registrar(runDirectory, device)
            space, methodName = registrar.space, "comreg"

            def run(points):
                return registrar.register(points, seed=seed)
        elif method == "ransac":
            ctModelNode = ctModelNode if ctModelNode is not None else p.ctModel
            if ctModelNode is None:
                raise ComRegError("The RANSAC baseline needs the CT bone model.",
                                  "Load a CT segmentation or bone mesh first.")
            baseline = self.ransacBaseline(ctModelNode, seed)
            baseline.reseed(seed)
            space, run, methodName = "LPS", baseline, "ransac"
        else:
            raise ComRegError(f"Unknown registration method '{method}'.",
                              f"Use one of: {', '.join(METHODS)}, or pass a callable.")

        points = apply_transform(space_change("RAS", space), arrayFromModelPoints(usPointsNode))
        start = time.perf_counter()
        raw = run(points)
        output = as_registration_output(raw, time.perf_counter() - start)
        T = check_rigid(output.T_ct_us)
        C = space_change(space, "RAS")
        T_ras = C @ T @ np.linalg.inv(C)

        transformNode = p.outputTransform
        if transformNode is None:
            transformNode = self.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode",
                                                         self._uniqueName(TRANSFORM_NODE_NAME))
        transformNode.SetMatrixTransformToParent(vtkMatrixFromArray(T_ras))
        usPointsNode.SetAndObserveTransformNodeID(transformNode.GetID())

        completion_ct = getattr(raw, "completion_ct", None)
        if completion_ct is None and output.completion is not None:
            completion_ct = apply_transform(T, output.completion)
        completedNode = None
        if completion_ct is not None and len(completion_ct):
            completedNode = self.addPointsModel(completion_ct, space, COMPLETED_BONE_NODE_NAME,
                                                COMPLETION_COLOR, node=p.completedBone)
            completedNode.SetAttribute(ATTRIBUTE_PREFIX + "role", "completed_bone")

        info = dict(output.info)
        attributes = {"method": methodName, "runtime_s": f"{output.runtime_s:.6g}",
                      "space": space, "info": json.dumps(info, default=_jsonable)}
        if methodName == "comreg":
            attributes["runDirectory"] = str(runDirectory)
        for key, value in attributes.items():
            transformNode.SetAttribute(ATTRIBUTE_PREFIX + key, value)
        p.outputTransform = transformNode
        p.usPoints = usPointsNode
        p.completedBone = completedNode
        p.runtimeSeconds = float(output.runtime_s)
        if "ambiguous" in info:
            p.ambiguous = bool(info["ambiguous"])
            transformNode.SetAttribute(ATTRIBUTE_PREFIX + "ambiguous",
                                       "true" if p.ambiguous else "false")
        if "confidence" in info and info["confidence"] is not None:
            p.confidence = float(info["confidence"])
            transformNode.SetAttribute(ATTRIBUTE_PREFIX + "confidence", repr(p.confidence))
        log.info("Registered '%s' with %s in %.3f s", usPointsNode.GetName(), methodName,
                 output.runtime_s)
        return RegistrationSummary(transformNode, completedNode, T, T_ras, space, methodName,
                                   float(output.runtime_s), info)

    # -- files ------------------------------------------------------------------------------

    def saveTransform(self, transformNode, path) -> Path:
        """Write a linear transform node as an ITK ``.tfm``/``.txt``/``.h5`` file, LPS, in ITK's
        resampling direction, exactly as 3D Slicer saves it (atomic write)."""
        from comreg_core.io import TRANSFORM_EXTENSIONS, save_transform
        from comreg_core.io._files import require_extension

        if transformNode is None:
            raise ComRegError("There is no linear transform to save.", "Register first.")
        requireNode(transformNode, "vtkMRMLLinearTransformNode", "transform to save",
                    "Pick the registration's transform (register first).")
        require_extension(path, "transform", TRANSFORM_EXTENSIONS)
        check_output_file(path, what="transform file")
        return save_transform(transformToParentRAS(transformNode), path, space="RAS")

    def saveScene(self, path) -> Path:
        """Save the scene as a ``.mrml`` file with one data file per node beside it (written by
        the nodes' storage nodes: segmentations ``.seg.nrrd``, models ``.vtk`` with
        ``SPACE=LPS``, transforms ``.h5``), every file written atomically. 3D Slicer opens the
        ``.mrml`` (File > Add Data or drag and drop)."""
        path = Path(path)
        if file_extension(path) not in SCENE_EXTENSIONS:
            raise UnsupportedFormatError(path, "scene", SCENE_EXTENSIONS)
        check_output_file(path, what="scene file")  # before any data file is written
        folder = path.resolve().parent
        folder.mkdir(parents=True, exist_ok=True)
        used: set = set()
        nodes = [self.scene.GetNthNodeByClass(i, "vtkMRMLStorableNode")
                 for i in range(self.scene.GetNumberOfNodesByClass("vtkMRMLStorableNode"))]
        for node in nodes:
            if not node.GetSaveWithScene() or node.GetHideFromEditors():
                continue
            storage = node.GetStorageNode()
            if storage is None:
                node.AddDefaultStorageNode()
                storage = node.GetStorageNode()
            if storage is None:
                continue
            ext = _SCENE_FILE_EXTENSIONS.get(node.GetClassName(),
                                             "." + storage.GetDefaultWriteFileExtension())
            stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", node.GetName()).strip("_") or "node"
            name, k = stem + ext, 1
            while name.lower() in used:
                name, k = f"{stem}_{k}{ext}", k + 1
            used.add(name.lower())
            target = folder / name
            with atomic_output(target) as tmp:
                storage.SetFileName(str(tmp))
                ok = storage.WriteData(node)
                storage.SetFileName(str(target))  # what the scene refers to, set before rename
                if not ok:
                    raise ComRegError(f"3D Slicer's writer could not save '{node.GetName()}' "
                                      f"to '{target}'.", "Check that the folder is writable.")
        self.scene.SetRootDirectory(str(folder))
        self.scene.SetURL(str(path.resolve()))
        self.scene.SetSaveToXMLString(1)  # the XML text, written atomically below
        try:
            ok = self.scene.Commit()
            xml = self.scene.GetSceneXMLString()
        finally:
            self.scene.SetSaveToXMLString(0)
        if not ok or not xml:
            raise ComRegError(f"3D Slicer's scene writer failed for '{path}'.",
                              "Check the log for the node it could not write.")
        with atomic_output(path) as tmp:
            tmp.write_text(xml, encoding="utf-8")
        log.info("Saved the scene to '%s' (%d data files)", path, len(used))
        return path

    def loadScene(self, path):
        """Replace this logic's scene content with a saved ``.mrml`` scene (data files are read
        by their storage nodes). Returns the scene."""
        path = require_input_file(path, "scene file")
        if file_extension(path) not in SCENE_EXTENSIONS:
            raise UnsupportedFormatError(path, "scene", SCENE_EXTENSIONS)
        self.scene.SetURL(str(Path(path).resolve()))
        if not self.scene.Connect():
            raise CorruptFileError(path, f"3D Slicer could not load the scene "
                                   f"(error code {self.scene.GetErrorCode()})")
        self._registrars.clear()
        self._baselines.clear()
        return self.scene
