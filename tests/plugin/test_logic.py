"""The 3D Slicer module's Logic, headless on slicer-core's real MRML nodes: segmentation ->
bone models, tracked sweep -> US points, registration -> transform node (known synthetic
transform), transform files read back by Slicer, scene save/reload, background pretraining with
progress and cancel, and clear errors for bad inputs."""

from __future__ import annotations

import copy
import time

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

import slicer  # noqa: E402

from comreg_core.errors import (ComRegError, CorruptFileError,  # noqa: E402
                                InputFileNotFoundError, UnsupportedFormatError)
from comreg_core.io import (load_transform, read_mesh, read_segmentation,  # noqa: E402
                            read_tracked_sweep, write_volume)
from comreg_core.io.segmentations import Segmentation  # noqa: E402
from comreg_core.surfaces.ct import extract_bone_surface  # noqa: E402
from comreg_core.surfaces.us import extract_us_surface  # noqa: E402
from comreg_core.transforms import T_RAS_LPS, apply_transform  # noqa: E402
from comreg_plugin import testing  # noqa: E402
from comreg_plugin.logic import ComRegLogic  # noqa: E402
from comreg_plugin.registration import COMPLETED_BONE_NODE_NAME, TRANSFORM_NODE_NAME  # noqa: E402
from comreg_plugin.scene_io import (arrayFromModelPoints, arraysFromModelMesh,  # noqa: E402
                                    transformToParentRAS)
from tests.helpers import FIBULA_STL, assert_close  # noqa: E402
from tests.training.tiny import TINY  # noqa: E402

SAMPLE = testing.SAMPLE_SEGMENTATION
RAS = np.diag([-1.0, -1.0, 1.0])  # LPS <-> RAS on (N, 3) rows: x and y negated

# A pretraining small enough for a test: one 2-sample step, no validation (~15 s on 2 busy cores).
MICRO = copy.deepcopy(TINY)
MICRO["data"].update(workers=0, ct_points=256)
MICRO["training"].update(samples_per_epoch=2, batch_size=2, validation_every=0)
MICRO["simulation"]["n_points"] = 128
MICRO["model"]["completion"]["input_points"] = 128
MICRO["model"]["icp"]["num_points"] = 128


def _bounds(points):
    return np.concatenate([points.min(0), points.max(0)])


# --------------------------------------------------------------------------------------------
# CT: segmentation -> bone models, meshes
# --------------------------------------------------------------------------------------------

def test_seg_nrrd_becomes_a_segmentation_node_and_a_closed_bone_model(logic):
    segNode, models = logic.loadSegmentation(SAMPLE)
    assert segNode.IsA("vtkMRMLSegmentationNode")
    assert segNode.GetSegmentation().GetNumberOfSegments() == 1
    assert len(models) == 1 and models[0].IsA("vtkMRMLModelNode")
    assert models[0].GetName() == "fibula bone"
    assert models[0].GetDisplayNode() is not None and segNode.GetDisplayNode() is not None

    # the model is comreg_core's extraction, moved from LPS to the RAS scene
    reference = extract_bone_surface(read_segmentation(SAMPLE), name="fibula")
    assert reference.space == "LPS"
    vertices, faces = arraysFromModelMesh(models[0])
    assert vertices.shape == reference.vertices.shape == (22464, 3)
    assert_close(vertices, reference.vertices @ RAS, atol=1e-9, what="model vertices (RAS)")
    assert np.array_equal(faces, reference.faces)

    # and lies where 3D Slicer's own labelmap -> closed surface conversion puts the bone
    assert segNode.CreateClosedSurfaceRepresentation()
    import vtk
    from vtkmodules.util.numpy_support import vtk_to_numpy

    surface = vtk.vtkPolyData()
    segNode.GetClosedSurfaceRepresentation(segNode.GetSegmentation().GetNthSegmentID(0), surface)
    slicer_points = vtk_to_numpy(surface.GetPoints().GetData())
    assert_close(_bounds(vertices), _bounds(slicer_points), atol=0.8,  # one voxel
                 what="model bounds vs Slicer's closed surface (mm)")
    # x, y negative in RAS: the sample's bone lies at LPS x in [15, 64] mm
    assert vertices[:, 0].max() < 0

    p = logic.getParameterNode()
    assert p.segmentation is segNode and p.ctModel is models[0]


