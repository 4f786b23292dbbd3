"""The verdict (comreg_core.registration.judgement.verdict, through the one judge): OK on correct
registrations, CHECK on a slide along the shaft, a 15 % scale error, a tie and points off the
bone; judged from points, transform and CT."""

import numpy as np
import pytest

from comreg_core.registration.geometry.icp import point_to_plane_icp
from comreg_core.registration.geometry.surface import CTSurface
from comreg_core.register.judge import Evidence, judge
from comreg_core.transforms import apply_transform
from tests.helpers import FIBULA_STL


def judge_registration(points, T, surface, *, short_sweep=False, scale_scan=True,
                       confidence=None):
    """The one judge's verdict with no search evidence but these."""
    evidence = Evidence(confidence=confidence, extent_share=0.1 if short_sweep else None)
    return judge(points, T, surface, evidence, scale_scan=scale_scan)


def _exact_icp(points, surface):
    """Point-to-plane ICP from the identity to the exact closest points (pairs within 5 mm)."""
    return point_to_plane_icp(points, np.eye(4), surface.matcher(5.0, n_samples=50_000),
                              iterations=100, tolerance_mm=1e-5).T


@pytest.fixture(scope="module")
def fibula():
    return CTSurface(FIBULA_STL)


@pytest.fixture(scope="module")
def axis(fibula):
    centred = fibula.vertices - fibula.vertices.mean(0)
    return np.linalg.svd(centred, full_matrices=False)[2][0]


@pytest.fixture(scope="module")
def real_sweep(shared_data, fibula):
    """The shared real fibula sweep's bone points and the pose a correct registration gives
    (exact ICP from the recorded tracking, as ComReg's final polish)."""
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import extract_us_surface

    points = extract_us_surface(read_tracked_sweep(
        shared_data / "ultrabones100k-fibula")).points.points
    return points, _exact_icp(points, fibula)


@pytest.fixture(scope="module")
def simulated_sweep(fibula):
    from comreg_core.simulation.bone import BoneModel
    from comreg_core.simulation.simulator import simulate_sweep

    bone = BoneModel((fibula.vertices, fibula.faces))
    return simulate_sweep(bone, rng=np.random.default_rng(100)).points


def slid(T, mm, axis):
    S = np.eye(4)
    S[:3, 3] = mm * axis
    return S @ T


def test_correct_registrations_are_ok(fibula, real_sweep, simulated_sweep):
    points, T = real_sweep
    real = judge_registration(points, T, fibula)
    assert real.verdict == "ok", real.reasons
    assert real.reasons == [] and real.headline == "Verdict: OK"
    sim = judge_registration(simulated_sweep, np.eye(4), fibula)
    assert sim.verdict == "ok", sim.reasons
    assert sim.figures["median_mm"] < 0.1 and sim.figures["within_2mm"] > 0.9


def test_slide_of_20_mm_along_the_shaft_is_check(fibula, axis, real_sweep, simulated_sweep):
    points, T = real_sweep
    for cloud, pose in ((points, T), (simulated_sweep, np.eye(4))):
        verdict = judge_registration(cloud, slid(pose, 20.0, axis), fibula)
        assert verdict.verdict == "check"
        assert any("better" in r and "mm away" in r for r in verdict.reasons), verdict.reasons


def test_scale_error_of_15_percent_is_check(fibula, real_sweep):
    """The US cloud 15 % too small (a calibration error), rigidly fitted as well as it goes."""
    points, T = real_sweep
    registered = apply_transform(T, points)
    centre = registered.mean(0)
    shrunk = centre + 0.85 * (registered - centre)
    T_fit = _exact_icp(shrunk, fibula)
    verdict = judge_registration(shrunk, T_fit, fibula)
    assert verdict.verdict == "check", verdict.figures
    assert verdict.figures["refit_scale"] > 1.06
    unscanned = judge_registration(shrunk, T_fit, fibula, scale_scan=False)  # live's warm updates
    assert not any("scaled by" in r for r in unscanned.reasons)
    assert unscanned.figures["refit_scale"] is None


def test_a_tie_is_check(fibula, simulated_sweep):
    verdict = judge_registration(simulated_sweep, np.eye(4), fibula, confidence=0.0)
    assert verdict.verdict == "check"
    assert verdict.to_json()["verdict"] == "check"
    assert any(r.startswith("Tie:") for r in verdict.to_json()["verdict_reasons"])


def test_points_off_the_bone_are_check(fibula, simulated_sweep):
    T = np.eye(4)
    T[:3, 3] = (0.0, 6.0, 0.0)  # 6 mm sideways: off the surface
    verdict = judge_registration(simulated_sweep, T, fibula)
    assert verdict.verdict == "check"
    assert any("lie off the CT bone" in r for r in verdict.reasons)


