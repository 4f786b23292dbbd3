"""Priors of the pose search (comreg_core.registration.search.priors): what is within an initial pose's
tolerances and a landmark's, the starts around them, and registrations of a real short fibula
sweep with a prior around the truth, one that excludes it, and landmarks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comreg_core.register import Registrar
from comreg_core.io import save_transform
from comreg_core.register import load_prior
from comreg_core.registration.geometry.metrics import registration_metrics
from comreg_core.registration.judgement.prior_reasons import prior_record
from comreg_core.registration.search.priors import Landmark, Prior
from comreg_core.registration.search.search import rotation_about
from comreg_core.registration.judgement.verdict import Verdict, with_prior_reasons
from comreg_core.simulation import sample_initial_pose
from comreg_core.transforms import apply_transform, invert_rigid, space_change
from tests.helpers import FIBULA_STL, assert_close, random_rigid

#: Frames of the real fibula sweep making one ~45 mm run (the partial-sweep benchmark's runs,
#: tests/benchmarks/bench_partial.py); the search alone and ICP from the recorded tracking both
#: land within 1 mm / 1 deg of the recording on it.
RUN_FRAMES = np.arange(29, 38)


@pytest.fixture(scope="module")
def short_run(shared_data):
    """The run's bone points (CT frame: the recorded tracking is the truth, T_ct_us = I)."""
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import extract_us_surface

    sweep = read_tracked_sweep(shared_data / "ultrabones100k-fibula")
    return extract_us_surface(sweep.select(RUN_FRAMES)).points.points


@pytest.fixture(scope="module")
def search(shared_data):
    return Registrar.from_ct(FIBULA_STL)


def _turned(centre, degrees, mm, seed) -> np.ndarray:
    """The identity turned by ``degrees`` about a random axis through ``centre`` and shifted
    ``mm`` in a random direction."""
    rng = np.random.default_rng(seed)
    T = rotation_about(centre, rng.normal(size=3), math.radians(degrees))
    direction = rng.normal(size=3)
    T[:3, 3] += mm * direction / np.linalg.norm(direction)
    return T


def _errors(T, truth, points):
    e = registration_metrics(T, truth, points, FIBULA_STL)
    return e["RTE_mm"], e["RRE_deg"]


# --- the prior's geometry (no search) -----------------------------------------------------------

def test_what_is_within_the_prior():
    rng = np.random.default_rng(3)
    T_init, centroid = random_rigid(rng), np.array([10.0, -20.0, 30.0])
    home = apply_transform(T_init, centroid[None])[0]
    pose = rotation_about(home, [0.0, 0.6, 0.8], math.radians(20.0)) @ T_init
    pose[:3, 3] += [0.0, 20.0, 0.0]  # 20 deg and 20 mm from the initial pose
    rotation, shift, _ = Prior(T_init).errors(pose[None], centroid)
    assert_close([rotation[0], shift[0]], [20.0, 20.0], atol=1e-9)
    assert Prior(T_init, 30, 30).allows(pose[None], centroid)[0]
    assert not Prior(T_init, 15, 30).allows(pose[None], centroid)[0]
    assert not Prior(T_init, 30, 15).allows(pose[None], centroid)[0]
    # a landmark 10 mm off: within a 15 mm tolerance, not within 5 mm
    us = np.array([5.0, 5.0, 5.0])
    ct = apply_transform(pose, us[None])[0] + [6.0, 8.0, 0.0]
    assert Prior(T_init, landmarks=[Landmark("tip", ct, us, 15.0)]).allows(pose[None],
                                                                          centroid)[0]
    assert not Prior(T_init, landmarks=[Landmark("tip", ct, us, 5.0)]).allows(pose[None],
                                                                             centroid)[0]
    # clamped back onto the edge of the tolerances
    far = rotation_about(home, [1.0, 0.0, 0.0], math.radians(70.0)) @ T_init
    far[:3, 3] += [0.0, 0.0, 50.0]
    prior = Prior(T_init, 30, 30)
    clamped = prior.clamp(far[None], centroid)
    assert prior.allows(clamped, centroid)[0]
    assert_close([a[0] for a in prior.errors(clamped, centroid)[:2]], [30.0, 30.0], atol=0.05)
    # the same prior in RAS allows the same poses expressed in RAS
    C = space_change("LPS", "RAS")
    ras = prior.in_space("RAS")
    assert ras.allows((C @ pose @ C.T)[None], C[:3, :3] @ centroid)[0]
    assert not ras.allows((C @ far @ C.T)[None], C[:3, :3] @ centroid)[0]
    with pytest.raises(Exception, match="initial pose or at least one landmark"):
        Prior()
    with pytest.raises(Exception, match="at most 180"):
        Prior(T_init, 200, 30)


