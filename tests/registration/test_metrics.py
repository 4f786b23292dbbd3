"""Metrics against independent computations: scipy rotations, an analytic box."""

import math

import numpy as np
import pytest
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from comreg_core.errors import ComRegError
from comreg_core.registration.geometry.metrics import (completion_metrics, is_flip, is_success,
                                                       registration_metrics, rotation_error_deg,
                                                       translation_error_mm)
from comreg_core.transforms import apply_transform, invert_rigid
from tests.helpers import BOX_CENTRE, assert_close, box_distance, random_rigid


def _rigid(rotvec_deg=(0, 0, 0), t=(0, 0, 0), about=(0, 0, 0)):
    R = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(about) - R @ np.asarray(about) + np.asarray(t)
    return T


# --- RRE ------------------------------------------------------------------------------------------

def test_rre_matches_scipy_relative_rotation_angle_for_random_poses():
    rng = np.random.default_rng(0)
    for _ in range(200):
        A, B = random_rigid(rng), random_rigid(rng)
        expected = np.degrees((Rotation.from_matrix(A[:3, :3]).inv()
                               * Rotation.from_matrix(B[:3, :3])).magnitude())
        assert_close(rotation_error_deg(A, B), expected, atol=1e-9, what="RRE")
        assert_close(rotation_error_deg(A[:3, :3], B[:3, :3]), expected, atol=1e-9, what="3x3")


@pytest.mark.parametrize("angle_deg", [0.0, 1e-7, 1e-4, 0.5, 1.999, 2.0, 45.0, 90.0, 135.0,
                                       179.0, 179.9999, 180.0])
def test_rre_exact_near_zero_and_near_180_degrees(angle_deg):
    rng = np.random.default_rng(int(angle_deg * 1000) % 2**32)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    base = random_rigid(rng)
    delta = _rigid(axis * angle_deg, about=rng.uniform(-50, 50, 3))
    got = rotation_error_deg(base @ delta, base)
    # absolute precision that arccos((tr - 1) / 2) cannot reach near 0 and 180 degrees
    assert_close(got, angle_deg, atol=1e-9, what=f"RRE of a {angle_deg} deg rotation")
    assert 0.0 <= got <= 180.0


def test_rre_is_symmetric_and_ignores_translation():
    A = _rigid([10, -20, 5], t=[100, 2, 3])
    B = _rigid([0, 0, 0], t=[-500, 7, 1])
    assert_close(rotation_error_deg(A, B), rotation_error_deg(B, A), atol=1e-12)
    assert_close(rotation_error_deg(A, B), np.linalg.norm([10, -20, 5]), atol=1e-9)


# --- RTE ------------------------------------------------------------------------------------------

def test_rte_is_the_displacement_of_the_reference_point():
    centroid = np.array([150.0, 300.0, 1300.0])
    truth = _rigid([5, 0, 0], t=[10, 20, 30], about=[1, 2, 3])
    # a pure translation error of (3, 4, 0) mm is 5 mm wherever it is measured
    shifted = _rigid(t=[3, 4, 0]) @ truth
    assert_close(translation_error_mm(shifted, truth, centroid), 5.0, atol=1e-9)
    assert_close(translation_error_mm(shifted, truth, np.zeros(3)), 5.0, atol=1e-9)
    # a 1 deg rotation error about the (mapped) centroid: 0 mm at the centroid, but the raw
    # matrix translations differ by |(R - I)(t - c')| (c' the centroid in the CT frame)
    mapped = apply_transform(truth, centroid[None])[0]
    turned = _rigid([0, 0, 1], about=mapped) @ truth
    assert_close(translation_error_mm(turned, truth, centroid), 0.0, atol=1e-9)
    R = Rotation.from_rotvec(np.radians([0, 0, 1])).as_matrix()
    expected_raw = np.linalg.norm((R - np.eye(3)) @ (truth[:3, 3] - mapped))
    assert_close(np.linalg.norm(turned[:3, 3] - truth[:3, 3]), expected_raw, rtol=1e-9)
    assert expected_raw > 4.0  # the frame-dependent figure RTE avoids


# --- success and flip -----------------------------------------------------------------------------

@pytest.mark.parametrize("rte, rre, success", [
    (0.0, 0.0, True), (1.999, 1.999, True), (2.0, 0.0, False), (0.0, 2.0, False),
    (2.5, 0.5, False), (0.5, 2.5, False), (math.nan, 0.0, False), (0.0, math.nan, False)])
def test_success_needs_rte_below_2mm_and_rre_below_2deg(rte, rre, success):
    assert is_success(rte, rre) is success


@pytest.mark.parametrize("rre, flip", [(0.0, False), (90.0, False), (90.001, True),
                                       (179.9, True), (180.0, True), (math.nan, False)])
def test_flip_is_rre_above_90_degrees(rre, flip):
    assert is_flip(rre) is flip


# --- registration and completion metrics ----------------------------------------------------------

