"""What the panel shows of a registration's record (issue 50), headless on real MRML nodes: the
lines of the verdict, uncertainty and where to scan (any record, including the keys the judge
adds: ``uncertainty``, ``scan_next``), the figures as node attributes, the US points coloured by
their exact distance to the CT with a legend, the competing pose (toggled), the patch to scan
next (against a naive selection of the CT's triangles)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

from comreg_core.io import read_points  # noqa: E402
from comreg_core.registration.geometry.surface import CTSurface  # noqa: E402
from comreg_core.report.style import colormap_rgb  # noqa: E402
from comreg_core.transforms import apply_transform, space_change  # noqa: E402
from comreg_plugin import result_views  # noqa: E402
from comreg_plugin.judged_registration import JudgedRegistration, showJudged  # noqa: E402
from comreg_plugin.scene_io import arrayFromModelPoints, arraysFromModelMesh  # noqa: E402
from comreg_plugin.verdict_record import (describeFigures, figuresFromNode,  # noqa: E402
                                          recordFigures, setFigureAttributes)

#: A record with the keys issue 48 adds (uncertainty, scan_next) besides comreg register's.
UNCERTAIN = {"verdict": "check", "verdict_reasons": ["The sweep covers too little bone."],
             "p_correct": 0.61, "search": {"confidence": 0.4, "ambiguous": False},
             "competitor": {"name": "pca+flip", "margin": 0.2, "distance_mm": 30.0,
                            "rotation_deg": 180.0},
             "uncertainty": {"bound_mm": 3.25, "noise_mm": 0.4, "directions": [
                 {"words": "about its axis", "bound_mm": 1.5, "bound_deg": 2.5},
                 {"words": "along the shaft", "bound_mm": 4.0, "bound_deg": 0.5}]},
             "scan_next": {"point_ct": [0.0, 0.0, 0.0], "normal_ct": [0.0, 0.0, 1.0],
                           "bound_mm": 1.8, "words": "scan the distal end"},
             "warnings": ["The verdict calibration was made for registrations with a prior of "
                          "kind 'none', this one has 'landmark'."]}


def test_the_lines_say_the_verdict_uncertainty_and_where_to_scan():
    lines = describeFigures(recordFigures(UNCERTAIN))
    assert lines[0] == "Verdict: CHECK"
    assert lines[1] == "  - The sweep covers too little bone."
    assert lines[2] == ("Warning: The verdict calibration was made for registrations with a "
                        "prior of kind 'none', this one has 'landmark'.")
    assert "p_correct 0.61, confidence 0.40" in lines
    assert ("Uncertainty: 95 % within 3.2 mm at the bone; weakest along the shaft (4.0 mm, "
            "0.5 deg)") in lines
    assert "Competing pose 'pca+flip': 30 mm, 180 deg away, margin 0.20" in lines
    assert lines[-1] == "Advice: scan the distal end"  # scan_next's words are the advice here
    assert describeFigures(recordFigures({}))[0].startswith("Verdict: none")


def test_the_figures_survive_node_attributes(logic):
    node = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "T")
    figures = recordFigures(UNCERTAIN, "/somewhere/registration-001")
    setFigureAttributes(node, figures)
    assert figuresFromNode(node) == {**figures, "advice": "scan the distal end"}
    assert node.GetAttribute("ComReg.p_correct") == repr(0.61)
    assert json.loads(node.GetAttribute("ComReg.uncertainty"))["bound_mm"] == 3.25
    setFigureAttributes(node, recordFigures({"verdict": "ok"}))  # nothing lingers
    assert figuresFromNode(node)["uncertainty"] is None
    assert figuresFromNode(node)["warnings"] == []  # none: nothing lingers
    assert node.GetAttribute("ComReg.scan_next") == ""


def _naive_patch(vertices, faces, point, radius):
    """The triangles whose three corners are within ``radius`` of ``point``, one at a time."""
    keep = []
    for face in faces:
        if all(np.sqrt(((vertices[i] - point) ** 2).sum()) <= radius for i in face):
            keep.append(vertices[face])
    return np.array(keep)


@pytest.fixture
def registered(logic, case):
    _, models = logic.loadSegmentation(case.segmentationPath)
    points = logic.loadUSPoints(case.usPointsPath)
    summary = logic.register(points, "search", ctModelNode=models[0])
    return summary, models[0], points


def test_points_are_coloured_by_their_exact_distance_to_the_ct(logic, case, registered):
    summary, ct, points = registered
    registered_lps = read_points(summary.resultFolder / "registered_us.ply").points
    expected = CTSurface((case.ctMesh.vertices, case.ctMesh.faces)).distance(registered_lps)
    from vtk.util import numpy_support

    array = points.GetPolyData().GetPointData().GetArray(result_views.DISTANCE_ARRAY)
    assert np.abs(numpy_support.vtk_to_numpy(array) - expected).max() < 1e-9
    display = points.GetDisplayNode()
    assert display.GetScalarVisibility() and display.GetScalarRange() == (0.0, 5.0)
    colors = logic.scene.GetNodeByID(display.GetColorNodeID())
    assert colors.GetNumberOfColors() == 256
    for k, t in ((0, 0.0), (255, 1.0)):
        rgba = [0.0] * 4
        colors.GetColor(k, rgba)
        # the table keeps 8 bits a channel
        assert np.abs(np.array(rgba[:3]) - colormap_rgb(np.array([t]))[0] / 255).max() <= 1 / 255
    legends = [points.GetNthDisplayNode(k) for k in range(points.GetNumberOfDisplayNodes())]
    assert any(n.IsA("vtkMRMLColorLegendDisplayNode") for n in legends)


def test_the_competing_pose_is_a_faint_model_that_can_be_hidden(logic, case, registered):
    summary, ct, points = registered
    competitor = result_views.roleNode(logic.scene, "competitor")
    assert competitor is not None and summary.record["competitor"]["name"] is not None
    T = np.array(json.loads(summary.transformNode.GetAttribute("ComReg.competitor_T_ct_us")))
    expected = apply_transform(space_change("LPS", "RAS") @ T, case.usPoints)
    assert np.abs(arrayFromModelPoints(competitor) - expected).max() < 1e-9
    # it puts the points' centroid where the record says
    centroid = apply_transform(space_change("RAS", "LPS"), expected).mean(axis=0)
    assert np.abs(centroid - summary.record["competitor"]["centroid_ct"]).max() < 1e-6
    assert competitor.GetDisplayNode().GetOpacity() < 0.5
    logic.setCompetitorVisible(False)
    assert not competitor.GetDisplayNode().GetVisibility()
    assert logic.getParameterNode().showCompetitor is False


def test_a_record_with_uncertainty_and_scan_next_is_shown(logic, registered):
    summary, ct, points = registered
    vertices, faces = arraysFromModelMesh(ct)
    centre_ras = vertices[np.argmax(vertices[:, 2])]  # the CT's top vertex
    record = {**summary.record, **UNCERTAIN, "scan_next": {
        **UNCERTAIN["scan_next"], "point_ct": (centre_ras * [-1, -1, 1]).tolist()}}
    judged = JudgedRegistration(_Result(summary.T_ct_us), record, summary.resultFolder,
                                recordFigures(record, str(summary.resultFolder)), _Registrar(),
                                "LPS")
    showJudged(logic.scene, judged, [points], summary.transformNode, ct)
    figures = figuresFromNode(summary.transformNode)
    assert figures["uncertainty_mm"] == 3.25 and figures["scan_next"] == record["scan_next"]
    patch = result_views.roleNode(logic.scene, "scan_next")
    got_vertices, got_faces = arraysFromModelMesh(patch)
    expected = _naive_patch(vertices, faces, centre_ras, result_views.SCAN_NEXT_RADIUS_MM)
    assert len(expected) > 0
    got = np.sort(got_vertices[got_faces].reshape(len(got_faces), -1), axis=0)
    assert np.array_equal(got, np.sort(expected.reshape(len(expected), -1), axis=0))
    without = {k: v for k, v in summary.record.items() if k != "scan_next"}
    showJudged(logic.scene, dataclasses.replace(judged, figures=recordFigures(without)),
               [points], summary.transformNode, ct)
    assert result_views.roleNode(logic.scene, "scan_next") is None  # gone with the key


class _Result:
    """A result holding only its pose (no search: no competitor pose)."""

    def __init__(self, T):
        self.T_ct_us, self.search = T, None


class _Registrar:
    """Distances of zero (the colouring is checked elsewhere)."""

    class surface:
        @staticmethod
        def distance(points):
            return np.zeros(len(points))


def test_the_scene_renders_off_screen_with_its_colours(logic, registered, tmp_path):
    """The headless scene's picture (the docs' screenshot): the bone's colour, the points'
    distance colours and the legend's top colour are in it."""
    from PIL import Image

    from comreg_plugin.scene_snapshot import SIZE, renderScene

    summary, ct, points = registered
    path = renderScene(logic.scene, tmp_path / "scene.png", fitNode=ct)
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert image.shape == (SIZE[1], SIZE[0], 3)

    def share_near(rgb, tolerance=12):
        return float((np.abs(image - np.asarray(rgb)).max(axis=-1) <= tolerance).mean())

    bone = (np.asarray(ct.GetDisplayNode().GetColor()) * 255).round()
    assert share_near(bone, 40) > 0.002  # the CT model (shaded; a thin bone)
    assert share_near(colormap_rgb(np.array([1.0]))[0]) > 0.0002  # the legend's 5 mm end
    assert share_near(colormap_rgb(np.array([0.0]))[0], 30) > 0.0005  # points on the bone
    assert path.stat().st_size < 300_000