def test_starts_cover_the_tolerances_and_stay_within_them():
    T_init = random_rigid(np.random.default_rng(4))
    centroid, axes = np.zeros(3), np.eye(3)
    home = apply_transform(T_init, centroid[None])[0]
    centre = home + [40.0, 0.0, 0.0]  # the CT's long axis (x) runs through the init's centroid
    prior = Prior(T_init, 30, 30)
    rotations = prior.init_rotations(centroid)
    starts = prior.starts(rotations, centroid, centre, axes, 8.0)
    assert list(rotations)[0] == "init" and 1000 < len(starts) < 3000
    poses = np.stack(list(starts.values()))
    assert prior.allows(poses, centroid).all()
    rotation, shift, _ = prior.errors(poses, centroid)
    assert rotation.max() > 29.9 and shift.max() > 27.0  # out to the edges
    # any pose within that keeps the US centroid within 10 mm of the bone's axis has a start
    # within 12 deg and 12 mm (the slides 4 mm; ICP does the rest)
    rng = np.random.default_rng(5)
    for _ in range(20):
        turn = Rotation.random(random_state=rng).as_rotvec()
        turn *= math.radians(rng.uniform(0, 30)) / np.linalg.norm(turn)
        probe = rotation_about(home, turn, np.linalg.norm(turn)) @ T_init
        across = rng.normal(size=2)
        probe[:3, 3] += [rng.uniform(-25, 25), *(rng.uniform(0, 10) * across
                                                  / np.linalg.norm(across))]
        r = np.degrees(Rotation.from_matrix(poses[:, :3, :3] @ probe[:3, :3].T).magnitude())
        d = np.linalg.norm(poses[:, :3, 3] - probe[:3, 3], axis=1)
        assert np.maximum(r / 12.0, d / 12.0).min() <= 1.0, (r.min(), d.min())
    # second round: other shells and slides, as many again at most
    again = prior.starts(prior.init_rotations(centroid, 0.5), centroid, centre, axes, 8.0, 0.5)
    assert not set(again) & set(starts) and len(again) < len(starts)
    # landmarks: every start puts the US landmark onto the CT one (before its shift); 3 not on
    # a line: their least-squares pose comes first
    T = random_rigid(rng)
    us = rng.normal(size=(3, 3)) * 30
    pairs = [Landmark(str(k), apply_transform(T, us[k][None])[0], us[k], 10.0) for k in range(3)]
    three = Prior(landmarks=pairs)
    assert_close(three.kabsch_pose(), T, atol=1e-9)
    moved = three.starts({"a": random_rigid(rng)}, centroid, centre, axes, 8.0)
    assert list(moved)[0] == "landmarks" and "a+lm" in moved
    one = Prior(landmarks=pairs[:1])
    onto = one.onto_landmarks(random_rigid(rng))
    assert_close(apply_transform(onto, us[:1]), pairs[0].ct[None], atol=1e-9)


# --- registrations of a real short sweep ------------------------------------------------------

def test_a_prior_around_the_truth_registers_a_real_short_run(tmp_path, search, short_run):
    """From 25 deg / 25 mm off, within the default 30 deg / 30 mm; the folder records the
    prior, and its transform.tfm given back as --init is the registration's pose."""
    from comreg_core.io import PointCloud, write_points
    from comreg_core.register import register_to_directory

    T_init = _turned(short_run.mean(axis=0), 25.0, 25.0, seed=0)
    init = save_transform(T_init, tmp_path / "init.tfm")
    prior = load_prior(init)
    assert_close(prior.T_init, T_init, atol=1e-9, what="--init read back")
    us = write_points(PointCloud(short_run), tmp_path / "us.ply")
    result = register_to_directory(None, us, tmp_path / "reg", ct_mesh=FIBULA_STL, prior=prior)
    rte, rre = _errors(result.T_ct_us, np.eye(4), short_run)
    assert rte < 4.0 and rre < 5.0, (rte, rre, result.search.chosen)
    record = result.info["prior"]
    assert record["within"] and record["init_file"] == str(init.absolute())
    assert abs(record["rotation_from_init_deg"] - 25.0) < 3.0
    assert abs(record["shift_from_init_mm"] - 25.0) < 4.0
    assert result.search.chosen.startswith("init")
    again = load_prior(tmp_path / "reg" / "transform.tfm")  # the registration's own output
    assert_close(again.T_init, result.T_ct_us, atol=1e-9, what="transform.tfm as --init")


