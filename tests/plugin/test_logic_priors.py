"""The Slicer module's prior on real MRML nodes (headless slicer-core): an initial-pose transform
node and CT / US landmark point lists, taken from the parameter node, restrict the pose search;
the result's info records where it lies in them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

from comreg_core.errors import ComRegError  # noqa: E402
from comreg_core.registration.geometry.metrics import registration_metrics  # noqa: E402
from comreg_core.registration.search.search import rotation_about  # noqa: E402
from comreg_core.registration.geometry.surface import CTSurface  # noqa: E402
from comreg_core.transforms import T_RAS_LPS, apply_transform, invert_rigid  # noqa: E402
from comreg_plugin.scene_io import vtkMatrixFromArray  # noqa: E402
from tests.helpers import FIBULA_STL  # noqa: E402


def _points_node(logic, name, labels_points_ras):
    node = logic.scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", name)
    for label, point in labels_points_ras:
        node.AddControlPoint(np.asarray(point, float).tolist(), label)
    return node


def test_initial_pose_and_landmarks_from_the_scene_restrict_the_search(logic):
    ct = logic.loadBoneMesh(FIBULA_STL)  # LPS mesh -> RAS model
    surface = CTSurface(FIBULA_STL, sample_seed=11)
    points, _ = surface.samples(20_000)
    along = (points - surface.bbox_centre) @ np.array([0.0, 0.0, 1.0])
    patch = points[along > along.max() - 50.0][::4]  # 50 mm of the end, CT frame (LPS)
    T_us_ct = rotation_about(np.zeros(3), [0.2, -0.5, 0.8], math.radians(70.0))
    T_us_ct[:3, 3] = [30.0, -12.0, 80.0]
    truth = invert_rigid(T_us_ct)
    us_lps = apply_transform(T_us_ct, patch)
    us = logic.addPointsModel(us_lps, "LPS", "US points")
    # a rough initial pose 20 deg / 15 mm off, as a transform node (RAS, like the result)
    centre = patch.mean(axis=0)
    T_init = rotation_about(centre, [1.0, 1.0, 0.0], math.radians(20.0)) @ truth
    T_init[:3, 3] += [0.0, 9.0, 12.0]
    init = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "InitialPose")
    init.SetMatrixTransformToParent(vtkMatrixFromArray(T_RAS_LPS @ T_init @ T_RAS_LPS))
    # one landmark pair, picked 8 mm off on the CT (RAS in the scene)
    ras = np.diag([-1.0, -1.0, 1.0])
    k = len(patch) // 2
    ct_landmarks = _points_node(logic, "CT landmarks", [("tip", (patch[k] + [0, 0, 8]) @ ras)])
    us_landmarks = _points_node(logic, "US landmarks", [("tip", us_lps[k] @ ras),
                                                        ("later", (0.0, 0.0, 0.0))])
    us_landmarks.UnsetNthControlPointPosition(1)  # listed, never placed: left out
    p = logic.getParameterNode()
    p.initialTransform, p.ctLandmarks, p.usLandmarks = init, ct_landmarks, us_landmarks
    p.initialToleranceDeg, p.initialToleranceMm, p.landmarkToleranceMm = 30.0, 30.0, 12.0

    summary = logic.register(us, "search", ctModelNode=ct)
    errors = registration_metrics(summary.T_ct_us, truth, us_lps, FIBULA_STL)
    assert errors["RTE_mm"] < 2.0 and errors["RRE_deg"] < 2.0, errors
    record = summary.info["prior"]
    assert record["within"] and record["init_file"] == "node 'InitialPose'"
    assert abs(record["rotation_from_init_deg"] - 20.0) < 2.0
    assert abs(record["shift_from_init_mm"] - 15.0) < 2.0
    assert record["landmarks"][0]["label"] == "tip"
    assert abs(record["landmarks"][0]["error_mm"] - 8.0) < 2.0
    assert "prior" in summary.transformNode.GetAttribute("ComReg.info")

    # a method that cannot take a prior, and half a pair of landmark lists, are refused
    with pytest.raises(ComRegError, match="'ransac' method cannot use an initial pose"):
        logic.register(us, "ransac", ctModelNode=ct)
    p.usLandmarks = None
    with pytest.raises(ComRegError, match="both point lists"):
        logic.register(us, "search", ctModelNode=ct)


def test_the_live_mode_takes_the_scene_prior(logic):
    """The live mode's session keeps to the parameter node's prior: a landmark pair picked in
    the scene (RAS) goes to the session's process in LPS with its tolerance."""
    from comreg_plugin.live import LiveRegistration

    logic.loadBoneMesh(FIBULA_STL)
    imageNode = logic.scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Image")
    logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ImageToReference")
    imageNode.SetAndObserveTransformNodeID(
        logic.scene.GetFirstNodeByName("ImageToReference").GetID())
    p = logic.getParameterNode()
    p.method = "search"
    p.ctLandmarks = _points_node(logic, "CT landmarks", [("ankle", (10.0, 20.0, 30.0))])
    p.usLandmarks = _points_node(logic, "US landmarks", [("ankle", (-4.0, 5.0, 6.0))])
    p.landmarkToleranceMm = 12.0
    live = LiveRegistration.fromNodeNames(logic, "Image", "ImageToReference")
    (landmark,) = live.setup.prior.landmarks  # what the session's process is given
    np.testing.assert_allclose(landmark.ct, [-10.0, -20.0, 30.0])
    np.testing.assert_allclose(landmark.us, [4.0, -5.0, 6.0])
    assert landmark.tolerance_mm == 12.0 and live.setup.prior.T_init is None
    live.stop()
    p.ctLandmarks = p.usLandmarks = None
    live = LiveRegistration.fromNodeNames(logic, "Image", "ImageToReference")
    assert live.setup.prior is None
    live.stop()
