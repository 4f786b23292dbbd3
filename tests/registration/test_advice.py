"""The advice of an ambiguous result against known poses on the real fibula CT."""

import numpy as np
import pytest

from comreg_core.registration.search.advice import ambiguity_advice, end_names
from comreg_core.registration.search.search import rotation_about
from comreg_core.registration.geometry.surface import CTSurface
from tests.helpers import FIBULA_STL, assert_close


@pytest.fixture(scope="module")
def cloud(shared_data):
    return CTSurface(FIBULA_STL).cloud(20_000)


def test_end_names_follow_the_patient_axes():
    assert end_names(np.array([0.1, 0.2, 0.97])) == ("superior", "inferior")
    assert end_names(np.array([0.0, 0.0, -1.0])) == ("inferior", "superior")
    assert end_names(np.array([-0.9, 0.1, 0.1])) == ("right", "left")


def test_a_slide_along_the_bone_says_how_far_and_which_way(cloud):
    axis = cloud.axes[:, 0]
    centroid = cloud.centre + 40.0 * axis  # a sweep 40 mm from the centre along the axis
    slide = np.eye(4)
    slide[:3, 3] = -30.0 * axis
    advice = ambiguity_advice(np.eye(4), slide, centroid, cloud)
    assert_close(advice["slide_mm"], -30.0, atol=1e-9)
    assert_close(advice["turn_deg"], 0.0, atol=1e-6)
    assert_close(advice["lateral_mm"], 0.0, atol=1e-9)
    towards, nearer = end_names(-axis)[0], end_names(axis)[0]
    assert f"30 mm further towards the {towards} end" in advice["advice"]
    assert f"towards the {nearer} end" in advice["advice"]
    assert advice["other_at_percent"] < advice["at_percent_of_length"]


def test_a_turn_or_a_flip_says_so(cloud):
    centroid = cloud.centre
    turn = rotation_about(cloud.centre, cloud.axes[:, 0], np.radians(90.0))
    assert "turned 90 deg about the bone" in ambiguity_advice(np.eye(4), turn, centroid,
                                                             cloud)["advice"]
    flip = rotation_about(cloud.centre, cloud.axes[:, 1], np.pi)
    assert "flipped end to end" in ambiguity_advice(np.eye(4), flip, centroid, cloud)["advice"]