def test_label_map_with_two_labels_gives_one_model_per_segment(logic, tmp_path):
    seg = read_segmentation(SAMPLE)
    labels = seg.layers[0].astype(np.uint8)
    k_mid = labels.shape[2] // 2
    labels[:, :, k_mid:] *= 2  # the distal half becomes label 2
    volume = seg.geometry(labels)
    path = write_volume(volume, tmp_path / "labels.nrrd")

    segNode, models = logic.loadSegmentation(path)
    assert segNode.GetSegmentation().GetNumberOfSegments() == 2
    assert len(models) == 2
    two = Segmentation.from_labelmap(volume)
    for model, segment in zip(models, two.segments):
        reference = extract_bone_surface(two, segment=segment)
        vertices, _ = arraysFromModelMesh(model)
        assert vertices.shape == reference.vertices.shape
        assert_close(vertices, reference.vertices @ RAS, atol=1e-9, what=segment.name)
    # the segmentation node built from the label map sits where Slicer's reader puts the
    # .seg.nrrd: compare Slicer's closed surfaces of both
    ref_node, _ = ComRegLogic().loadSegmentation(SAMPLE, segmentNames=[])
    import vtk
    from vtkmodules.util.numpy_support import vtk_to_numpy

    def surface_bounds(node):
        node.CreateClosedSurfaceRepresentation()
        pts = []
        for i in range(node.GetSegmentation().GetNumberOfSegments()):
            pd = vtk.vtkPolyData()
            node.GetClosedSurfaceRepresentation(node.GetSegmentation().GetNthSegmentID(i), pd)
            pts.append(vtk_to_numpy(pd.GetPoints().GetData()))
        return _bounds(np.concatenate(pts))

    assert_close(surface_bounds(segNode), surface_bounds(ref_node), atol=0.8,
                 what="label-map segmentation vs .seg.nrrd (Slicer closed surfaces)")


def test_bone_mesh_loads_directly_as_a_model(logic):
    model = logic.loadBoneMesh(FIBULA_STL)
    mesh = read_mesh(FIBULA_STL)  # no SPACE tag: LPS
    vertices, faces = arraysFromModelMesh(model)
    assert_close(vertices, mesh.vertices @ RAS, atol=1e-9, what="mesh vertices (RAS)")
    assert np.array_equal(faces, mesh.faces) and len(faces) == 44194
    assert logic.getParameterNode().ctModel is model


# --------------------------------------------------------------------------------------------
# US: tracked sweep -> points
# --------------------------------------------------------------------------------------------

def test_tracked_sweep_becomes_us_points_on_the_bone(logic, small_sweep):
    node, result = logic.loadTrackedSweep(small_sweep)
    reference = extract_us_surface(read_tracked_sweep(small_sweep)).points.points  # LPS
    points = arrayFromModelPoints(node)
    assert len(points) == len(reference) == len(result.points.points) > 500
    assert node.GetPolyData().GetNumberOfVerts() == len(points)
    assert_close(points, reference @ RAS, atol=1e-9, what="US points (RAS)")
    assert logic.getParameterNode().usPoints is node

    # tracking and CT share one frame here (ground truth = identity): in the scene the points
    # lie on the CT bone model (a LPS/RAS mix-up would put them ~400 mm away)
    from comreg_core.registration.geometry.surface import CTSurface

    bone = logic.loadBoneMesh(FIBULA_STL)
    d = CTSurface(arraysFromModelMesh(bone)).distance(points)
    print(f"{len(points)} US points from {result.frames_total} frames: distance to the CT "
          f"model median {np.median(d):.2f} mm, 90th percentile {np.percentile(d, 90):.2f} mm")
    assert np.median(d) < 1.5 and np.percentile(d, 90) < 4.0, (np.median(d),
                                                                  np.percentile(d, 90))


