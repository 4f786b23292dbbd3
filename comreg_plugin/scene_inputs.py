"""Inputs the ComReg module takes from the scene, as 3D Slicer / SlicerIGT users hold them.

- A tracked sweep as a Sequence browser: a volume sequence of 2D frames (the master) and a
  linear-transform sequence of per-frame ``ImageToReference`` poses, as PLUS / OpenIGTLink
  recordings or loaded ``.seq.nrrd`` / ``.igs.mha`` files give them ->
  :class:`comreg_core.io.TrackedSweep` (:func:`trackedSweepFromBrowser`), and the other way
  (:func:`addSweepBrowser`: a file sweep shown in Slicer as a Sequence).
- Bone points as a model node (its vertices) or a markups node (its control points):
  :func:`arrayFromPointsNode`.
- A CT segmentation node -> :class:`comreg_core.io.Segmentation` through Slicer's own
  ``.seg.nrrd`` writer (:func:`segmentationFromNode`).
- A reconstructed 3D US volume as a scalar volume node -> :class:`comreg_core.io.volumes.Volume`
  (RAS, its IJKToRAS geometry; :func:`volumeFromNode`).
- A prior for the pose search: an initial-pose transform node and CT / US landmarks markups
  nodes -> :class:`comreg_core.registration.search.priors.Prior` (:func:`priorFromNodes`).

Coordinates: frame geometry in the scene is ``T_ImageToReference (RAS) @ IJKToRAS``; a
``TrackedSweep`` is LPS, so ``T_ref_pixel (LPS) = T_RAS_LPS @ T_ImageToReference @ IJKToRAS``.
"""

import logging
import re
import tempfile
from pathlib import Path
from typing import Optional

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.io.sweeps import TrackedSweep, frames_to_grey
from comreg_core.transforms import T_RAS_LPS
from comreg_plugin.scene_io import arrayFromModelPoints, arrayFromVtkMatrix, requireNode, \
    uniqueName, vtkMatrixFromArray
from comreg_plugin.slicer_compat import require_slicer

slicer = require_slicer()
import vtk  # noqa: E402
from vtkmodules.util import numpy_support  # noqa: E402

log = logging.getLogger(__name__)

#: Node classes that hold bone points.
POINTS_NODE_CLASSES = ("vtkMRMLModelNode", "vtkMRMLMarkupsNode")


# --------------------------------------------------------------------------------------------
# Sequences <-> TrackedSweep
# --------------------------------------------------------------------------------------------

def sweepSequences(browserNode, imageSequence=None, transformSequence=None) -> tuple:
    """``(imageSequence, transformSequence or None)`` of a Sequence browser: the volume sequence
    (default: the only one, or the master) and the linear-transform sequence of the frame poses
    (default: the only one, else the one named ``ImageTo...``). Raises :class:`ComRegError`
    naming the candidates when the choice is not clear."""
    requireNode(browserNode, "vtkMRMLSequenceBrowserNode", "tracked US sweep",
                "Pick the Sequence browser of the recorded sweep (frames + tracking).")
    nodes = vtk.vtkCollection()
    browserNode.GetSynchronizedSequenceNodes(nodes, True)
    sequences = [nodes.GetItemAsObject(i) for i in range(nodes.GetNumberOfItems())]
    volumes = [s for s in sequences if _holds(s, "vtkMRMLVolumeNode")]
    transforms = [s for s in sequences if _holds(s, "vtkMRMLLinearTransformNode")]
    name = browserNode.GetName()
    if imageSequence is None:
        master = browserNode.GetMasterSequenceNode()
        if len(volumes) == 1 or (volumes and master in volumes):
            imageSequence = volumes[0] if len(volumes) == 1 else master
        else:
            raise ComRegError(f"The sequence browser '{name}' holds "
                              f"{_names(volumes) or 'no image sequence'}.",
                              "Pick the sequence of the ultrasound frames.")
    if transformSequence is None and transforms:
        byName = [s for s in transforms if re.match(r"ImageTo", s.GetName() or "")]
        if len(transforms) == 1 or len(byName) == 1:
            transformSequence = transforms[0] if len(transforms) == 1 else byName[0]
        else:
            raise ComRegError(f"The sequence browser '{name}' holds several transform "
                              f"sequences ({_names(transforms)}).",
                              "Pick the ImageToReference sequence of the frame poses.")
    return imageSequence, transformSequence


