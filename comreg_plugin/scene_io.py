"""numpy <-> VTK / MRML helpers of the ComReg module: matrices, polydata and model nodes, node
type checks, segmentation nodes, and the transform and scene files.

Coordinates: MRML nodes hold RAS (Slicer's convention); arrays are ``float64``, in millimetres;
files are written in LPS (``SPACE=LPS`` headers, ITK transforms), as 3D Slicer writes them.
Functions that make nodes take the ``vtkMRMLScene`` to make them in;
:class:`comreg_plugin.logic.ComRegLogic` passes its own.
"""

import logging
import re
from pathlib import Path
from typing import Optional

import numpy as np

from comreg_core.errors import ComRegError, CorruptFileError, UnsupportedFormatError
from comreg_core.io._files import (atomic_output, check_output_file, file_extension,
                                   require_input_file)
from comreg_core.transforms import space_change
from comreg_plugin.slicer_compat import require_slicer

slicer = require_slicer()
import vtk  # noqa: E402  (after the clear error above when slicer is missing)
from vtkmodules.util import numpy_support  # noqa: E402

log = logging.getLogger(__name__)

SCENE_EXTENSIONS = [".mrml"]
#: The ``<MRML version=...>`` header of scenes saved outside the 3D Slicer application, in the
#: "<application> <major>.<minor>.<patch> <revision>" form Slicer 5 writes (e.g. a scene saved by
#: Slicer 5.6.1 reads ``version="Slicer 5.6.1 32438"``). Slicer warns that a scene "may not load
#: correctly" when its application name is not "Slicer" or its version is newer than the running
#: one (qSlicerSceneReader); slicer-core's MRML would write "slicer-core 4.0.0 0". Version 5.0.0
#: is the oldest Slicer 5, so every Slicer 5 release opens the file without that warning; the
#: revision 0 says it is not a Slicer build. Inside the application the scene keeps its own.
HEADLESS_SCENE_VERSION = "Slicer 5.0.0 0"
# Data file extension per storable node class when saving a scene (Slicer's defaults, except
# models: .vtk, whose header carries SPACE=LPS).
_SCENE_FILE_EXTENSIONS = {
    "vtkMRMLSegmentationNode": ".seg.nrrd",
    "vtkMRMLModelNode": ".vtk",
    "vtkMRMLLinearTransformNode": ".h5",
    "vtkMRMLTransformNode": ".h5",
}


# --------------------------------------------------------------------------------------------
# numpy <-> VTK
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



def surfaceMeshFromModel(modelNode):
    """The triangle mesh of a model node as an LPS :class:`~comreg_core.io.SurfaceMesh` (mm)."""
    from comreg_core.io.meshes import SurfaceMesh

    vertices, faces = arraysFromModelMesh(modelNode)
    return SurfaceMesh(vertices, faces, "RAS").in_space("LPS")


# --------------------------------------------------------------------------------------------
# Nodes in a scene
# --------------------------------------------------------------------------------------------

def uniqueName(scene, name: str) -> str:
    """``name``, or a numbered variant of it when ``scene`` already holds a node of that name."""
    return scene.GenerateUniqueName(name) if scene.GetFirstNodeByName(name) else name


def addModelNode(scene, points_ras: np.ndarray, faces: Optional[np.ndarray], name: str, color,
                 pointSize: float = 3.0, node=None):
    """A model node (with display node) of RAS ``points_ras`` ``(N, 3)`` and triangles ``faces``
    ``(M, 3)``, or of vertices only (shown as points of ``pointSize`` pixels) when ``faces`` is
    None; ``color`` is RGB in 0..1; ``node`` is updated in place if given."""
    if node is not None:
        requireNode(node, "vtkMRMLModelNode", "node to update")
    polydata = polyDataFromArrays(points_ras, faces)
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLModelNode", uniqueName(scene, name))
    node.SetAndObservePolyData(polydata)
    if node.GetDisplayNode() is None:
        node.CreateDefaultDisplayNodes()
    display = node.GetDisplayNode()
    display.SetColor(*[float(c) for c in color])
    if faces is None:
        display.SetRepresentation(display.PointsRepresentation)
        display.SetPointSize(pointSize)
    return node


def readSlicerSegmentation(scene, path: Path, name: str):
    """A segmentation node read from a 3D Slicer ``.seg.nrrd`` by Slicer's own storage node."""
    segNode = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", uniqueName(scene, name))
    storage = scene.AddNewNodeByClass("vtkMRMLSegmentationStorageNode")
    storage.SetFileName(str(Path(path).resolve()))
    if not storage.ReadData(segNode):
        scene.RemoveNode(storage)
        scene.RemoveNode(segNode)
        raise CorruptFileError(path, "3D Slicer's segmentation reader rejected it")
    segNode.SetAndObserveStorageNodeID(storage.GetID())
    return segNode