def test_us_point_cloud_file_loads_as_points(logic, case):
    node = logic.loadUSPoints(case.usPointsPath)
    assert_close(arrayFromModelPoints(node), case.usPoints @ RAS, atol=1e-6,
                 what="US points (RAS)")


# --------------------------------------------------------------------------------------------
# Registration with a known transform, transform files, scene save/reload
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def registered(case):
    """Sample CT + the synthetic US points registered with the RANSAC + ICP baseline."""
    logic = ComRegLogic()
    _, models = logic.loadSegmentation(case.segmentationPath)
    us = logic.loadUSPoints(case.usPointsPath)
    summary = logic.register(us, "ransac", ctModelNode=models[0], seed=0)
    return logic, summary, us


def test_registration_recovers_the_known_transform(registered, case):
    logic, summary, us = registered
    node = summary.transformNode
    assert node.IsA("vtkMRMLLinearTransformNode") and node.GetName() == TRANSFORM_NODE_NAME
    assert us.GetParentTransformNode() is node  # US points under US->CT
    # to parent, RAS: the node's matrix = T_RAS_LPS @ T_ct_us(LPS) @ T_RAS_LPS
    T_node = transformToParentRAS(node)
    assert_close(T_node, T_RAS_LPS @ summary.T_ct_us @ T_RAS_LPS, atol=1e-12)
    errors = testing.poseErrors(T_RAS_LPS @ T_node @ T_RAS_LPS, case.T_ct_us, case.usPoints)
    print(f"RANSAC+ICP in the scene: translation error {errors['translation_mm']:.3f} mm, "
          f"rotation error {errors['rotation_deg']:.4f} deg, mean point error "
          f"{errors['mean_point_mm']:.3f} mm, max {errors['max_point_mm']:.3f} mm")
    assert errors["translation_mm"] < 2.0 and errors["rotation_deg"] < 2.0
    assert errors["max_point_mm"] < 2.0
    # the scene view: the US points moved by their parent transform land on the simulated
    # CT-frame points (RAS)
    moved = apply_transform(T_node, arrayFromModelPoints(us))
    assert np.abs(moved - case.usPointsCT @ RAS).max() < 2.0
    p = logic.getParameterNode()
    assert p.outputTransform is node and p.usPoints is us
    assert node.GetAttribute("ComReg.method") == "ransac"
    assert summary.completedBoneNode is None  # the baseline completes nothing


def test_search_registers_in_the_scene_without_a_network(case):
    """The pose search alone on the CT model recovers the known transform too; no completed
    bone, and its confidence reaches the parameter node."""
    logic = ComRegLogic()
    logic.loadSegmentation(case.segmentationPath)
    us = logic.loadUSPoints(case.usPointsPath)
    summary = logic.register(us, "search", seed=0)
    T_node = transformToParentRAS(summary.transformNode)
    errors = testing.poseErrors(T_RAS_LPS @ T_node @ T_RAS_LPS, case.T_ct_us, case.usPoints)
    assert errors["translation_mm"] < 2.0 and errors["rotation_deg"] < 2.0, errors
    assert summary.method == "search" and summary.completedBoneNode is None
    assert summary.info["ambiguous"] is False
    assert logic.getParameterNode().confidence == summary.info["confidence"]


def test_transform_files_read_back_by_slicer_and_comreg(registered, tmp_path):
    logic, summary, _ = registered
    T_ras = transformToParentRAS(summary.transformNode)
    for ext in (".tfm", ".h5"):
        path = logic.saveTransform(summary.transformNode, tmp_path / f"us_to_ct{ext}")
        assert_close(testing.readTransformWithSlicer(path), T_ras, atol=1e-6,
                     what=f"Slicer reading ComReg's {ext}")
        assert_close(load_transform(path), summary.T_ct_us, atol=1e-6, what=f"LPS {ext}")
        assert_close(load_transform(path, space="RAS"), T_ras, atol=1e-6)
    # and the other way: Slicer's own writer, read by comreg_core
    storage = logic.scene.AddNewNodeByClass("vtkMRMLTransformStorageNode")
    for ext in (".tfm", ".h5"):
        storage.SetFileName(str(tmp_path / f"slicer{ext}"))
        assert storage.WriteData(summary.transformNode)
        assert_close(load_transform(tmp_path / f"slicer{ext}"), summary.T_ct_us, atol=1e-6,
                     what=f"comreg reading Slicer's {ext}")
    logic.scene.RemoveNode(storage)