def trackedSweepFromBrowser(browserNode, imageSequence=None, transformSequence=None
                            ) -> TrackedSweep:
    """The :class:`~comreg_core.io.TrackedSweep` (LPS, mm) of a Sequence browser: one frame per
    image item, its pose ``T_ImageToReference @ IJKToRAS`` with the transform item at the same
    index value (frames without one are invalid); without a transform sequence the frames'
    own geometry is their pose. Index values that are numbers become timestamps (s)."""
    imageSequence, transformSequence = sweepSequences(browserNode, imageSequence,
                                                      transformSequence)
    n = imageSequence.GetNumberOfDataNodes()
    if n == 0:
        raise ComRegError(f"The image sequence '{imageSequence.GetName()}' has no frames.",
                          "Record or load the sweep again.")
    frames, poses, stamps = [], np.full((n, 4, 4), np.nan), np.full(n, np.nan)
    for i in range(n):
        value = imageSequence.GetNthIndexValue(i)
        volume = imageSequence.GetNthDataNode(i)
        frames.append(_frameArray(volume, imageSequence.GetName(), i))
        try:
            stamps[i] = float(value)
        except ValueError:
            pass
        item = transformSequence.GetDataNodeAtValue(value, True) \
            if transformSequence is not None else None
        if transformSequence is not None and item is None:
            continue  # no pose recorded for this frame
        ijk_to_ras = vtk.vtkMatrix4x4()
        volume.GetIJKToRASMatrix(ijk_to_ras)
        T_image = _toParent(item) if item is not None else np.eye(4)
        poses[i] = T_RAS_LPS @ T_image @ arrayFromVtkMatrix(ijk_to_ras)
    shapes = {f.shape[:2] for f in frames}
    if len(shapes) != 1:
        raise ComRegError(f"The frames of '{imageSequence.GetName()}' differ in size "
                          f"({sorted(shapes)}).", "Use a sequence of equally sized 2D frames.")
    spacing = np.linalg.norm(poses[:, :3, :2], axis=1)  # N 2 (nan where no pose)
    spacing = np.nanmedian(spacing, axis=0)
    T_ref_image = poses @ np.diag([1 / spacing[0], 1 / spacing[1], 1.0, 1.0])
    normals = T_ref_image[:, :3, 2]
    T_ref_image[:, :3, 2] = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    reference = _referenceName(transformSequence)
    return TrackedSweep(frames_to_grey(np.stack(frames)), spacing, T_ref_image, stamps,
                        np.isfinite(poses).all(axis=(1, 2)), reference,
                        [f"Frame{i:04d}" for i in range(n)], None)


