"""Principal-axis camera presets, orientation letters and parallel-projection framing (no
rendering here; the projection is checked against VTK in test_scenes.py)."""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.io.meshes import SurfaceMesh
from comreg_core.report.cameras import (CONTENT_BOX, bone_frame, frame_points,
                                        patient_directions, view_presets)
from tests.helpers import assert_close

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])


def _angle_deg(a, b):
    cos = abs(float(np.dot(a, b))) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(min(1.0, cos))))


def _cylinder(direction, *, height=200.0, radius=10.0, center=(10.0, -20.0, 300.0)):
    import pyvista as pv

    mesh = pv.Cylinder(center=center, direction=direction, radius=radius, height=height,
                       resolution=64, capping=True).triangulate()
    return SurfaceMesh.from_polydata(mesh, "LPS")


def test_patient_directions():
    lps, ras = patient_directions("LPS"), patient_directions("RAS")
    assert_close(lps["left"], [1, 0, 0])
    assert_close(lps["anterior"], [0, -1, 0])
    assert_close(ras["left"], [-1, 0, 0])
    assert_close(ras["anterior"], [0, 1, 0])
    assert_close(lps["superior"], [0, 0, 1])
    assert_close(ras["superior"], [0, 0, 1])


def test_fibula_frame_matches_a_naive_pca_of_surface_samples(fibula):
    from comreg_core.registration.geometry.surface import CTSurface

    frame = bone_frame(fibula.vertices, fibula.faces, fibula.space)
    # Naive reference: mean and covariance of 200k area-uniform surface samples.
    samples, _ = CTSurface(fibula, sample_seed=1).samples(200_000)
    center = samples.mean(axis=0)
    values, vectors = np.linalg.eigh(np.cov(samples.T))
    assert_close(frame.center, center, atol=0.5, what="centroid (mm)")
    assert _angle_deg(frame.axis, vectors[:, -1]) < 0.5
    assert_close(frame.variances, values[::-1], rtol=0.02, what="principal variances")
    # The fibula runs superior-inferior in this CT; anterior/left are the patient's.
    patient = patient_directions("LPS")
    assert frame.long_axis_from_pca
    assert frame.axis @ patient["superior"] > 0.95
    assert frame.anterior @ patient["anterior"] > 0.95
    assert frame.left @ patient["left"] > 0.95
    basis = np.stack([frame.axis, frame.anterior, frame.left])
    assert_close(basis @ basis.T, np.eye(3), atol=1e-12, what="orthonormal")
    assert_close(np.cross(frame.axis, frame.anterior), frame.left, atol=1e-12)


def test_oblique_long_bone_axis_is_found_and_points_superior():
    direction = np.array([0.3, 0.4, -0.866])  # downwards: the frame must flip it to superior
    mesh = _cylinder(direction)
    frame = bone_frame(mesh.vertices, mesh.faces, "LPS")
    assert _angle_deg(frame.axis, direction) < 0.5
    assert frame.axis[2] > 0
    assert abs(frame.anterior @ frame.axis) < 1e-12
    assert frame.anterior @ patient_directions("LPS")["anterior"] > 0


def test_bone_along_the_anterior_axis_still_gets_an_orthonormal_frame():
    mesh = _cylinder([0.0, 1.0, 0.05], radius=8.0)
    frame = bone_frame(mesh.vertices, mesh.faces, "LPS")
    basis = np.stack([frame.axis, frame.anterior, frame.left])
    assert_close(basis @ basis.T, np.eye(3), atol=1e-9, what="orthonormal")


def test_round_bone_uses_the_patient_superior_axis():
    import pyvista as pv

    sphere = SurfaceMesh.from_polydata(pv.Sphere(radius=20, theta_resolution=40,
                                                 phi_resolution=40), "RAS")
    frame = bone_frame(sphere.vertices, sphere.faces, "RAS")
    assert not frame.long_axis_from_pca
    assert_close(frame.axis, [0, 0, 1])
    assert_close(frame.anterior, [0, 1, 0], atol=1e-12)  # RAS: anterior is +y