def test_scene_saved_and_reloaded_with_the_same_nodes(registered, case, tmp_path):
    logic, summary, us = registered
    path = logic.saveScene(tmp_path / "scene" / "comreg.mrml")
    files = sorted(p.name for p in path.parent.iterdir())
    assert files == ["ReferenceToCT.h5", "US_bone_points.vtk", "comreg.mrml", "fibula.seg.nrrd",
                     "fibula_bone.vtk"]
    assert not list(path.parent.glob(".*"))  # no temporary files left
    with open(path.parent / "fibula_bone.vtk", "rb") as f:
        assert b"SPACE=LPS" in f.read(200)

    fresh = ComRegLogic(slicer.vtkMRMLScene())
    fresh.loadScene(path)
    expected = {"fibula": "vtkMRMLSegmentationNode", "fibula bone": "vtkMRMLModelNode",
                "US bone points": "vtkMRMLModelNode",
                TRANSFORM_NODE_NAME: "vtkMRMLLinearTransformNode"}
    assert testing.sceneSummary(logic.scene) == expected
    assert testing.sceneSummary(fresh.scene) == expected
    testing.checkScenesMatch(logic.scene, fresh.scene, atol=1e-6)
    node = fresh.scene.GetFirstNodeByName(TRANSFORM_NODE_NAME)
    assert_close(transformToParentRAS(node), transformToParentRAS(summary.transformNode),
                 atol=1e-6, what="reloaded transform")
    assert node.GetAttribute("ComReg.space") is None  # the node is RAS; no stale LPS label
    for key in ("ComReg.method", "ComReg.info", "ComReg.runtime_s"):
        assert node.GetAttribute(key) == summary.transformNode.GetAttribute(key)
    assert_close(arrayFromModelPoints(fresh.scene.GetFirstNodeByName("US bone points")),
                 arrayFromModelPoints(us), atol=1e-9)
    seg = fresh.scene.GetFirstNodeByName("fibula")
    assert seg.GetSegmentation().GetNumberOfSegments() == 1
    # the parameter node comes back with its references and values
    p, q = logic.getParameterNode(), fresh.getParameterNode()
    assert q.parameterNode.GetID() == p.parameterNode.GetID()
    assert q.outputTransform is node and q.usPoints.GetName() == "US bone points"
    assert q.ctModel.GetName() == "fibula bone" and q.segmentation is seg
    assert q.runtimeSeconds == pytest.approx(p.runtimeSeconds)
    errors = testing.checkRegistrationAccuracy(q.outputTransform, case)
    assert errors["translation_mm"] < 2.0


def test_ambiguous_confidence_and_completion_are_stored(logic, case):
    logic.loadSegmentation(SAMPLE)
    us = logic.loadUSPoints(case.usPointsPath)
    completion = case.usPointsCT[:100]

    def oracle(points):  # a method that knows the answer and reports extras
        assert_close(points, case.usPoints, atol=1e-6, what="points given to the method (LPS)")
        return {"T_ct_us": case.T_ct_us, "runtime_s": 0.5, "completion_ct": completion,
                "info": {"ambiguous": True, "confidence": 0.25}}

    summary = logic.register(us, oracle)
    node = summary.transformNode
    assert node.GetAttribute("ComReg.ambiguous") == "true"
    assert float(node.GetAttribute("ComReg.confidence")) == 0.25
    p = logic.getParameterNode()
    assert p.ambiguous is True and p.confidence == 0.25 and p.runtimeSeconds == 0.5
    assert node.GetAttribute("ComReg.verdict") == "" and p.verdict == ""  # not judged
    assert summary.record is None and summary.figures is None
    assert summary.completedBoneNode.GetName() == COMPLETED_BONE_NODE_NAME
    assert summary.completedBoneNode.GetParentTransformNode() is None  # CT frame
    assert_close(arrayFromModelPoints(summary.completedBoneNode), completion @ RAS, atol=1e-9)
    assert testing.checkRegistrationAccuracy(node, case)["max_point_mm"] < 1e-6
    # registering again updates the same nodes
    again = logic.register(us, oracle)
    assert again.transformNode is node and again.completedBoneNode is summary.completedBoneNode