def addSweepBrowser(scene, sequencesLogic, sweep: TrackedSweep, name: str = "Sweep"):
    """Show a :class:`TrackedSweep` in ``scene`` as a SlicerIGT recording: a browser
    ``name`` with the volume sequence "Image" (master) and the transform sequence
    "ImageTo<sweep.reference>" (items: ``IJKToRAS = T_RAS_LPS @ diag(spacing)``, transform
    ``T_RAS_LPS @ T_ref_image @ T_RAS_LPS``), and the proxy image under the proxy transform.
    Frames without a pose get no transform item. Returns the browser node."""
    imageSequence = scene.AddNewNodeByClass("vtkMRMLSequenceNode", uniqueName(scene, "Image"))
    transformSequence = scene.AddNewNodeByClass(
        "vtkMRMLSequenceNode", uniqueName(scene, f"ImageTo{sweep.reference or 'Reference'}"))
    for sequence in (imageSequence, transformSequence):
        sequence.SetIndexName("time")
        sequence.SetIndexUnit("s")
    ijk_to_ras = vtkMatrixFromArray(T_RAS_LPS @ np.diag([*sweep.spacing, 1.0, 1.0]))
    volume = slicer.vtkMRMLScalarVolumeNode()
    transform = slicer.vtkMRMLLinearTransformNode()
    H, W = sweep.image_shape
    for i in range(sweep.n_frames):
        value = f"{sweep.timestamps[i]:.6f}" if np.isfinite(sweep.timestamps[i]) else str(i)
        image = vtk.vtkImageData()
        image.SetDimensions(W, H, 1)
        image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(
            np.ascontiguousarray(sweep.frames[i]).ravel(), deep=True,
            array_type=numpy_support.get_vtk_array_type(sweep.frames.dtype)))
        volume.SetAndObserveImageData(image)
        volume.SetIJKToRASMatrix(ijk_to_ras)
        imageSequence.SetDataNodeAtValue(volume, value)
        if sweep.valid[i]:
            transform.SetMatrixTransformToParent(vtkMatrixFromArray(
                T_RAS_LPS @ sweep.T_ref_image[i] @ T_RAS_LPS))
            transformSequence.SetDataNodeAtValue(transform, value)
    browser = scene.AddNewNodeByClass("vtkMRMLSequenceBrowserNode", uniqueName(scene, name))
    browser.SetAndObserveMasterSequenceNodeID(imageSequence.GetID())
    browser.AddSynchronizedSequenceNodeID(transformSequence.GetID())
    sequencesLogic.UpdateProxyNodesFromSequences(browser)
    proxyImage = browser.GetProxyNode(imageSequence)
    proxyTransform = browser.GetProxyNode(transformSequence)
    if proxyImage is not None and proxyTransform is not None:
        proxyImage.SetAndObserveTransformNodeID(proxyTransform.GetID())
    return browser


def _holds(sequence, className: str) -> bool:
    item = sequence.GetNthDataNode(0) if sequence.GetNumberOfDataNodes() else None
    return item is not None and item.IsA(className)


def _names(nodes) -> str:
    return ", ".join(f"'{node.GetName()}'" for node in nodes)


def _toParent(transformNode) -> np.ndarray:
    matrix = vtk.vtkMatrix4x4()
    transformNode.GetMatrixTransformToParent(matrix)
    return arrayFromVtkMatrix(matrix)


def _frameArray(volume, sequenceName: str, index: int) -> np.ndarray:
    """``(H, W)`` or ``(H, W, C)`` pixels of a 2D frame volume (row = IJK ``j``)."""
    image = volume.GetImageData()
    if image is None or image.GetPointData().GetScalars() is None:
        raise ComRegError(f"Frame {index} of '{sequenceName}' has no image.",
                          "Record or load the sweep again.")
    W, H, depth = image.GetDimensions()
    if depth != 1:
        raise ComRegError(f"'{sequenceName}' holds 3D volumes ({W} x {H} x {depth}), not 2D "
                          "ultrasound frames.", "Pick the sequence of the 2D frames.")
    scalars = numpy_support.vtk_to_numpy(image.GetPointData().GetScalars())
    components = image.GetNumberOfScalarComponents()
    return scalars.reshape((H, W, components) if components > 1 else (H, W))


def _referenceName(transformSequence) -> str:
    """"Reference" from "ImageToReference" (SlicerIGT naming), else "Reference"."""
    match = re.search(r"To([A-Za-z0-9]+)", transformSequence.GetName() or "") \
        if transformSequence is not None else None
    return match.group(1) if match else "Reference"


# --------------------------------------------------------------------------------------------
# Points and segmentations
# --------------------------------------------------------------------------------------------