def test_ras_frame_and_presets_are_the_lps_ones_mirrored(fibula):
    lps = bone_frame(fibula.vertices, fibula.faces, "LPS")
    ras_mesh = fibula.in_space("RAS")
    ras = bone_frame(ras_mesh.vertices, ras_mesh.faces, "RAS")
    for name in ("center", "axis", "anterior", "left"):
        assert_close(getattr(ras, name), LPS_TO_RAS @ getattr(lps, name), atol=1e-9, what=name)
    p_lps, p_ras = view_presets(lps), view_presets(ras)
    for view in p_lps:
        assert_close(p_ras[view].direction, LPS_TO_RAS @ p_lps[view].direction, atol=1e-9)
        assert_close(p_ras[view].view_up, LPS_TO_RAS @ p_lps[view].view_up, atol=1e-9)


@pytest.mark.parametrize("space", ["LPS", "RAS"])
def test_orientation_letters_of_each_preset(fibula, space):
    mesh = fibula.in_space(space)
    frame = bone_frame(mesh.vertices, mesh.faces, space)
    expected = {
        "anterior": {"right": "L", "left": "R", "top": "S", "bottom": "I"},
        "lateral": {"right": "P", "left": "A", "top": "S", "bottom": "I"},
        "bone_axis": {"right": "L", "left": "R", "top": "A", "bottom": "P"},
    }
    for view, preset in view_presets(frame).items():
        camera = frame_points(preset, mesh.vertices, (400, 300), space=space)
        assert camera.orientation_labels() == expected[view], view
    right_side = view_presets(frame, "right")["lateral"]
    labels = frame_points(right_side, mesh.vertices, (400, 300), space=space).orientation_labels()
    assert labels == {"right": "A", "left": "P", "top": "S", "bottom": "I"}


def test_oblique_edges_get_two_letters():
    from comreg_core.report.cameras import CameraView

    camera = CameraView("x", np.zeros(3), np.array([0.0, -10.0, 0.0]),  # from anterior (LPS)
                        np.array([0.0, 0.0, 1.0]), 10.0, (100, 100), "LPS")
    assert camera.orientation_labels()["right"] == "L"
    tilted = CameraView("x", np.zeros(3), np.array([-5.0, -10.0, 0.0]),
                        np.array([0.0, 0.0, 1.0]), 10.0, (100, 100), "LPS")
    assert tilted.orientation_labels()["right"] == "LA"


@pytest.mark.parametrize("window", [(320, 320), (640, 360), (300, 500)])
def test_framing_fits_the_points_tightly_into_the_content_box(fibula, window):
    frame = bone_frame(fibula.vertices, fibula.faces, "LPS")
    width, height = window
    x0, y0, x1, y1 = CONTENT_BOX
    margin = 0.04
    for preset in view_presets(frame).values():
        camera = frame_points(preset, fibula.vertices, window, margin=margin)
        px = camera.project(fibula.vertices)
        cols, rows_up = px[:, 0], height - px[:, 1]  # rows measured from the bottom like VTK
        assert cols.min() >= x0 * width - 1e-6 and cols.max() <= x1 * width + 1e-6
        assert rows_up.min() >= y0 * height - 1e-6 and rows_up.max() <= y1 * height + 1e-6
        # Tight: along one screen axis the points span the content box less its margins.
        fill_u = (cols.max() - cols.min()) / ((x1 - x0) * width)
        fill_v = (rows_up.max() - rows_up.min()) / ((y1 - y0) * height)
        assert max(fill_u, fill_v) == pytest.approx(1 / (1 + 2 * margin), rel=1e-9)
        # Centred in the content box.
        assert (cols.max() + cols.min()) / 2 == pytest.approx((x0 + x1) / 2 * width, abs=1e-6)
        assert (rows_up.max() + rows_up.min()) / 2 == pytest.approx((y0 + y1) / 2 * height,
                                                                   abs=1e-6)
        assert camera.mm_per_pixel > 0