# --------------------------------------------------------------------------------------------
# Pretraining in the background
# --------------------------------------------------------------------------------------------

def test_pretraining_runs_in_the_background_and_its_run_registers(logic, case, tmp_path):
    _, models = logic.loadSegmentation(SAMPLE)
    run = tmp_path / "run"
    job = logic.startPretraining(models[0], run, preset="cpu", epochs=1, maxMinutes=0,
                                 seed=0, device="cpu", config=MICRO)
    first = job.poll()
    assert first.state == "running" and logic.getParameterNode().pretrainingState == "running"
    seen = []
    status = job.wait(timeoutSeconds=300, intervalSeconds=0.25, callback=seen.append)
    assert status.state == "finished", (status.message, job.consolePath.read_text())
    progress = [s.progress for s in seen]
    assert progress == sorted(progress) and progress[-1] == 1.0
    assert status.epoch == 1 and status.totalEpochs == 1 and status.loss is not None
    assert status.returnCode == 0
    assert (run / "checkpoint.pt").is_file() and (run / "ct_bone.vtk").is_file()
    assert not job.temporaryFiles()
    polled = logic.pollPretraining()
    p = logic.getParameterNode()
    assert polled.state == "finished" and p.pretrainingState == "finished"
    assert p.pretrainingProgress == 1.0 and p.runDirectory == str(run.resolve())
    with pytest.raises(ComRegError, match="not running"):
        job.cancel()
    with pytest.raises(ComRegError, match="already holds a training run"):
        logic.startPretraining(models[0], run, epochs=1)

    # register with the run (a 1-step network: no accuracy expected, only the scene objects)
    us = logic.loadUSPoints(case.usPointsPath)
    summary = logic.register(us, "comreg", device="cpu")
    assert summary.method == "comreg" and summary.space == "LPS"
    assert us.GetParentTransformNode() is summary.transformNode
    T = transformToParentRAS(summary.transformNode)
    assert_close(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9, what="rigid")
    completed = summary.completedBoneNode
    registrar = logic.registrar(run, "cpu")
    assert completed.GetPolyData().GetNumberOfPoints() == \
        registrar.model.config.completion.dense_points
    assert completed.GetParentTransformNode() is None
    assert summary.transformNode.GetAttribute("ComReg.run") == "run"  # a name, not a path
    assert "residuals_mm" in summary.info


def test_pretraining_cancel_stops_it_and_leaves_no_half_written_checkpoint(logic, tmp_path):
    from comreg_core.training import load_checkpoint

    run = tmp_path / "run"
    job = logic.startPretraining(FIBULA_STL, run, preset="cpu", epochs=1000, maxMinutes=0,
                                 seed=0, device="cpu", config=MICRO)
    try:  # a failed assertion must not leave a 1000-epoch job running
        deadline = time.monotonic() + 120
        while not (run / "training_log.csv").is_file() and time.monotonic() < deadline:
            assert job.running, job.consolePath.read_text()
            time.sleep(0.2)
        assert job.running  # training (1000 epochs) is under way
        # what a kill in the middle of an atomic checkpoint write would leave behind
        leftover = run / ".checkpoint.pt.abc123.tmp.pt"
        leftover.write_bytes(b"half a checkpoint")
        assert leftover in job.temporaryFiles()  # beside, maybe, the job's own write in flight
        status = logic.cancelPretraining()
        assert status.state == "cancelled" and status.returnCode not in (None, 0)
        assert not job.running and logic.getParameterNode().pretrainingState == "cancelled"
        assert not job.temporaryFiles()
        assert not [p for p in run.iterdir() if ".tmp" in p.name]
        if (run / "checkpoint.pt").exists():  # the last complete one
            state = load_checkpoint(run)
            assert 0 <= state["epoch"] < 1000  # a complete checkpoint from before the cancel
        with pytest.raises(ComRegError, match="not running"):
            logic.cancelPretraining()
    finally:
        if job.running:
            job.cancel()


