"""The module's live mode (comreg_plugin.live) headless on real MRML nodes: frames of the real
fibula sweep arrive in an image node and a transform node as OpenIGTLink's connector updates
them (in the module's RAS convention of a shown sweep); each tick registers the grown sweep
(in a worker thread) into the output transform node and the status line, onto the pseudo ground
truth."""

from __future__ import annotations

import numpy as np
import pytest
import vtk
from vtk.util import numpy_support

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

from comreg_core.errors import ComRegError  # noqa: E402
from comreg_core.io.tracked_us import read_tracked_sweep  # noqa: E402
from comreg_core.transforms import T_RAS_LPS  # noqa: E402
from comreg_plugin.live import LiveRegistration  # noqa: E402
from comreg_plugin.scene_io import transformToParentRAS, vtkMatrixFromArray  # noqa: E402
from tests.helpers import FIBULA_STL, assert_close  # noqa: E402
from tests.live.conftest import cut_sweep  # noqa: E402


@pytest.fixture(scope="module")
def sweep16(shared_data, tmp_path_factory):
    return read_tracked_sweep(cut_sweep(tmp_path_factory.mktemp("live16"), 0, 16, step=3))


def _stream_frame(imageNode, poseNode, sweep, i):
    """Frame i into the nodes as the connector shows a PLUS stream in the module's convention:
    the pose first, then the image (which fires ImageDataModifiedEvent)."""
    poseNode.SetMatrixTransformToParent(vtkMatrixFromArray(
        T_RAS_LPS @ sweep.T_ref_image[i] @ T_RAS_LPS))
    imageNode.SetIJKToRASMatrix(vtkMatrixFromArray(T_RAS_LPS @ np.diag([*sweep.spacing, 1, 1])))
    H, W = sweep.image_shape
    image = vtk.vtkImageData()
    image.SetDimensions(W, H, 1)
    image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(
        np.ascontiguousarray(sweep.frames[i]).ravel(), deep=True,
        array_type=vtk.VTK_UNSIGNED_CHAR))
    imageNode.SetAndObserveImageData(image)


def test_live_mode_registers_the_incoming_frames(logic, sweep16):
    from comreg_core.demo import pseudo_ground_truth
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
    from comreg_core.surfaces.us import extract_us_surface

    ct = logic.loadBoneMesh(FIBULA_STL)
    imageNode = logic.scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Image")
    poseNode = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ImageToReference")
    logic.getParameterNode().method = "search"  # the pose search: no pretrained run needed
    live = LiveRegistration.fromNodeNames(logic, "Image", "ImageToReference")
    assert live.poseNode is poseNode and "waiting for frames in 'Image'" in live.status
    assert live.tick() is None  # nothing came yet
    updates = []
    for i in range(sweep16.n_frames):
        _stream_frame(imageNode, poseNode, sweep16, i)
        if i % 4 == 3:
            updates.append(live.tick(wait=True))
    while live.session.backlog:
        updates.append(live.tick(wait=True))
    updates = [u for u in updates if u is not None]
    assert updates and live.received == 16 and live.session.points.frames_used == 16
    last = updates[-1]
    assert last.frames_received == 16 and last.frames_used == 16

    # the points: extract-us's of the same frames (poses through the scene's RAS, exactly)
    expected = extract_us_surface(sweep16).points
    cloud = live.session.points.cloud()
    assert_close(cloud.points, expected.points, atol=1e-6, what="points (mm)")

    # the output node holds the last update in RAS, with its verdict and advice
    node = live.outputTransformNode
    assert logic.getParameterNode().outputTransform is node
    assert node.GetName() == "ReferenceToCT"
    assert_close(transformToParentRAS(node), T_RAS_LPS @ last.T_ct_us @ T_RAS_LPS, atol=1e-9)
    assert node.GetAttribute("ComReg.verdict") == last.verdict
    assert node.GetAttribute("ComReg.advice") == last.advice
    assert live.status == last.status_line() and "frames 16/16" in live.status
    T_truth = pseudo_ground_truth(expected.points, live.session.registrar.surface)
    assert translation_error_mm(last.T_ct_us, T_truth, cloud.points.mean(axis=0)) < 4.0
    assert rotation_error_deg(last.T_ct_us, T_truth) < 5.0
    assert ct is logic.getParameterNode().ctModel

    live.stop()  # no more frames taken
    _stream_frame(imageNode, poseNode, sweep16, 0)
    assert live.received == 16 and live.tick() is None


def test_live_mode_registers_off_the_gui_thread(logic, sweep16):
    """The timer's ticks do not wait for the registration: the updates run in another thread
    and are applied to the scene by a later tick, on the GUI thread; stopping applies the one
    under way."""
    import threading
    import time

    ct = logic.loadBoneMesh(FIBULA_STL)
    imageNode = logic.scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Image")
    poseNode = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ImageToReference")
    live = LiveRegistration(logic, imageNode, poseNode, ctModelNode=ct)
    ran_in, real_update = [], live.session.update

    def update(*args, **kwargs):  # the real update, noting its thread
        ran_in.append(threading.get_ident())
        return real_update(*args, **kwargs)

    live.session.update = update
    applied, deadline = [], time.monotonic() + 120.0
    for i in range(sweep16.n_frames):
        _stream_frame(imageNode, poseNode, sweep16, i)
        applied.append(live.tick())
    while (live.busy or live.session.backlog or live._frames) and time.monotonic() < deadline:
        applied.append(live.tick())
        time.sleep(0.02)
    applied = [u for u in applied if u is not None]
    assert ran_in and threading.get_ident() not in ran_in
    assert not live.busy and live.session.points.frames_used == 16
    assert [id(u) for u in applied] == [id(u) for u in live.session.updates]  # each once
    last = live.session.updates[-1]
    live.stop()
    assert_close(transformToParentRAS(live.outputTransformNode),
                 T_RAS_LPS @ last.T_ct_us @ T_RAS_LPS, atol=1e-9)
    assert live.status == last.status_line()


def test_live_mode_refuses_missing_nodes_and_takes_the_parent_transform(logic, sweep16):
    with pytest.raises(ComRegError, match="no node 'Image'"):
        LiveRegistration.fromNodeNames(logic, "Image", "ImageToReference")
    imageNode = logic.scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Image")
    with pytest.raises(ComRegError, match="image pose"):
        LiveRegistration(logic, imageNode, None, ctModelNode=None)
    poseNode = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ImageToReference")
    imageNode.SetAndObserveTransformNodeID(poseNode.GetID())
    with pytest.raises(ComRegError, match="needs the CT bone model"):
        LiveRegistration(logic, imageNode)
    ct = logic.loadBoneMesh(FIBULA_STL)
    live = LiveRegistration(logic, imageNode, ctModelNode=ct)
    assert live.poseNode is poseNode
    sheared = np.diag([1.0, 1.0, 1.0, 1.0])
    sheared[0, 1] = 0.5
    _stream_frame(imageNode, poseNode, sweep16, 0)
    poseNode.SetMatrixTransformToParent(vtkMatrixFromArray(sheared))
    imageNode.GetImageData().Modified()
    imageNode.SetAndObserveImageData(imageNode.GetImageData())
    assert live.received >= 2 and any("right angles" in note for note in live.notes)
    live.stop()
