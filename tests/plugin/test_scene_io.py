"""numpy <-> VTK / MRML helpers of the Slicer module (comreg_plugin.scene_io), headless on
slicer-core's real MRML nodes: matrices, polydata, model nodes, node type checks."""

from __future__ import annotations

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

import slicer  # noqa: E402

from comreg_core.errors import ComRegError  # noqa: E402
from comreg_core.transforms import T_RAS_LPS  # noqa: E402
from comreg_plugin.scene_io import (addModelNode, arrayFromModelPoints,  # noqa: E402
                                    arrayFromVtkMatrix, arraysFromModelMesh,
                                    polyDataFromArrays, requireNode, surfaceMeshFromModel,
                                    transformToParentRAS, uniqueName, vtkMatrixFromArray)
from tests.helpers import assert_close, random_rigid  # noqa: E402

TETRAHEDRON = (np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]]),
               np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))


@pytest.fixture
def scene():
    return slicer.vtkMRMLScene()


def test_matrices_round_trip_through_vtk_and_transform_nodes(scene):
    T = random_rigid(np.random.default_rng(0))
    assert np.array_equal(arrayFromVtkMatrix(vtkMatrixFromArray(T)), T)
    node = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "T")
    node.SetMatrixTransformToParent(vtkMatrixFromArray(T))
    assert np.array_equal(transformToParentRAS(node), T)


def test_polydata_of_points_or_triangles():
    vertices, faces = TETRAHEDRON
    points = polyDataFromArrays(vertices)
    assert points.GetNumberOfVerts() == 4 and points.GetNumberOfPolys() == 0
    mesh = polyDataFromArrays(vertices, faces)
    assert mesh.GetNumberOfVerts() == 0 and mesh.GetNumberOfPolys() == 4
    assert mesh.GetPoints().GetDataType() == 11  # VTK_DOUBLE: no float32 rounding


def test_model_nodes_hold_the_arrays(scene):
    vertices, faces = TETRAHEDRON
    mesh = addModelNode(scene, vertices, faces, "bone", (1.0, 0.5, 0.0))
    got_vertices, got_faces = arraysFromModelMesh(mesh)
    assert np.array_equal(got_vertices, vertices) and np.array_equal(got_faces, faces)
    assert mesh.GetDisplayNode().GetColor() == (1.0, 0.5, 0.0)

    points = addModelNode(scene, vertices, None, "points", (0.0, 0.0, 1.0), pointSize=5.0)
    display = points.GetDisplayNode()
    assert display.GetRepresentation() == display.PointsRepresentation
    assert display.GetPointSize() == 5.0
    again = addModelNode(scene, vertices[:2] + 1.0, None, "ignored", (0.0, 0.0, 1.0),
                         node=points)
    assert again is points and again.GetName() == "points"  # updated in place
    assert np.array_equal(arrayFromModelPoints(points), vertices[:2] + 1.0)
    with pytest.raises(ComRegError, match="no surface"):
        arraysFromModelMesh(points)


def test_unique_names(scene):
    assert uniqueName(scene, "bone") == "bone"
    addModelNode(scene, *TETRAHEDRON, "bone", (1.0, 1.0, 1.0))
    second = addModelNode(scene, *TETRAHEDRON, "bone", (1.0, 1.0, 1.0))
    assert second.GetName() != "bone" and second.GetName().startswith("bone")


def test_a_model_as_an_lps_surface_mesh(scene):
    vertices, faces = TETRAHEDRON
    node = addModelNode(scene, vertices, faces, "bone", (1.0, 1.0, 1.0))  # RAS
    mesh = surfaceMeshFromModel(node)
    assert mesh.space == "LPS"
    assert_close(mesh.vertices, vertices * np.diag(T_RAS_LPS)[:3], atol=0.0, what="LPS")
    assert np.array_equal(mesh.faces, faces)


def test_require_node_names_what_it_got(scene):
    model = scene.AddNewNodeByClass("vtkMRMLModelNode", "m")
    assert requireNode(model, "vtkMRMLModelNode", "model") is model
    with pytest.raises(ComRegError, match=r"The US points must be a model node "
                                          r"\(vtkMRMLModelNode\), but nothing was given"):
        requireNode(None, "vtkMRMLModelNode", "US points")
    transform = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "T")
    with pytest.raises(ComRegError, match="but the vtkMRMLLinearTransformNode 'T' was given"):
        requireNode(transform, "vtkMRMLModelNode", "CT bone model")
    with pytest.raises(ComRegError, match="must be a linear transform node.*but a str"):
        requireNode("T", "vtkMRMLLinearTransformNode", "transform")
    with pytest.raises(ComRegError, match="The volume must be vtkMRMLScalarVolumeNode, but the "
                                          "vtkMRMLModelNode 'm' was given"):
        requireNode(model, "vtkMRMLScalarVolumeNode", "volume")