def test_a_prior_that_excludes_the_truth_ends_at_its_edge(search, short_run):
    """60 deg off with 10 deg / 10 mm tolerances: the best pose within fits worse and sits at
    the edge; the verdict turns CHECK with the reason in words."""
    T_init = rotation_about(short_run.mean(axis=0), [1.0, 0.3, 0.2], math.radians(60.0))
    result = search.register(short_run, prior=Prior(T_init, 10.0, 10.0))
    record = result.info["prior"]
    assert record["within"] and record["at_edge"]
    assert record["rotation_from_init_deg"] <= 10.0 + 1e-6
    assert record["shift_from_init_mm"] <= 10.0 + 1e-6
    assert _errors(result.T_ct_us, np.eye(4), short_run)[1] > 40.0
    assert any("at the edge of the initial pose's tolerance" in r and "of 10 deg" in r
               and "may exclude the true pose" in r for r in record["reasons"])
    verdict = with_prior_reasons(Verdict("ok", [], {"median_mm": 0.1}), record)
    assert verdict.verdict == "check" and verdict.reasons == record["reasons"]
    assert verdict.figures["prior_at_edge"] is True


def test_one_landmark_10mm_off_registers_from_any_rotation(search, short_run):
    """A landmark picked 10 mm off (tolerance 15 mm) and no initial pose: the search starts from
    the usual rotations moved onto it and lands on the truth from a full-rotation pose."""
    rng = np.random.default_rng(1)
    T_moved = sample_initial_pose(rng, "full", center=short_run.mean(axis=0))
    us, truth = apply_transform(T_moved, short_run), invert_rigid(T_moved)
    mid = len(us) // 2
    landmark = Landmark("tip", short_run[mid] + [0.0, 6.0, 8.0], us[mid], 15.0)
    result = search.register(us, prior=Prior(landmarks=[landmark]))
    rte, rre = _errors(result.T_ct_us, truth, us)
    assert rte < 4.0 and rre < 5.0, (rte, rre, result.search.chosen)
    record = result.info["prior"]
    assert record["within"] and record["max_deg"] is None
    assert 5.0 < record["landmarks"][0]["error_mm"] < 15.0
    assert "+lm" in result.search.chosen or result.search.chosen == "landmarks"


def test_a_landmark_beyond_its_tolerance_rules_poses_out(search, short_run):
    """A landmark picked 30 mm beside the bone from where the truth puts it, 5 mm tolerance:
    the truth fits best but is not eligible; the chosen pose keeps the landmark within 5 mm,
    and the record says that a pose outside the prior fits clearly better."""
    from comreg_core.registration.geometry.surface import principal_frame

    _, axes = principal_frame(short_run)
    mid = len(short_run) // 2
    landmark = Landmark("tip", short_run[mid] + 30.0 * axes[:, 1], short_run[mid], 5.0)
    prior = Prior(landmarks=[landmark])
    centroid = short_run.mean(axis=0)
    assert not prior.allows(np.eye(4)[None], centroid)[0]
    result = search.register(short_run, prior=prior)
    record = result.info["prior"]
    assert record["within"] and record["landmarks"][0]["error_mm"] <= 5.0
    assert prior.allows(result.search.best.T_ct_us[None], centroid)[0]
    assert _errors(result.T_ct_us, np.eye(4), short_run)[0] > 10.0
    best_outside = record["best_outside"]
    assert best_outside["lead"] >= 0.3 and best_outside["rotation_from_init_deg"] is None
    assert any("outside the prior fits the US points clearly better" in r
               for r in record["reasons"])
    # the record of the truth itself under this prior: not within, in words
    truth = prior_record(prior, np.eye(4), centroid)
    assert not truth["within"] and "No pose within the prior" in truth["reasons"][0]
    assert "landmark 'tip' 30.0 of 5 mm" in truth["reasons"][0]


def test_with_the_network_its_pose_is_one_more_start(tmp_path_factory, short_run):
    """``--model``: the network's pose is refined as one more start (the tiny test network's
    lands far off) but, outside the prior, never chosen; the search around the initial pose
    finds the truth. The prior needs the search: with ``search=False`` it is refused."""
    from comreg_core.errors import ComRegError
    from tests.training.tiny import tiny_run

    registrar = Registrar.from_run(tiny_run(tmp_path_factory)[1], "cpu")
    prior = Prior(_turned(short_run.mean(axis=0), 25.0, 25.0, seed=2))
    result = registrar.register(short_run, prior=prior)
    network = next(h for h in result.search.candidates if h.name == "network")
    assert result.info["prior"]["within"]
    if not prior.allows(network.T_ct_us[None], short_run.mean(axis=0))[0]:
        assert result.search.chosen != "network"
    rte, rre = _errors(result.T_ct_us, np.eye(4), short_run)
    assert rte < 4.0 and rre < 5.0, (rte, rre, result.search.chosen)
    with pytest.raises(ComRegError, match="need the pose search"):
        registrar.register(short_run, search=False, prior=prior)
