"""The module's live mode (comreg_plugin.live) headless on real MRML nodes: frames of the real
fibula sweep arrive in an image node and a transform node as OpenIGTLink's connector updates
them (in the module's RAS convention of a shown sweep); the session registers the grown sweep
in a second process (comreg_plugin.live_process) exactly as comreg live's session does in its
own, and each tick writes its newest update into the output transform node and the status line,
onto the pseudo ground truth."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

from comreg_core.errors import ComRegError  # noqa: E402
from comreg_core.io.tracked_us import read_tracked_sweep  # noqa: E402
from comreg_core.transforms import T_RAS_LPS  # noqa: E402
from comreg_plugin.live import LiveRegistration  # noqa: E402
from comreg_plugin.panel_testing import streamFrame  # noqa: E402
from comreg_plugin.scene_io import transformToParentRAS, vtkMatrixFromArray  # noqa: E402
from tests.helpers import FIBULA_STL, assert_close  # noqa: E402
from tests.live.conftest import cut_sweep  # noqa: E402


@pytest.fixture(scope="module")
def sweep16(shared_data, tmp_path_factory):
    return read_tracked_sweep(cut_sweep(tmp_path_factory.mktemp("live16"), 0, 16, step=3))


def _stream_frame(imageNode, poseNode, sweep, i):
    """Frame i into the nodes as the connector shows a PLUS stream (the module's own helper)."""
    streamFrame(imageNode, poseNode, sweep, i, vtkMatrixFromArray)


def test_live_mode_registers_the_incoming_frames(logic, sweep16):
    from comreg_core.demo import pseudo_ground_truth
    from comreg_core.live.session import LiveSession
    from comreg_core.register import Registrar
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
    from comreg_core.registration.geometry.surface import CTSurface
    from comreg_core.surfaces.us import extract_us_surface

    ct = logic.loadBoneMesh(FIBULA_STL)
    imageNode = logic.scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Image")
    poseNode = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ImageToReference")
    p = logic.getParameterNode()
    p.method = "search"  # the pose search: no pretrained run needed
    live = LiveRegistration.fromNodeNames(logic, "Image", "ImageToReference")
    assert live.poseNode is poseNode and "waiting for frames in 'Image'" in live.status
    assert live.tick() is None  # nothing came yet
    captured, capture = [], live.captureFrame
    live.captureFrame = lambda: captured.append(capture()) or captured[-1]
    updates = []
    for i in range(sweep16.n_frames):
        _stream_frame(imageNode, poseNode, sweep16, i)
        if i % 4 == 3:
            updates.append(live.tick(wait=True))
    updates = [u for u in updates if u is not None]
    assert updates and live.received == 16 and updates == live.updates
    assert live.processId is not None and live.processId != os.getpid()
    last = updates[-1]
    assert last.frames_received == 16 and last.frames_used == 16

    # comreg live's session in this process, given the same frames in the same batches,
    # gives the same registrations bit for bit
    session = LiveSession(Registrar.from_ct(FIBULA_STL), seed=0)
    session.warm_up()
    reference = [session.update(captured[k:k + 4], received=k + 4) for k in range(0, 16, 4)]
    reference = [u for u in reference if u is not None]
    assert [(u.verdict, u.mode, u.n_points) for u in updates] == \
        [(u.verdict, u.mode, u.n_points) for u in reference]
    for got, expected_update in zip(updates, reference):
        assert np.array_equal(got.T_ct_us, expected_update.T_ct_us)

    # the points: extract-us's of the same frames (poses through the scene's RAS, exactly)
    expected = extract_us_surface(sweep16).points
    assert_close(session.points.cloud().points, expected.points, atol=1e-6, what="points (mm)")
    assert last.n_points == len(expected.points)

    # the output node holds the last update in RAS, with its verdict and advice
    node = live.outputTransformNode
    assert logic.getParameterNode().outputTransform is node
    assert node.GetName() == "ReferenceToCT"
    assert_close(transformToParentRAS(node), T_RAS_LPS @ last.T_ct_us @ T_RAS_LPS, atol=1e-9)
    assert node.GetAttribute("ComReg.verdict") == last.verdict
    assert node.GetAttribute("ComReg.advice") == last.advice
    assert json.loads(node.GetAttribute("ComReg.verdict_reasons")) == last.reasons
    assert p.verdict == last.verdict and live.figures["advice"] == last.advice
    assert live.status == last.status_line() and "frames 16/16" in live.status
    T_truth = pseudo_ground_truth(expected.points, CTSurface(FIBULA_STL))
    assert translation_error_mm(last.T_ct_us, T_truth, expected.points.mean(axis=0)) < 4.0
    assert rotation_error_deg(last.T_ct_us, T_truth) < 5.0
    assert ct is logic.getParameterNode().ctModel

    live.stop()  # no more frames taken, the process gone
    assert not live.process.running
    _stream_frame(imageNode, poseNode, sweep16, 0)
    assert live.received == 16 and live.tick() is None


def test_live_mode_registers_in_another_process(logic, sweep16):
    """The timer's ticks do not wait for the registration: the session runs in a second
    process (its full searches in a third, as comreg live), and a later tick applies its newest
    answer to the scene; stopping applies the one under way."""
    import time

    ct = logic.loadBoneMesh(FIBULA_STL)
    imageNode = logic.scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Image")
    poseNode = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ImageToReference")
    live = LiveRegistration(logic, imageNode, poseNode, ctModelNode=ct, background=True)
    applied, deadline = [], time.monotonic() + 180.0
    for i in range(sweep16.n_frames):
        _stream_frame(imageNode, poseNode, sweep16, i)
        applied.append(live.tick())
    while (live.busy or live._frames) and time.monotonic() < deadline:
        applied.append(live.tick())
        time.sleep(0.02)
    applied = [u for u in applied if u is not None]
    assert live.processId is not None and live.processId != os.getpid()
    assert not live.busy and live.updates[-1].frames_used == 16
    assert applied and applied[-1] is live.updates[-1]
    assert all(u in live.updates for u in applied)
    last = live.updates[-1]
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