def requirePointsNode(node):
    """``node`` if it is a model or markups node, else a :class:`ComRegError` naming it."""
    if hasattr(node, "IsA") and any(node.IsA(c) for c in POINTS_NODE_CLASSES):
        return node
    return requireNode(node, "vtkMRMLModelNode", "US points",
                       "Pick the US bone points: a model or markups node.")


def arrayFromPointsNode(node) -> np.ndarray:
    """``(N, 3)`` float64 RAS points of a model (its vertices) or markups node (its control
    points), in the node's own frame (without its parent transform)."""
    requirePointsNode(node)
    if node.IsA("vtkMRMLMarkupsNode"):
        n = node.GetNumberOfControlPoints()
        if n == 0:
            raise ComRegError(f"The markups '{node.GetName()}' has no control points.",
                              "Place or load the bone points first.")
        points = np.empty((n, 3))
        for i in range(n):
            node.GetNthControlPointPosition(i, points[i])
        return points
    return arrayFromModelPoints(node)


def segmentationFromNode(segmentationNode, workDir: Optional[str] = None):
    """The :class:`comreg_core.io.Segmentation` of a segmentation node in the scene, written by
    Slicer's own ``.seg.nrrd`` writer into a temporary file and read by comreg_core (so the
    bone surface comes from the same extraction as a file's)."""
    from comreg_core.io import read_segmentation

    requireNode(segmentationNode, "vtkMRMLSegmentationNode", "CT segmentation",
                "Pick the CT bone segmentation.")
    if segmentationNode.GetSegmentation().GetNumberOfSegments() == 0:
        raise ComRegError(f"The segmentation '{segmentationNode.GetName()}' has no segments.",
                          "Segment the bone first (Segment Editor).")
    storage = slicer.vtkMRMLSegmentationStorageNode()
    with tempfile.TemporaryDirectory(prefix="comreg-seg-", dir=workDir) as folder:
        path = Path(folder) / "segmentation.seg.nrrd"
        storage.SetFileName(str(path))
        if not storage.WriteData(segmentationNode):
            raise ComRegError(f"3D Slicer could not write the segmentation "
                              f"'{segmentationNode.GetName()}' as a labelmap.",
                              "Make sure it has a binary labelmap representation.")
        return read_segmentation(path)


def volumeFromNode(volumeNode):
    """A scalar volume node (e.g. SlicerIGT's volume reconstruction) as a
    :class:`comreg_core.io.volumes.Volume`: voxels ``(I, J, K)`` and ``IJKToRAS`` (space RAS)."""
    from comreg_core.io.volumes import Volume

    requireNode(volumeNode, "vtkMRMLScalarVolumeNode", "reconstructed US volume")
    image = volumeNode.GetImageData()
    if image is None or image.GetPointData().GetScalars() is None:
        raise ComRegError(f"The volume node '{volumeNode.GetName()}' holds no image.",
                          "Reconstruct or load the volume again.")
    I, J, K = image.GetDimensions()
    scalars = numpy_support.vtk_to_numpy(image.GetPointData().GetScalars())
    if image.GetNumberOfScalarComponents() != 1:
        raise ComRegError(f"The volume node '{volumeNode.GetName()}' has "
                          f"{image.GetNumberOfScalarComponents()} components per voxel.",
                          "Pass a scalar (grey) ultrasound volume.")
    matrix = vtk.vtkMatrix4x4()
    volumeNode.GetIJKToRASMatrix(matrix)
    array = np.ascontiguousarray(scalars.reshape(K, J, I).transpose(2, 1, 0))
    return Volume(array, arrayFromVtkMatrix(matrix), "RAS")


# --------------------------------------------------------------------------------------------
# Prior: initial pose and landmarks
# --------------------------------------------------------------------------------------------