def test_a_short_sweep_skips_the_scale_scan_it_ignores(fibula, axis, real_sweep):
    """A short sweep (its best-fitting scale says nothing) is judged without the scale scan:
    every other figure as a long sweep's judgement of the same points, the same verdict but
    for the scale; a slide is still CHECK."""
    points, T = real_sweep
    short = points[:800]
    for pose in (T, slid(T, 20.0, axis)):
        skipped = judge_registration(short, pose, fibula, short_sweep=True)
        scanned = judge_registration(short, pose, fibula)
        assert skipped.figures["refit_scale"] is None and scanned.figures["refit_scale"] > 0
        assert skipped.reasons == [r for r in scanned.reasons if "scaled by" not in r]
        assert {k: v for k, v in skipped.figures.items() if not k.startswith("refit_scale")} \
            == {k: v for k, v in scanned.figures.items() if not k.startswith("refit_scale")}
    assert scanned.verdict == "check"  # the slide


def _turned_end_to_end(points, T, axis):
    """``T`` then a half turn about an axis across the shaft through the points' centroid."""
    from scipy.spatial.transform import Rotation

    centre = apply_transform(T, points).mean(0)
    across = np.cross(axis, [0.0, 0.0, 1.0])
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(np.pi * across / np.linalg.norm(across)).as_matrix()
    turn[:3, 3] = centre - turn[:3, :3] @ centre
    return turn @ T


def test_the_search_s_ambiguity_stands_unless_the_fit_rules_its_competitor_out(
        fibula, axis, real_sweep, simulated_sweep):
    """The search's ``ambiguous`` (a relative score margin) is CHECK unless the uncertainty
    weighs its clinically different competitor under RULED_OUT_WEIGHT: a whole simulated
    sweep against itself turned end to end is OK, the same flag with no competitor to weigh
    is CHECK, and a 800-point real slab against itself slid 8 mm stays CHECK: refitted, that
    pose settles in another basin along the shaft that fits about as well."""
    from comreg_core.registration.judgement.verdict import RULED_OUT_WEIGHT, ambiguity_words

    def judged(points, T, competitor):
        evidence = Evidence(confidence=0.2, ambiguous=True,
                            competitor=None if competitor is None else {"T_ct_us": competitor})
        return judge(points, T, fibula, evidence)

    flipped = judged(simulated_sweep, np.eye(4),
                     _turned_end_to_end(simulated_sweep, np.eye(4), axis))
    weight = flipped.uncertainty["competitor"]["weight"]
    assert flipped.verdict == "ok" and weight < RULED_OUT_WEIGHT, (flipped.reasons, weight)
    assert ambiguity_words(True, flipped.uncertainty["competitor"]).startswith("close in score")
    unweighed = judged(simulated_sweep, np.eye(4), None)
    assert unweighed.verdict == "check"
    assert any(r.startswith("Ambiguous pose") for r in unweighed.reasons), unweighed.reasons
    points, T = real_sweep
    slab = judged(points[:800], T, slid(T, 8.0, axis))
    weight = slab.uncertainty["competitor"]["weight"]
    assert weight > 0.1 and not slab.uncertainty["competitor"]["same_basin"], \
        slab.uncertainty["competitor"]
    assert any(r.startswith("Ambiguous pose") for r in slab.reasons), slab.reasons
    assert ambiguity_words(True, slab.uncertainty["competitor"]) == "YES: check the images"


def test_the_ambiguity_is_overruled_at_the_ok_line_s_odds_and_p_correct_decides(
        fibula, simulated_sweep):
    """The search's ``ambiguous`` stands while the refitted competitor weighs over 1/19 (then
    ``p_basin`` alone is under 0.95) and gives way at 1/19 or less, where ``p_correct``
    decides: the same whole simulated sweep at its truth, with one competitor record each side
    of the line (weights 0.0520 and 0.0533 around 0.0526), and at ``p_correct`` 0.90."""
    from dataclasses import replace

    from comreg_core.registration.judgement.assessment import pose_uncertainty
    from comreg_core.registration.judgement.verdict import (RULED_OUT_WEIGHT,
                                                            judge_registration as verdict_of)

    base = pose_uncertainty(simulated_sweep, np.eye(4), fibula, profiles=False, advice=False)

    def judged(weight, p_correct):
        competitor = {"delta_cost": -2.0 * np.log(weight), "weight": weight,
                      "same_basin": False}
        uncertainty = replace(base, competitor=competitor)
        return verdict_of(simulated_sweep, np.eye(4), fibula, uncertainty=uncertainty,
                          p_correct=p_correct, confidence=0.2, ambiguous=True)

    assert RULED_OUT_WEIGHT == pytest.approx(0.05 / 0.95, rel=1e-12)
    assert 0.0520 <= RULED_OUT_WEIGHT < 0.0533  # the two weights lie either side of the line
    heavier, lighter = judged(0.0533, 0.99), judged(0.0520, 0.99)
    assert any(r.startswith("Ambiguous pose") for r in heavier.reasons), heavier.reasons
    assert heavier.verdict == "check"
    assert lighter.verdict == "ok", lighter.reasons
    unsure = judged(0.0520, 0.90)
    assert unsure.verdict == "check"
    assert not any(r.startswith("Ambiguous pose") for r in unsure.reasons), unsure.reasons