def segmentationNodeFromArrays(scene, seg, name: str, defaultColor):
    """A segmentation node (binary labelmaps, RAS) built from a comreg_core ``Segmentation``;
    segments without a colour get ``defaultColor`` (RGB in 0..1)."""
    segNode = scene.AddNewNodeByClass("vtkMRMLSegmentationNode", uniqueName(scene, name))
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
            image, segment.name, [float(c) for c in (segment.color or defaultColor)])
    if image is not None:  # Slicer's writer wants the reference geometry
        segmentation = segNode.GetSegmentation()
        segmentation.SetConversionParameter(
            slicer.vtkSegmentationConverter.GetReferenceImageGeometryParameterName(),
            slicer.vtkSegmentationConverter.SerializeImageGeometry(image))
    return segNode


# --------------------------------------------------------------------------------------------
# Transform and scene files
# --------------------------------------------------------------------------------------------

def writeTransform(transformNode, path) -> Path:
    """Write a linear transform node as an ITK ``.tfm``/``.txt``/``.h5`` file, LPS, in ITK's
    resampling direction, exactly as 3D Slicer saves it (atomic write)."""
    from comreg_core.io import TRANSFORM_EXTENSIONS, save_transform
    from comreg_core.io._files import require_extension

    require_extension(path, "transform", TRANSFORM_EXTENSIONS)
    check_output_file(path, what="transform file")
    return save_transform(transformToParentRAS(transformNode), path, space="RAS")


def writeScene(scene, path) -> Path:
    """Save ``scene`` as a ``.mrml`` file with one data file per node beside it (written by
    the nodes' storage nodes: segmentations ``.seg.nrrd``, models ``.vtk`` with ``SPACE=LPS``,
    transforms ``.h5``), every file written atomically."""
    path = Path(path)
    if file_extension(path) not in SCENE_EXTENSIONS:
        raise UnsupportedFormatError(path, "scene", SCENE_EXTENSIONS)
    check_output_file(path, what="scene file")  # before any data file is written
    folder = path.resolve().parent
    folder.mkdir(parents=True, exist_ok=True)
    used: set = set()
    nodes = [scene.GetNthNodeByClass(i, "vtkMRMLStorableNode")
             for i in range(scene.GetNumberOfNodesByClass("vtkMRMLStorableNode"))]
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
    scene.SetRootDirectory(str(folder))
    scene.SetURL(str(path.resolve()))
    if sceneApplication(scene.GetVersion())[0] != "Slicer":  # headless: slicer-core's own name
        scene.SetVersion(HEADLESS_SCENE_VERSION)
    if scene.GetUserTagTable() is None:  # the application's scene has one: userTags=""
        scene.SetUserTagTable(slicer.vtkTagTable())
    scene.SetSaveToXMLString(1)  # the XML text, written atomically below
    try:
        ok = scene.Commit()
        xml = scene.GetSceneXMLString()
    finally:
        scene.SetSaveToXMLString(0)
    if not ok or not xml:
        raise ComRegError(f"3D Slicer's scene writer failed for '{path}'.",
                          "Check the log for the node it could not write.")
    with atomic_output(path) as tmp:
        tmp.write_text(xml, encoding="utf-8")
    log.info("Saved the scene to '%s' (%d data files)", path, len(used))
    return path


def sceneApplication(version: Optional[str]) -> tuple:
    """``(application, (major, minor, patch), revision)`` of a scene version string parsed by
    MRML's own ``vtkMRMLScene.ParseVersion``; ``("", (0, 0, 0), 0)`` when it does not parse."""
    parts = [vtk.reference(""), *(vtk.reference(0) for _ in range(4))]
    if not version or not slicer.vtkMRMLScene.ParseVersion(version, *parts):
        return "", (0, 0, 0), 0
    application, major, minor, patch, revision = (part.get() for part in parts)
    return application, (major, minor, patch), revision


def readScene(scene, path):
    """Replace ``scene``'s content with a saved ``.mrml`` scene (data files are read by their
    storage nodes). Returns the scene."""
    path = require_input_file(path, "scene file")
    if file_extension(path) not in SCENE_EXTENSIONS:
        raise UnsupportedFormatError(path, "scene", SCENE_EXTENSIONS)
    scene.SetURL(str(Path(path).resolve()))
    if not scene.Connect():
        raise CorruptFileError(path, f"3D Slicer could not load the scene "
                               f"(error code {scene.GetErrorCode()})")
    return scene