# --------------------------------------------------------------------------------------------
# Bad inputs
# --------------------------------------------------------------------------------------------

def test_bad_inputs_give_clear_errors(logic, tmp_path):
    missing = tmp_path / "missing.seg.nrrd"
    with pytest.raises(InputFileNotFoundError, match="does not exist"):
        logic.loadSegmentation(missing)
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(UnsupportedFormatError, match=r"\.seg\.nrrd"):
        logic.loadSegmentation(text)
    with pytest.raises(UnsupportedFormatError):
        logic.loadSegmentation(FIBULA_STL)  # a mesh is not a segmentation
    broken = tmp_path / "broken.seg.nrrd"
    broken.write_bytes(b"NRRD0004\ntype: nonsense\n\n")
    with pytest.raises(CorruptFileError):
        logic.loadSegmentation(broken)
    with pytest.raises(UnsupportedFormatError):
        logic.loadBoneMesh(SAMPLE)
    with pytest.raises(InputFileNotFoundError):
        logic.loadTrackedSweep(tmp_path / "no_sweep.igs.mha")
    with pytest.raises(UnsupportedFormatError):
        logic.loadUSPoints(SAMPLE)
    assert logic.scene.GetNumberOfNodesByClass("vtkMRMLModelNode") == 0  # nothing half-added

    with pytest.raises(ComRegError, match="no US points"):
        logic.register()
    us = logic.addPointsModel(np.random.default_rng(0).normal(size=(50, 3)) * 20, "LPS")
    with pytest.raises(ComRegError, match="No pretrained run folder"):
        logic.register(us, "comreg")
    with pytest.raises(ComRegError, match="No checkpoint"):
        logic.register(us, "comreg", runDirectory=tmp_path)
    with pytest.raises(ComRegError, match="needs the CT bone model"):
        logic.register(us, "ransac")
    with pytest.raises(ComRegError, match="Unknown registration method"):
        logic.register(us, "magic")

    with pytest.raises(ComRegError, match="nothing to cancel"):
        logic.cancelPretraining()
    with pytest.raises(ComRegError, match="No pretraining was started"):
        logic.pollPretraining()
    with pytest.raises(ComRegError, match="No CT bone model"):
        logic.startPretraining(None, tmp_path / "run")
    with pytest.raises(ComRegError, match="No run folder"):
        logic.startPretraining(FIBULA_STL, None)

    with pytest.raises(ComRegError, match="no linear transform"):
        logic.saveTransform(None, tmp_path / "t.tfm")
    node = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
    with pytest.raises(UnsupportedFormatError):
        logic.saveTransform(node, tmp_path / "t.mat")
    with pytest.raises(UnsupportedFormatError):
        logic.saveScene(tmp_path / "scene.txt")
    with pytest.raises(InputFileNotFoundError):
        logic.loadScene(tmp_path / "nothing.mrml")


def test_models_with_polygons_or_without_points(logic):
    import vtk

    cube = vtk.vtkCubeSource()
    cube.Update()
    node = logic.scene.AddNewNodeByClass("vtkMRMLModelNode", "cube")
    node.SetAndObservePolyData(cube.GetOutput())  # 6 quads
    vertices, faces = arraysFromModelMesh(node)
    assert faces.shape == (12, 3) and faces.max() < len(vertices)
    empty = logic.scene.AddNewNodeByClass("vtkMRMLModelNode", "empty")
    with pytest.raises(ComRegError, match="'empty' has no points"):
        logic.register(empty, lambda points: np.eye(4))
    points = logic.addPointsModel(np.zeros((3, 3)), "LPS", "points only")
    with pytest.raises(ComRegError, match="no surface"):
        logic.register(points, "ransac", ctModelNode=points)