def test_registration_metrics_on_known_estimates(box_surface, box_cloud):
    rng = np.random.default_rng(5)
    T_us_ct = random_rigid(rng)  # the US frame: somewhere else
    us = apply_transform(T_us_ct, box_cloud)
    truth = invert_rigid(T_us_ct)
    exact = registration_metrics(truth, truth, us, box_surface)
    assert_close([exact["RTE_mm"], exact["RRE_deg"], exact["CD_mm"], exact["HD95_mm"]],
                 [0, 0, 0, 0], atol=1e-9)
    assert exact["success"] and not exact["flip"]
    # 0.5 mm outward along +z (CT frame): top-face points 0.5 mm off, side points stay on the
    # +x face except those pushed past its top edge
    up = _rigid(t=[0, 0, 0.5]) @ truth
    m = registration_metrics(up, truth, us, box_surface)
    d = box_distance(box_cloud + [0, 0, 0.5])
    assert_close(m["RTE_mm"], 0.5, atol=1e-9)
    assert_close(m["RRE_deg"], 0.0, atol=1e-6)
    assert_close(m["CD_mm"], d.mean(), atol=1e-9, what="CD = mean US->CT distance")
    assert_close(m["HD95_mm"], np.percentile(d, 95), atol=1e-9, what="HD95")
    assert m["success"]
    # 3 deg about the cloud's centroid: RTE 0, RRE 3, not a success
    c = box_cloud.mean(axis=0)
    turned = _rigid([3, 0, 0], about=c) @ truth
    m = registration_metrics(turned, truth, us, box_surface)
    assert_close([m["RTE_mm"], m["RRE_deg"]], [0.0, 3.0], atol=1e-9)
    d = box_distance(apply_transform(turned, us))
    assert_close(m["CD_mm"], d.mean(), atol=1e-9)
    assert not m["success"] and not m["flip"]
    # turned round about the long (x) axis: a flip
    flipped = _rigid([180, 0, 0], about=c) @ truth
    m = registration_metrics(flipped, truth, us, box_surface)
    assert_close(m["RRE_deg"], 180.0, atol=1e-9)
    assert m["flip"] and not m["success"]


def test_completion_metrics_against_ground_truth_in_the_same_pose(box_surface):
    rng = np.random.default_rng(8)
    T_us_ct = random_rigid(rng)
    truth = invert_rigid(T_us_ct)
    ct_samples, _ = box_surface.samples(4000)
    # a perfect completion (the very CT samples, in the US pose): 0 both ways
    perfect = completion_metrics(apply_transform(T_us_ct, ct_samples), truth, box_surface,
                                 n_ct_samples=4000)
    assert_close(list(perfect.values()), [0.0, 0.0], atol=1e-9)
    # a completion that is only part of the box, 1 mm too high: recompute both directions
    part = ct_samples[ct_samples[:, 0] > BOX_CENTRE[0]] + [0, 0, 1.0]
    m = completion_metrics(apply_transform(T_us_ct, part), truth, box_surface, n_ct_samples=4000)
    d1 = box_distance(part)
    d2 = cdist(ct_samples, part).min(axis=1)
    assert_close(m["completion_CD_mm"], (d1.mean() + d2.mean()) / 2, atol=1e-9)
    assert_close(m["completion_HD95_mm"], np.percentile(np.concatenate([d1, d2]), 95), atol=1e-9)


@pytest.mark.parametrize("points, match", [
    (np.zeros((0, 3)), "empty"),
    (np.array([[0.0, 0, np.nan]]), "non-finite"),
    (np.array([[0.0, 0, np.inf], [1, 2, 3]]), "non-finite"),
    (np.zeros((5, 2)), "expected \\(N, 3\\)"),
])
def test_bad_clouds_raise_clear_errors(box_surface, points, match):
    with pytest.raises(ComRegError, match=match):
        registration_metrics(np.eye(4), np.eye(4), points, box_surface)
    with pytest.raises(ComRegError, match=match):
        completion_metrics(points, np.eye(4), box_surface)


def test_bad_transforms_and_meshes_raise_clear_errors(box_surface, box_cloud):
    scaled = np.diag([2.0, 2.0, 2.0, 1.0])
    with pytest.raises(ComRegError, match="not rigid"):
        registration_metrics(scaled, np.eye(4), box_cloud, box_surface)
    with pytest.raises(ComRegError, match="4x4"):
        rotation_error_deg(np.eye(4), np.full((4, 4), np.nan))
    with pytest.raises(ComRegError, match="expected \\(3, 3\\)"):
        rotation_error_deg(np.eye(2), np.eye(3))
    with pytest.raises(ComRegError, match="no triangles"):
        registration_metrics(np.eye(4), np.eye(4), box_cloud, (np.eye(3), np.zeros((0, 3))))
    with pytest.raises(ComRegError, match="does not exist"):
        registration_metrics(np.eye(4), np.eye(4), box_cloud, "/no/such/bone.stl")
    with pytest.raises(ComRegError, match="Cannot use a int"):
        registration_metrics(np.eye(4), np.eye(4), box_cloud, 3)
