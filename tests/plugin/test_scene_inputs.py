"""Inputs from the scene, as SlicerIGT users hold them, headless on slicer-core: a tracked sweep
as a Sequence browser (volume sequence + ImageToReference transform sequence), bone points as a
model or markups node, the CT as a segmentation node; and the whole path the issue asks for:
Sequence sweep -> bone points -> registration -> an output transform node chosen by the caller
-> scene saved -> reloaded, with a header and node classes as 3D Slicer 5 writes them."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

import slicer  # noqa: E402

from comreg_core.errors import ComRegError  # noqa: E402
from comreg_core.register import Registrar  # noqa: E402
from comreg_core.io import read_mesh, read_tracked_sweep  # noqa: E402
from comreg_core.surfaces.us import extract_us_surface  # noqa: E402
from comreg_core.transforms import T_RAS_LPS, apply_transform, invert_rigid  # noqa: E402
from comreg_plugin import testing  # noqa: E402
from comreg_plugin.logic import ComRegLogic  # noqa: E402
from comreg_plugin.scene_inputs import (addSweepBrowser, arrayFromPointsNode,  # noqa: E402
                                        trackedSweepFromBrowser)
from comreg_plugin.scene_io import arraysFromModelMesh, transformToParentRAS  # noqa: E402
from tests.helpers import FIBULA_STL, assert_close  # noqa: E402
from tests.plugin.test_scene_format import (SLICER5_RELEASES,  # noqa: E402
                                            scene_version_warnings)

RAS = np.diag([-1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def sweep(small_sweep):
    """The real fibula sweep (every 5th frame) with its poses moved out of the CT frame into a
    "Reference" frame by the known transform: T_ref_image = inv(T_ct_ref) @ T_ct_image."""
    original = read_tracked_sweep(small_sweep)
    T_ct_ref = testing.knownTransform(center=read_mesh(FIBULA_STL).vertices.mean(axis=0))
    moved = original.select(np.arange(original.n_frames))
    moved.T_ref_image = invert_rigid(T_ct_ref) @ original.T_ref_image
    moved.reference = "Reference"
    return original, moved, T_ct_ref


def test_a_sweep_becomes_a_sequence_browser_and_comes_back_unchanged(sweep):
    _, moved, _ = sweep
    logic = ComRegLogic()
    browser = addSweepBrowser(logic.scene, logic.sequencesLogic, moved)
    assert browser.IsA("vtkMRMLSequenceBrowserNode")
    assert browser.GetNumberOfSynchronizedSequenceNodes(True) == 2
    images = browser.GetMasterSequenceNode()
    assert images.GetName() == "Image" and images.GetNumberOfDataNodes() == moved.n_frames == 23
    # the proxy image sits under the proxy ImageToReference transform: a pixel lands where the
    # sweep says (LPS -> RAS), independently of the reader below
    proxyImage = browser.GetProxyNode(images)
    proxyTransform = proxyImage.GetParentTransformNode()
    assert proxyTransform.GetName() == "ImageToReference"
    import vtk

    ijk_to_ras = vtk.vtkMatrix4x4()
    proxyImage.GetIJKToRASMatrix(ijk_to_ras)
    H, W = moved.image_shape
    col, row = W - 1, H - 1
    world = transformToParentRAS(proxyTransform) @ \
        np.array(ijk_to_ras.MultiplyPoint([col, row, 0, 1]))
    i = browser.GetSelectedItemNumber()
    expected = moved.pixel_to_reference([i], [row], [col])[0] @ RAS
    assert_close(world[:3], expected, atol=1e-6, what="pixel in the scene (RAS mm)")

    back = trackedSweepFromBrowser(browser)
    assert np.array_equal(back.frames, moved.frames) and back.reference == "Reference"
    assert_close(back.spacing, moved.spacing, atol=1e-12, what="spacing")
    assert_close(back.T_ref_image, moved.T_ref_image, atol=1e-9, what="poses (LPS)")
    assert_close(back.timestamps, moved.timestamps, atol=1e-6, what="timestamps (s)")


def test_a_plus_recording_with_its_calibration_shown_as_a_sequence_keeps_every_pixel(
        shared_data):
    """A real PLUS recording (21 frames, ProbeToTracker + ReferenceToTracker + the device set's
    ImageToProbe) loaded through the panel's file route: the Sequence's frames and poses give
    back what comreg_core reads from the files, pixel corners within 1e-5 mm."""
    plus = shared_data / "plus"
    recording = plus / "TestImages" / "SpinePhantomFreehand.igs.mha"
    calibration = (plus / "ConfigFiles" / "Testing" /
                   "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml")
    reference = read_tracked_sweep(recording, calibration=calibration)
    logic = ComRegLogic()
    browser = logic.addSweepSequence(recording, calibration=calibration)
    assert logic.getParameterNode().sweep is browser
    back = trackedSweepFromBrowser(browser)
    assert back.n_frames == reference.n_frames == 21 and back.valid.all()
    assert np.array_equal(back.frames, reference.frames)
    assert_close(back.frame_corners(), reference.frame_corners(), atol=1e-5,
                 what="frame corners (LPS mm)")
    assert_close(back.timestamps, reference.timestamps, atol=1e-6, what="timestamps (s)")


def test_a_frame_without_a_recorded_pose_is_invalid(sweep):
    _, moved, _ = sweep
    part = moved.select(np.arange(4))
    part.valid[1] = False  # tracking lost: no ImageToReference item at this time
    logic = ComRegLogic()
    browser = addSweepBrowser(logic.scene, logic.sequencesLogic, part)
    images, poses = (browser.GetMasterSequenceNode(),
                     logic.scene.GetFirstNodeByName("ImageToReference"))
    assert (images.GetNumberOfDataNodes(), poses.GetNumberOfDataNodes()) == (4, 3)
    back = trackedSweepFromBrowser(browser)
    assert back.valid.tolist() == [True, False, True, True]
    assert np.isnan(back.T_ref_image[1]).all() and np.isfinite(back.timestamps).all()
    assert_close(back.T_ref_image[back.valid], part.T_ref_image[part.valid], atol=1e-9,
                 what="the other poses")


def test_sequence_sweep_to_points_to_registration_into_a_chosen_node_saved_and_reloaded(
        sweep, tmp_path):
    original, moved, T_ct_ref = sweep
    logic = ComRegLogic()
    ct = logic.loadBoneMesh(FIBULA_STL)
    browser = addSweepBrowser(logic.scene, logic.sequencesLogic, moved)

    # bone points from the Sequence = the library's points from the files, moved
    us, result = logic.usPointsFromSequence(browser)
    reference = apply_transform(invert_rigid(T_ct_ref),
                                extract_us_surface(original).points.points)
    points = arrayFromPointsNode(us)
    assert len(points) == len(reference) > 500
    assert_close(points, reference @ RAS, atol=1e-6, what="US points from the Sequence (RAS)")
    assert logic.getParameterNode().sweep is browser
    assert us.GetAttribute("ComReg.source") == browser.GetName()

    # registration into an output node the caller picked
    chosen = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "TrackerToCTChosen")
    summary = logic.register(us, "search", ctModelNode=ct, outputTransformNode=chosen, seed=0)
    assert summary.transformNode is chosen and chosen.GetName() == "TrackerToCTChosen"
    assert us.GetParentTransformNode() is chosen
    assert logic.scene.GetNumberOfNodesByClass("vtkMRMLLinearTransformNode") == 2  # + proxy
    # the same as the library on the same points, and near the known frame change (real
    # recording: the tracked pose itself is 1-3 mm off the CT)
    direct = Registrar.from_ct(read_mesh(FIBULA_STL)).register(points @ RAS, seed=0).T_ct_us
    assert_close(T_RAS_LPS @ transformToParentRAS(chosen) @ T_RAS_LPS, direct, atol=1e-6,
                 what="scene vs library registration")
    errors = testing.poseErrors(direct, T_ct_ref, reference)
    print(f"Sequence sweep ({moved.n_frames} frames, {len(points)} points) registered by the "
          f"search: {errors['translation_mm']:.2f} mm, {errors['rotation_deg']:.2f} deg from "
          f"the known transform (mean point {errors['mean_point_mm']:.2f} mm)")
    assert errors["mean_point_mm"] < 5.0 and errors["rotation_deg"] < 5.0, errors

    # saved and reloaded: Slicer 5's header, MRML's tags, the same nodes and matrices
    path = logic.saveScene(tmp_path / "scene" / "sweep.mrml")
    root = ET.parse(path).getroot()
    for running in SLICER5_RELEASES:
        assert scene_version_warnings(root.attrib["version"], running) == []
    fresh = ComRegLogic(slicer.vtkMRMLScene())
    fresh.loadScene(path)
    for element in root:
        node = fresh.scene.GetNodeByID(element.attrib["id"])
        assert fresh.scene.GetTagByClassName(node.GetClassName()) == element.tag
    tags = {element.tag for element in root}
    assert {"SequenceBrowser", "Sequence", "LinearTransform", "Model", "ScriptedModule"} <= tags
    # Slicer's .seq.mha reader renames a transform sequence it loads ("<file>-<name>-Seq"), as
    # it does inside the application; the sweep read back below is what matters
    testing.checkScenesMatch(logic.scene, fresh.scene, atol=1e-6,
                             ignoreClasses=("vtkMRMLSequenceNode",))
    reloaded = fresh.scene.GetFirstNodeByName("TrackerToCTChosen")
    assert fresh.getParameterNode().outputTransform is reloaded
    assert fresh.scene.GetFirstNodeByName(us.GetName()).GetParentTransformNode() is reloaded
    assert_close(transformToParentRAS(reloaded), transformToParentRAS(chosen), atol=1e-9,
                 what="reloaded output transform")
    again = trackedSweepFromBrowser(fresh.getParameterNode().sweep)
    assert np.array_equal(again.frames, moved.frames)
    assert_close(again.T_ref_image, moved.T_ref_image, atol=0.01,  # .seq.mha text precision
                 what="reloaded sweep poses (mm)")


def test_markups_points_register_like_a_model(logic, case):
    markups = logic.scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "bone points")
    subset = case.usPoints[::200] @ RAS
    for p in subset:
        markups.AddControlPoint(*p)
    assert_close(arrayFromPointsNode(markups), subset, atol=1e-9, what="markups points")

    def oracle(points):  # the truth, after checking the points the method receives (LPS)
        assert_close(points, case.usPoints[::200], atol=1e-9, what="LPS points")
        return case.T_ct_us

    summary = logic.register(markups, oracle)
    assert markups.GetParentTransformNode() is summary.transformNode
    assert summary.transformNode.GetName() == "ReferenceToCT"
    assert testing.checkRegistrationAccuracy(summary.transformNode, case)["max_point_mm"] < 1e-9


def test_a_segmentation_node_in_the_scene_gives_the_same_bone_model(logic):
    segNode, models = logic.loadSegmentation(testing.SAMPLE_SEGMENTATION)
    fromNode = logic.boneModelsFromSegmentation(segNode)
    assert len(fromNode) == 1 and logic.getParameterNode().ctModel is fromNode[0]
    (v1, f1), (v2, f2) = arraysFromModelMesh(models[0]), arraysFromModelMesh(fromNode[0])
    assert v2.shape == v1.shape == (22464, 3) and np.array_equal(f1, f2)
    assert_close(v2, v1, atol=1e-6, what="bone from the node vs from the file (RAS mm)")
    assert fromNode[0].GetAttribute("ComReg.source") == segNode.GetName()


def test_bad_scene_inputs_give_clear_errors(logic, sweep):
    _, moved, _ = sweep
    model = logic.addPointsModel(np.zeros((3, 3)), "LPS", "not a sweep")
    with pytest.raises(ComRegError, match="tracked US sweep must be .*SequenceBrowser.*"
                                          "'not a sweep'"):
        logic.usPointsFromSequence(model)
    empty = logic.scene.AddNewNodeByClass("vtkMRMLSequenceBrowserNode", "empty")
    with pytest.raises(ComRegError, match="'empty' holds no image sequence"):
        logic.usPointsFromSequence(empty)
    browser = addSweepBrowser(logic.scene, logic.sequencesLogic, moved.select(np.arange(3)))
    extra = logic.scene.AddNewNodeByClass("vtkMRMLSequenceNode", "StylusToReference")
    extra.SetDataNodeAtValue(slicer.vtkMRMLLinearTransformNode(), "0")
    browser.AddSynchronizedSequenceNodeID(extra.GetID())
    assert trackedSweepFromBrowser(browser).n_frames == 3  # ImageTo... is still picked
    import vtk

    nodes = vtk.vtkCollection()
    browser.GetSynchronizedSequenceNodes(nodes, False)  # the two transform sequences
    for i in range(nodes.GetNumberOfItems()):
        nodes.GetItemAsObject(i).SetName(f"Tool{i}ToTracker")
    with pytest.raises(ComRegError, match="several transform sequences.*Tool0ToTracker"):
        logic.usPointsFromSequence(browser)
    segNode = logic.scene.AddNewNodeByClass("vtkMRMLSegmentationNode", "blank")
    with pytest.raises(ComRegError, match="'blank' has no segments"):
        logic.boneModelsFromSegmentation(segNode)
    with pytest.raises(ComRegError, match="output transform must be a linear transform"):
        logic.register(model, lambda points: np.eye(4), outputTransformNode=model)
    with pytest.raises(ComRegError, match="completed bone output must be a model"):
        logic.register(model, lambda points: np.eye(4), completedBoneNode=segNode)
    assert model.GetParentTransformNode() is None  # refused before anything was made
    assert logic.scene.GetFirstNodeByName("ReferenceToCT") is None


def test_a_reconstructed_volume_node_gives_the_points_of_its_file(tmp_path):
    """PLUS's reconstructed spine-phantom volume as a scalar volume node (RAS, as Slicer loads
    an LPS file): the bone points equal those of the file path, mapped to RAS."""
    from comreg_core.io.volumes import read_volume
    from comreg_core.surfaces.us_volume import extract_volume_surface
    from tests.helpers import SHARED_DATA

    path = SHARED_DATA / "plus" / "TestImages" / "SpinePhantomFreehandReconstructed.mha"
    volume = read_volume(path)
    logic = ComRegLogic()
    node = logic.scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Reconstruction")
    import vtk
    from vtkmodules.util import numpy_support

    image = vtk.vtkImageData()
    image.SetDimensions(*volume.array.shape)
    flat = np.ascontiguousarray(volume.array.transpose(2, 1, 0)).ravel()
    image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(flat, deep=True))
    node.SetAndObserveImageData(image)
    matrix = vtk.vtkMatrix4x4()
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ volume.ijk_to_space  # LPS file -> RAS node
    for r in range(4):
        for c in range(4):
            matrix.SetElement(r, c, ras[r, c])
    node.SetIJKToRASMatrix(matrix)
    points_node, result = logic.usPointsFromVolume(node)
    expected, _ = extract_volume_surface(volume)
    assert len(result.points.points) == len(expected.points.points) >= 30
    assert_close(arrayFromPointsNode(points_node), expected.points.points @ RAS.T, atol=1e-6)
    assert logic.getParameterNode().usPoints is points_node
    assert logic.getParameterNode().usVolume is node
    with pytest.raises(ComRegError):
        logic.usPointsFromVolume(points_node)  # a model is not a volume