def markupsFromNode(node, what: str):
    """The placed control points of a markups point list as
    :class:`comreg_core.io.markups.Markups` (RAS, the node's own coordinates; labels,
    descriptions and their ``tol=5`` tolerances), points never placed left out."""
    from comreg_core.io.markups import Markups, description_tolerance

    requireNode(node, "vtkMRMLMarkupsFiducialNode", what,
                "Pick a markups point list with the landmarks.")
    defined = getattr(slicer.vtkMRMLMarkupsNode, "PositionDefined", None)
    labels, points, descriptions = [], [], []
    for i in range(node.GetNumberOfControlPoints()):
        if defined is not None and node.GetNthControlPointPositionStatus(i) != defined:
            continue
        position = np.zeros(3)
        node.GetNthControlPointPosition(i, position)
        labels.append(node.GetNthControlPointLabel(i).strip())
        points.append(position)
        descriptions.append(node.GetNthControlPointDescription(i) or "")
    if not labels:
        raise ComRegError(f"The {what} '{node.GetName()}' has no placed point.",
                          "Place the landmarks first.")
    source = f"node '{node.GetName()}'"
    return Markups(tuple(labels), np.array(points), "RAS", tuple(descriptions),
                   tuple(description_tolerance(d, source, lab)
                         for d, lab in zip(descriptions, labels)), source)


def priorFromNodes(initialTransformNode=None, ctLandmarksNode=None, usLandmarksNode=None, *,
                   maxDeg: float = 30.0, maxMm: float = 30.0,
                   landmarkToleranceMm: float = 10.0, parameters=None):
    """The pose search's :class:`~comreg_core.registration.search.priors.Prior` (LPS) of scene nodes,
    or None when neither an initial pose nor landmarks are given.

    ``initialTransformNode``: a linear transform node holding a rough ``T_ct_us`` the way the
    registration's output does (the US points placed under it land on the CT): its transform
    to world, RAS. ``ctLandmarksNode`` / ``usLandmarksNode``: markups point lists on the CT and
    in the US points' own frame (each node's coordinates without its parent transform), paired
    by label (:func:`comreg_core.register.inputs.match_landmarks`), tolerance
    ``landmarkToleranceMm`` unless a point's description says ``tol=5``. ``parameters``: the
    module's parameter node: nodes not given and the tolerances are its (``initialTransform``,
    ``ctLandmarks``, ``usLandmarks``, ``initialToleranceDeg``, ...).
    """
    from comreg_core.register.inputs import match_landmarks
    from comreg_core.registration.search.priors import Prior

    if parameters is not None:
        p = parameters
        pick = lambda node, default: default if node is None else node  # noqa: E731
        initialTransformNode = pick(initialTransformNode, p.initialTransform)
        ctLandmarksNode = pick(ctLandmarksNode, p.ctLandmarks)
        usLandmarksNode = pick(usLandmarksNode, p.usLandmarks)
        maxDeg, maxMm = p.initialToleranceDeg, p.initialToleranceMm
        landmarkToleranceMm = p.landmarkToleranceMm

    if (ctLandmarksNode is None) != (usLandmarksNode is None):
        raise ComRegError("Landmarks need both point lists: the CT's and the US data's.",
                          "Pick the CT landmarks and the US landmarks, or neither.")
    if initialTransformNode is None and ctLandmarksNode is None:
        return None
    T_init = None
    if initialTransformNode is not None:
        requireNode(initialTransformNode, "vtkMRMLLinearTransformNode", "initial pose",
                    "Pick a linear transform node (US -> CT), or none.")
        matrix = vtk.vtkMatrix4x4()
        initialTransformNode.GetMatrixTransformToWorld(matrix)
        T_init = T_RAS_LPS @ arrayFromVtkMatrix(matrix) @ T_RAS_LPS
    pairs = ()
    if ctLandmarksNode is not None:
        pairs = match_landmarks(markupsFromNode(ctLandmarksNode, "CT landmarks"),
                                markupsFromNode(usLandmarksNode, "US landmarks"),
                                default_tolerance_mm=landmarkToleranceMm, space="LPS")
    return Prior(T_init, maxDeg, maxMm, pairs, space="LPS",
                 init_file=None if initialTransformNode is None
                 else f"node '{initialTransformNode.GetName()}'")
