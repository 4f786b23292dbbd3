"""The verdict's calibration: clinical sameness, the competitor, p_correct's fit and its
monotonicity, the calibration file, and the verdict that uses it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comreg_core.errors import ComRegError
from comreg_core.registration.judgement.calibration import (Calibration, clinical_competitor,
                                                            extent_share, fit_calibration,
                                                            pose_difference, reliability_table,
                                                            same_answer)
from comreg_core.registration.search.scoring import Candidate, SearchResult
from comreg_core.registration.judgement.verdict import judge_registration


def _pose(rotvec_deg=(0.0, 0.0, 0.0), shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = shift
    return T


@pytest.fixture()
def strip() -> np.ndarray:
    """A 50 mm strip of US points along x (mm)."""
    rng = np.random.default_rng(0)
    return np.column_stack([rng.uniform(-25, 25, 400), rng.uniform(-5, 5, 400),
                            rng.normal(0, 0.2, 400)])


def test_pose_difference_and_clinical_sameness_against_known_transforms(strip):
    distance, angle = pose_difference(np.eye(4), _pose(shift=(3.0, 0.0, 0.0)), strip)
    assert distance == pytest.approx(3.0, abs=1e-9) and angle == pytest.approx(0.0, abs=1e-6)
    assert same_answer(np.eye(4), _pose(shift=(0.0, 3.0, 2.0)), strip)  # 3.6 mm
    assert not same_answer(np.eye(4), _pose(shift=(5.0, 0.0, 0.0)), strip)
    # 4 deg about z moves the strip's ends (25 mm out) by 25 * 2 sin(2 deg) = 1.7 mm: same
    distance, angle = pose_difference(np.eye(4), _pose((0, 0, 4.0)), strip)
    assert angle == pytest.approx(4.0, abs=1e-6)
    radius = np.linalg.norm(strip[:, :2], axis=1).max()  # about z, only x and y count
    assert distance == pytest.approx(2 * np.sin(np.radians(2.0)) * radius, rel=0.02)
    assert same_answer(np.eye(4), _pose((0, 0, 4.0)), strip)
    assert not same_answer(np.eye(4), _pose((0, 0, 6.0)), strip)  # beyond 5 deg, though 2.6 mm


def _result(strip, entries) -> SearchResult:
    candidates = tuple(Candidate(name, np.eye(4), T, score, 0.0) for name, T, score in entries)
    return SearchResult(T_ct_us=entries[0][1], chosen=entries[0][0], runner_up=None,
                        score_gap_mm=None, confidence=1.0, ambiguous=False,
                        candidates=candidates)


def test_the_competitor_is_the_best_clinically_different_pose(strip):
    result = _result(strip, [("chosen", np.eye(4), 0.10),
                             ("near", _pose(shift=(2.0, 0, 0)), 0.11),  # the same answer
                             ("far", _pose(shift=(0, 0, 30.0)), 0.40),
                             ("slid", _pose(shift=(12.0, 0, 0)), 0.20)])
    competitor = clinical_competitor(result, strip)
    assert competitor["name"] == "slid"
    assert competitor["margin"] == pytest.approx((0.20 - 0.10) / 0.20)
    assert competitor["distance_mm"] == pytest.approx(12.0)
    assert np.allclose(competitor["centroid_ct"], strip.mean(axis=0) + [12.0, 0, 0])
    # a prior that rules the slide out leaves the far pose
    allowed = clinical_competitor(result, strip, allowed=lambda T: T[0, 3] < 5.0)
    assert allowed["name"] == "far" and allowed["margin"] == pytest.approx(0.75)
    alone = clinical_competitor(_result(strip, [("chosen", np.eye(4), 0.1)]), strip)
    assert alone["name"] is None and alone["margin"] == 1.0


def test_extent_share_is_the_sweeps_spread_over_the_ct_length(strip):
    assert extent_share(strip, 400.0) == pytest.approx(45.0 / 400.0, rel=0.05)  # p5-p95 of 50
    assert extent_share(strip, 10.0) == 1.0


def test_fit_is_monotone_learns_a_miscalibration_and_keeps_p_raw_where_data_are_few():
    rng = np.random.default_rng(1)
    p_raw = rng.uniform(0, 1, 2000)
    correct = rng.uniform(0, 1, 2000) < p_raw ** 2  # p_raw says too much
    cal = fit_calibration(p_raw, correct, ct_length_mm=400.0)
    grid = np.linspace(0, 1, 41)
    p = np.array([cal.p_correct(x) for x in grid])
    assert np.all(np.diff(p) >= 0) and 0.0 <= p.min() and p.max() <= 1.0
    for x in (0.3, 0.5, 0.8, 0.95):
        assert cal.p_correct(x) == pytest.approx(x ** 2, abs=0.1)
    # four sweeps say little: the identity prior keeps p_correct near p_raw
    few = fit_calibration([0.1, 0.9, 0.5, 0.7], [False, True, True, True], ct_length_mm=400.0)
    assert few.p_correct(0.5) == pytest.approx(0.5, abs=0.2)
    assert few.p_correct(0.95) > few.p_correct(0.3)
    # deterministic
    assert fit_calibration(p_raw, correct, ct_length_mm=400.0).knots == cal.knots


def test_reliability_table_counts_and_rates():
    p = np.array([0.1, 0.2, 0.85, 0.97, 0.99, 1.0])
    correct = np.array([False, True, True, True, True, False])
    rows = reliability_table(p, correct)
    assert [r["count"] for r in rows] == [2, 1, 3]
    assert rows[0]["observed"] == 0.5 and rows[2]["observed"] == pytest.approx(2 / 3)
    assert rows[2]["predicted"] == pytest.approx(np.mean([0.97, 0.99, 1.0]))


def test_calibration_file_round_trip_and_bad_files(tmp_path):
    cal = fit_calibration([0.1, 0.9, 0.5, 0.7], [False, True, True, True],
                          ct_length_mm=380.0, settings={"seed": 3})
    path = cal.save(tmp_path / "calibration.json")
    again = Calibration.load(path)
    assert again.knots == cal.knots and again.p_correct(0.4) == cal.p_correct(0.4)
    assert again.settings == {"seed": 3} and again.ct_length_mm == 380.0
    (tmp_path / "bad.json").write_text(json.dumps({"weights": [1, 2]}))
    with pytest.raises(ComRegError, match="not a ComReg calibration"):
        Calibration.load(tmp_path / "bad.json")
    for version in (1, 2, 3):  # the score margin's; the uncertainty's before today's
        older = {**json.loads(path.read_text()), "format": version}
        (tmp_path / "older.json").write_text(json.dumps(older))
        with pytest.raises(ComRegError, match=f"older ComReg \\(format {version}"):
            Calibration.load(tmp_path / "older.json")
    with pytest.raises(ComRegError):
        Calibration.load(tmp_path / "missing.json")



def test_a_saved_calibration_is_strict_json_and_loads_whatever_its_settings_hold(tmp_path):
    cal = fit_calibration([0.1, 0.9, 0.5, 0.7], [False, True, True, True],
                          ct_length_mm=380.0, settings={"trials": [{"RTE_mm": float("nan")}]})
    path = cal.save(tmp_path / "calibration.json")
    saved = json.loads(path.read_text(), parse_constant=lambda token: pytest.fail(token))
    assert saved["null_reasons"] == {"/settings/trials/0/RTE_mm": "not finite (NaN)"}
    again = Calibration.load(path)
    assert again.knots == cal.knots and again.settings == {"trials": [{"RTE_mm": None}]}


KNOTS = {"p_raw": [0.0, 0.5, 1.0], "p_correct": [0.1, 0.4, 0.9]}


@pytest.mark.parametrize("changes, message", [
    ({"knots": {**KNOTS, "p_correct": [0.1, float("nan"), 0.9]}}, "'knots p_correct' is nan"),
    ({"knots": {**KNOTS, "p_raw": [0.0, 1.0]}}, "same length"),
    ({"knots": {**KNOTS, "p_raw": [0.0, 0.6, 0.5]}}, "does not rise"),
    ({"knots": {**KNOTS, "p_correct": [0.5, 0.4, 0.9]}}, "falls"),
    ({"knots": [0.0, 1.0]}, "not {p_raw, p_correct}"),
    ({"ok_probability": 1.2}, "'ok_probability' is 1.2"),
    ({"sweeps": True}, "'sweeps' is True"),
    ({"ct_fingerprint": {"n_vertices": 3}}, "'ct_fingerprint'"),
    ({"settings": {"prior": None}}, "'settings prior' is None"),
])
def test_a_calibration_with_a_wrong_entry_cannot_be_made(changes, message):
    entries = dict(knots=KNOTS, sweeps=4, correct_share=0.5, ct_length_mm=300.0)
    with pytest.raises(ValueError, match=message):
        Calibration(**{**entries, **changes})


def test_a_calibration_fits_registrations_that_know_as_much_or_more():
    """``check_fits``: a calibration's prior kind against a registration's (``prior_kind`` of
    real :class:`Prior` objects): more known by the calibration is refused, less is a note."""
    from comreg_core.registration.search.priors import Landmark, Prior, prior_kind

    landmark = Landmark("L1", np.zeros(3), np.zeros(3))
    kinds = [prior_kind(None), prior_kind(Prior(T_init=np.eye(4))),
             prior_kind(Prior(landmarks=(landmark,))),
             prior_kind(Prior(T_init=np.eye(4), landmarks=(landmark,)))]
    assert kinds == ["none", "init", "landmark", "landmark"]
    entries = dict(knots=KNOTS, sweeps=4, correct_share=0.5, ct_length_mm=300.0)
    assert Calibration(**entries).prior_kind == "none"  # a file from before --prior
    for fitted_at, fitted in enumerate(("none", "init", "landmark")):
        calibration = Calibration(**entries, settings={"prior": fitted})
        for used_at, used in enumerate(("none", "init", "landmark")):
            if fitted_at > used_at:
                with pytest.raises(ComRegError, match=f"kind '{fitted}', this one has '{used}'"):
                    calibration.check_fits("f" * 64, used, "cal.json")
            else:
                note = calibration.check_fits("f" * 64, used, "cal.json")
                assert (note is None) == (fitted == used), note
                assert note is None or f"--prior {used}" in note


def _bone_points(n=3000):
    from tests.helpers import FIBULA_STL
    from comreg_core.registration.geometry.surface import CTSurface

    surface = CTSurface(FIBULA_STL)
    return surface, surface.samples(n)[0]  # on the bone: residuals and refit pass


def test_a_p_correct_that_is_not_finite_is_never_ok(shared_data):
    from comreg_core.registration.judgement.assessment import pose_uncertainty

    surface, points = _bone_points()
    u = pose_uncertainty(points, np.eye(4), surface, ct_length_mm=400.0, profiles=False,
                         advice=False)
    assert judge_registration(points, np.eye(4), surface, uncertainty=u, p_correct=0.99).ok
    for value in (float("nan"), float("-inf")):
        verdict = judge_registration(points, np.eye(4), surface, uncertainty=u, p_correct=value)
        assert not verdict.ok and len(verdict.reasons) == 1
        assert "estimated probability of only" in verdict.reasons[0]


def test_verdict_judges_by_p_correct_and_says_the_bound(shared_data):
    from comreg_core.registration.judgement.assessment import pose_uncertainty

    surface, points = _bone_points()
    u = pose_uncertainty(points, np.eye(4), surface, ct_length_mm=400.0, profiles=False,
                         advice=False)
    low = judge_registration(points, np.eye(4), surface, uncertainty=u, p_correct=0.6,
                             confidence=0.9)
    assert not low.ok and any("0.60" in r and "0.95" in r and "(95 %)" in r
                              for r in low.reasons)
    high = judge_registration(points, np.eye(4), surface, uncertainty=u, p_correct=0.97,
                              confidence=0.1)
    assert high.ok and high.figures["p_correct"] == pytest.approx(0.97)
    assert high.figures["bound_mm"] == pytest.approx(u.bound_mm)
    assert high.uncertainty["summary"] == u.summary()
    unjudged = judge_registration(points + 50.0, np.eye(4), surface)
    assert not unjudged.ok and "Too few US points" in unjudged.reasons[0]
    tie = judge_registration(points, np.eye(4), surface, uncertainty=u, p_correct=0.99,
                             confidence=0.0)
    assert not tie.ok and tie.reasons[0].startswith("Tie:")


def test_tracking_drift_moves_each_slice_rigidly_by_the_rms_asked():
    from comreg_core.evaluation.calibrate import tracking_drift

    rng = np.random.default_rng(3)
    slices = np.repeat(np.arange(200), 20)
    points = rng.uniform(-20, 20, (len(slices), 3))
    assert np.allclose(tracking_drift(points, slices, rng, 0.0, 0.0), points, atol=1e-12)
    moved = tracking_drift(points, slices, np.random.default_rng(4), 0.0, 1.5)
    shifts = (moved - points).reshape(200, 20, 3)
    assert np.allclose(shifts, shifts[:, :1], atol=1e-9)  # one translation per slice
    assert np.sqrt((shifts[:, 0] ** 2).sum(axis=1).mean()) == pytest.approx(1.5, rel=1e-6)
    turned = tracking_drift(points, slices, np.random.default_rng(5), 1.5, 0.0)
    centre = points.mean(axis=0)
    angles = []
    for s in range(0, 200, 20):  # each slice turned rigidly about the sweep's centre
        a, b = points[slices == s] - centre, turned[slices == s] - centre
        R = Rotation.align_vectors(b, a)[0]
        assert np.allclose(R.apply(a), b, atol=1e-9)
        angles.append(R.magnitude())
    assert 0.3 < np.degrees(np.sqrt(np.mean(np.square(angles)))) < 4.0


def test_points_off_the_bone_for_their_own_noise_and_a_short_sweeps_scale(shared_data):
    from comreg_core.registration.judgement.assessment import pose_uncertainty

    surface, points = _bone_points()
    rng = np.random.default_rng(2)
    noisy = points + rng.normal(0, 0.8, points.shape)  # 0.8 mm noise: still on the bone
    u = pose_uncertainty(noisy, np.eye(4), surface, ct_length_mm=400.0, profiles=False,
                         advice=False)
    verdict = judge_registration(noisy, np.eye(4), surface, uncertainty=u, p_correct=0.99)
    assert verdict.ok and 0.5 < verdict.figures["noise_mm"] < 1.2
    assert verdict.figures["p90_mm"] > 1.0  # what fixed limits would have called far
    # a quarter of the points 15 mm off the bone: not the bone, whatever p_correct says
    off = noisy.copy()
    off[::4] += 15.0 * surface.samples(3000)[1][::4]
    u_off = pose_uncertainty(off, np.eye(4), surface, ct_length_mm=400.0, profiles=False,
                             advice=False)
    bad = judge_registration(off, np.eye(4), surface, uncertainty=u_off, p_correct=0.99)
    assert not bad.ok and any("lie off the CT bone" in r for r in bad.reasons)
    # the scale check: a whole cloud scaled by 0.9 is refused, a short sweep's scale not judged
    scaled = 0.9 * (points - points.mean(0)) + points.mean(0)
    u_s = pose_uncertainty(scaled, np.eye(4), surface, ct_length_mm=400.0, profiles=False,
                           advice=False)
    assert any("scaled by" in r for r in judge_registration(
        scaled, np.eye(4), surface, uncertainty=u_s, p_correct=0.99).reasons)
    assert not any("scaled by" in r for r in judge_registration(
        scaled, np.eye(4), surface, uncertainty=u_s, p_correct=0.99, short_sweep=True).reasons)
