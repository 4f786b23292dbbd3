"""The evaluation harness: metrics.json values recomputed independently on known transforms,
schema, reproducibility, simulated clouds and bad inputs."""

import json

import numpy as np
import pytest
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from comreg_core.errors import ComRegError, InvalidGeometryError
from comreg_core.evaluation import (RegistrationOutput, evaluate, simulated_us_clouds,
                                    write_metrics)
from comreg_core.io import PointCloud
from comreg_core.simulation import BoneModel, sample_initial_pose, simulate_sweep, sweep_rng
from comreg_core.transforms import apply_transform, invert_rigid
from tests.helpers import BOX_CENTRE, box_distance
from tests.helpers import FIBULA_STL, assert_close, random_rigid

NAMESPACE = 0x4556414C  # documented first spawn-key word of evaluation streams ("EVAL")
STAT_KEYS = {"mean", "std", "median"}
SUMMARY_KEYS = {"RTE_mm", "RRE_deg", "CD_mm", "HD95_mm", "completion_CD_mm",
                "completion_HD95_mm", "runtime_s", "success_rate", "flip_rate", "ambiguous_rate",
                "unflagged_flip_rate", "trials", "failures"}


def _about(R_deg, centre):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(R_deg)).as_matrix()
    T[:3, 3] = centre - T[:3, :3] @ centre
    return T


def _expected_truth(seed, k, perturbation="paper"):
    """The trial's ground truth from the documented protocol, rebuilt here."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(NAMESPACE, 1, k)))
    return invert_rigid(sample_initial_pose(rng, perturbation, BOX_CENTRE))


class Oracle:
    """Returns the ground truth and a perfect completion (in the received cloud's frame)."""

    needs_ground_truth = True

    def __init__(self, box_surface):
        self.completion_ct, _ = box_surface.samples(2000)

    def __call__(self, points, T_ct_us_gt):
        return RegistrationOutput(T_ct_us_gt, 0.25,
                                  apply_transform(invert_rigid(T_ct_us_gt), self.completion_ct))


class Perturbed:
    """The ground truth followed by a known CT-frame error ``error(cloud centroid in CT)``."""

    needs_ground_truth = True

    def __init__(self, error):
        self.error = error

    def __call__(self, points, T_ct_us_gt):
        c = apply_transform(T_ct_us_gt, points).mean(axis=0)
        return {"T_ct_us": self.error(c) @ T_ct_us_gt, "runtime_s": 0.5}


def _methods(box_surface):
    shift = np.eye(4)
    shift[:3, 3] = [1.5, 0.0, 0.0]
    return {"oracle": Oracle(box_surface),
            "shifted": Perturbed(lambda c: shift),
            "turned": Perturbed(lambda c: _about([0, 3, 0], c)),
            "flipped": Perturbed(lambda c: _about([180, 0, 0], c)),
            "identity": lambda points: np.eye(4)}


def test_metrics_json_values_recomputed_independently(box_mesh, box_surface, box_cloud,
                                                      tmp_path):
    seed, trials = 11, 4
    # n_ct_samples = the oracle's completion size: its completion is exactly those CT samples
    result = evaluate(_methods(box_surface), box_cloud, box_mesh, trials=trials, seed=seed,
                      n_ct_samples=2000)
    assert set(result) == {"settings", "trials", "summary"}
    rows = result["trials"]
    assert len(rows) == trials * 5
    expected = {name: {k: [] for k in ("RTE_mm", "RRE_deg", "CD_mm", "HD95_mm")}
                for name in ("oracle", "shifted", "turned", "flipped", "identity")}
    for row in rows:
        k = row["trial"]
        truth = _expected_truth(seed, k)
        T_p = invert_rigid(truth)
        moved = apply_transform(T_p, box_cloud)
        assert_close(row["T_ct_us_gt"], truth, atol=1e-9, what="ground truth of the trial")
        ct_centroid = box_cloud.mean(axis=0)
        est = {"oracle": truth, "shifted": np.eye(4), "turned": _about([0, 3, 0], ct_centroid),
               "flipped": _about([180, 0, 0], ct_centroid), "identity": None}[row["method"]]
        if row["method"] == "shifted":
            est = truth.copy()
            est[:3, 3] += [1.5, 0, 0]
        elif row["method"] in ("turned", "flipped"):
            est = est @ truth
        elif row["method"] == "identity":
            est = np.eye(4)
        assert_close(row["T_ct_us"], est, atol=1e-9, what=f"{row['method']} estimate")
        # independent metrics: displacement of the moved centroid, scipy angle, analytic box
        c = moved.mean(axis=0)
        rte = np.linalg.norm(apply_transform(est, c[None]) - apply_transform(truth, c[None]))
        rre = np.degrees((Rotation.from_matrix(est[:3, :3]).inv()
                          * Rotation.from_matrix(truth[:3, :3])).magnitude())
        d = box_distance(apply_transform(est, moved))
        values = {"RTE_mm": rte, "RRE_deg": rre, "CD_mm": d.mean(),
                  "HD95_mm": np.percentile(d, 95)}
        for key, value in values.items():
            assert_close(row[key], value, atol=1e-6, what=f"{row['method']} {key}")
            expected[row["method"]][key].append(value)
        assert row["success"] == bool(rte < 2 and rre < 2)
        assert row["flip"] == bool(rre > 90)
        assert row["error"] is None
        assert_close(row["initial_RRE_deg"], np.degrees(
            Rotation.from_matrix(truth[:3, :3]).magnitude()), atol=1e-9)
        assert_close(row["initial_RTE_mm"],
                     np.linalg.norm(apply_transform(truth, c[None])[0] - c), atol=1e-9)
        if row["method"] == "oracle":
            assert_close([row["completion_CD_mm"], row["completion_HD95_mm"]], [0, 0], atol=1e-9)
            assert_close(row["runtime_s"], 0.25, atol=0)
        else:
            assert row["completion_CD_mm"] is None and row["completion_HD95_mm"] is None
    # the known outcomes
    by = {name: [r for r in rows if r["method"] == name] for name in expected}
    assert all(r["success"] for r in by["oracle"] + by["shifted"])
    assert_close([r["RTE_mm"] for r in by["shifted"]], [1.5] * trials, atol=1e-9)
    assert not any(r["success"] or r["flip"] for r in by["turned"])
    assert all(r["flip"] for r in by["flipped"])
    # summary recomputed from the independent values
    summary = result["summary"]
    assert list(summary) == list(expected)
    for name, metrics in expected.items():
        entry = summary[name]
        assert set(entry) == SUMMARY_KEYS
        for key, values in metrics.items():
            assert set(entry[key]) == STAT_KEYS
            assert_close([entry[key]["mean"], entry[key]["std"], entry[key]["median"]],
                         [np.mean(values), np.std(values), np.median(values)], atol=1e-6,
                         what=f"{name} {key} summary")
        assert entry["trials"] == trials and entry["failures"] == 0
    assert summary["oracle"]["success_rate"] == 1.0 and summary["shifted"]["success_rate"] == 1.0
    assert summary["turned"]["success_rate"] == 0.0 and summary["turned"]["flip_rate"] == 0.0
    assert summary["flipped"]["flip_rate"] == 1.0
    assert_close(summary["shifted"]["runtime_s"]["mean"], 0.5, atol=0)
    assert summary["identity"]["completion_CD_mm"] == {"mean": None, "std": None,
                                                       "median": None}
    # metrics.json: valid JSON, the same content
    path = write_metrics(result, tmp_path / "out" / "metrics.json")
    loaded = json.loads(path.read_text())
    assert loaded["summary"] == json.loads(json.dumps(result["summary"]))
    assert len(loaded["trials"]) == len(rows)
    assert not list(path.parent.glob(".*tmp*"))


def test_ground_truth_transform_of_a_cloud_in_its_own_frame(box_mesh, box_surface, box_cloud):
    """With --gt, the cloud is first put in place by T_gt, then moved: the trial's truth is the
    same as for the cloud given in the CT frame, and the oracle's CD is 0."""
    rng = np.random.default_rng(2)
    T_gt = random_rigid(rng, 300.0)  # T_ct_us
    us = apply_transform(invert_rigid(T_gt), box_cloud)
    a = evaluate({"oracle": Oracle(box_surface)}, us, box_mesh, trials=3, seed=4, T_gt=T_gt)
    b = evaluate({"oracle": Oracle(box_surface)}, box_cloud, box_mesh, trials=3, seed=4)
    for ra, rb in zip(a["trials"], b["trials"]):
        assert_close(ra["T_ct_us_gt"], rb["T_ct_us_gt"], atol=1e-9)
        assert_close(ra["CD_mm"], 0.0, atol=1e-6)
        assert_close(ra["initial_RTE_mm"], rb["initial_RTE_mm"], atol=1e-6)
    assert_close(a["settings"]["T_gt"], T_gt, atol=0)


def test_same_seed_same_trials_other_seed_other_trials(box_mesh, box_cloud):
    run = lambda seed, perturbation="paper": evaluate(  # noqa: E731
        {"identity": lambda p: np.eye(4)}, box_cloud, box_mesh, trials=3, seed=seed,
        perturbation=perturbation)["trials"]
    a, b, c = run(1), run(1), run(2)
    assert [r["T_ct_us_gt"] for r in a] == [r["T_ct_us_gt"] for r in b]
    assert [r["T_ct_us_gt"] for r in a] != [r["T_ct_us_gt"] for r in c]
    full = run(1, "full")
    for k, row in enumerate(full):
        assert_close(row["T_ct_us_gt"], _expected_truth(1, k, "full"), atol=1e-9)
    # trial k does not depend on the number of trials
    longer = evaluate({"identity": lambda p: np.eye(4)}, box_cloud, box_mesh, trials=5,
                      seed=1)["trials"]
    assert [r["T_ct_us_gt"] for r in longer[:3]] == [r["T_ct_us_gt"] for r in a]


def test_several_clouds_are_used_in_turn_and_pointclouds_accepted(box_mesh, box_cloud):
    clouds = [box_cloud[:200], PointCloud(box_cloud[200:])]
    seen = []

    def record(points):
        seen.append(len(points))
        return np.eye(4)

    result = evaluate({"m": record}, clouds, box_mesh, trials=3, seed=0)
    assert [r["cloud"] for r in result["trials"]] == [0, 1, 0]
    assert seen == [200, 300, 200]
    # a nested list of coordinates is one cloud
    one = evaluate({"m": lambda p: np.eye(4)}, box_cloud[:10].tolist(), box_mesh, trials=1)
    assert one["trials"][0]["cloud"] == 0


def test_a_failing_method_is_recorded_and_others_go_on(box_mesh, box_surface, box_cloud):
    def fails(points):
        raise InvalidGeometryError("No correspondences.", "Try again.")

    def not_rigid(points):
        return np.diag([2.0, 1, 1, 1])

    result = evaluate({"fails": fails, "not_rigid": not_rigid, "oracle": Oracle(box_surface)},
                      box_cloud, box_mesh, trials=2, seed=0)
    rows = {(r["method"], r["trial"]): r for r in result["trials"]}
    assert "No correspondences" in rows["fails", 0]["error"]
    assert "not rigid" in rows["not_rigid", 1]["error"]
    assert rows["fails", 0]["RTE_mm"] is None and rows["fails", 0]["success"] is False
    s = result["summary"]
    assert s["fails"]["failures"] == 2 and s["fails"]["success_rate"] == 0.0
    assert s["fails"]["RTE_mm"] == {"mean": None, "std": None, "median": None}
    assert s["oracle"]["success_rate"] == 1.0
    json.dumps(result, allow_nan=False)

    def bug(points):
        raise ZeroDivisionError("a bug")

    with pytest.raises(ZeroDivisionError):
        evaluate({"bug": bug}, box_cloud, box_mesh, trials=1)


def test_completion_given_in_the_ct_frame_is_mapped_back(box_mesh, box_surface, box_cloud):
    ct_samples, _ = box_surface.samples(1500)

    def method(points, T_ct_us_gt):
        off = T_ct_us_gt.copy()
        off[:3, 3] += [0.0, 0.0, 4.0]  # a wrong estimate; the completion follows it
        return {"T_ct_us": off, "completion_ct": ct_samples}

    method.needs_ground_truth = True
    row = evaluate({"m": method}, box_cloud, box_mesh, trials=1, n_ct_samples=1500)["trials"][0]
    assert_close(row["RTE_mm"], 4.0, atol=1e-9)
    # completion_ct is the CT samples under the estimate, so in truth 4 mm too low along z
    completion = ct_samples - [0, 0, 4.0]
    d1 = box_distance(completion)
    d2 = cdist(ct_samples, completion).min(axis=1)
    assert_close(row["completion_CD_mm"], (d1.mean() + d2.mean()) / 2, atol=1e-6)
    assert_close(row["completion_HD95_mm"], np.percentile(np.concatenate([d1, d2]), 95),
                 atol=1e-6)


@pytest.mark.parametrize("kwargs, match", [
    ({"methods": {}}, "No registration methods"),
    ({"methods": {"": lambda p: np.eye(4)}}, "not a non-empty string"),
    ({"methods": {"x": 3}}, "not callable"),
    ({"trials": 0}, "positive integer"),
    ({"trials": 2.5}, "positive integer"),
    ({"seed": -1}, "non-negative integer"),
    ({"perturbation": "huge"}, "Unknown perturbation 'huge'.*paper, full"),
    ({"us_points": np.zeros((0, 3))}, "0 points"),
    ({"us_points": np.array([[0, 0, np.nan]] * 4)}, "non-finite"),
    ({"us_points": np.zeros((10, 2))}, "expected \\(N, 3\\)"),
    ({"us_points": [np.zeros((10, 3)), np.zeros((10, 4))]}, "cloud 1.*expected \\(N, 3\\)"),
    ({"us_points": []}, "No US clouds"),
    ({"us_points": "simulatd"}, "'simulatd' is not understood"),
    ({"us_points": 5}, "Cannot use a int"),
    ({"us_points": "simulated", "T_gt": np.diag([1.0, -1, -1, 1])}, "drop --gt"),
    ({"T_gt": np.diag([1.0, 1, 2, 1])}, "not rigid"),
    ({"T_gt": np.eye(3)}, "4x4"),
    ({"ct_mesh": "/no/such/ct.stl"}, "does not exist"),
])
def test_bad_inputs_raise_helpful_errors(box_mesh, box_cloud, kwargs, match):
    args = {"methods": {"identity": lambda p: np.eye(4)}, "us_points": box_cloud,
            "ct_mesh": box_mesh, "trials": 2, "seed": 0}
    args.update(kwargs)
    methods, us, ct = args.pop("methods"), args.pop("us_points"), args.pop("ct_mesh")
    with pytest.raises(ComRegError, match=match):
        evaluate(methods, us, ct, **args)


def test_a_method_returning_nonsense_fails_its_trial(box_mesh, box_cloud):
    result = evaluate({"none": lambda p: None, "nan": lambda p: np.full((4, 4), np.nan)},
                      box_cloud, box_mesh, trials=1)
    errors = {r["method"]: r["error"] for r in result["trials"]}
    assert "not a result" in errors["none"]
    assert "finite 4x4" in errors["nan"]


# --- simulated clouds --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def fibula_bone(shared_data):
    return BoneModel(FIBULA_STL)


def test_simulated_clouds_reproducible_and_disjoint_from_training_streams(fibula_bone):
    a = simulated_us_clouds(fibula_bone, 2, seed=0)
    b = simulated_us_clouds(fibula_bone, 1, seed=0)
    assert_close(b[0], a[0], atol=0, what="cloud 0 does not depend on the count")
    assert not np.allclose(a[0][:100], a[1][:100])
    assert a[0].shape == (20_000, 3)
    # the training stream with the same integer seed gives other sweeps
    train = simulate_sweep(fibula_bone, None, sweep_rng(0, 0)).points
    assert train.shape == a[0].shape and not np.allclose(train, a[0])
    assert fibula_bone.distance(a[0]).mean() < 1.0  # on the bone (bar false hits)


def test_evaluate_on_simulated_sweeps(fibula_bone):
    def oracle(points, T_ct_us_gt):
        return T_ct_us_gt

    oracle.needs_ground_truth = True
    result = evaluate({"oracle": oracle}, "simulated", fibula_bone, trials=2, seed=3)
    assert result["settings"]["us_points"] == "simulated"
    assert [r["cloud"] for r in result["trials"]] == [0, 1]
    s = result["summary"]["oracle"]
    assert s["success_rate"] == 1.0 and s["RTE_mm"]["mean"] < 1e-9
    # CD of the ground truth is the simulated false hits' share only: HD95 ~ 0
    assert s["HD95_mm"]["median"] < 1e-3


def test_ambiguity_flags_are_recorded_and_summarised(box_mesh, box_surface, box_cloud):
    """A method's own confidence/ambiguous verdict lands in its rows; the summary counts the
    flagged trials and the flips that were *not* flagged (silent flips)."""
    calls = {"n": 0}

    def flagging(points, T_ct_us_gt):
        # trials 0, 1: flipped (0 flagged, 1 silent); trial 2: right and flagged; 3: right
        k = calls["n"]
        calls["n"] += 1
        c = apply_transform(T_ct_us_gt, points).mean(axis=0)
        T = _about([180, 0, 0], c) @ T_ct_us_gt if k < 2 else T_ct_us_gt
        return {"T_ct_us": T, "confidence": 0.9 if k in (1, 3) else 0.05,
                "ambiguous": k in (0, 2)}

    flagging.needs_ground_truth = True
    result = evaluate({"flagging": flagging, "oracle": Oracle(box_surface)}, box_cloud,
                      box_mesh, trials=4, seed=0)
    rows = [r for r in result["trials"] if r["method"] == "flagging"]
    assert [r["ambiguous"] for r in rows] == [True, False, True, False]
    assert [r["confidence"] for r in rows] == [0.05, 0.9, 0.05, 0.9]
    assert [r["flip"] for r in rows] == [True, True, False, False]
    s = result["summary"]
    assert s["flagging"]["ambiguous_rate"] == 0.5
    assert s["flagging"]["unflagged_flip_rate"] == 0.25
    assert s["flagging"]["flip_rate"] == 0.5
    # a method without a verdict: null rates and null row fields
    assert s["oracle"]["ambiguous_rate"] is None and s["oracle"]["unflagged_flip_rate"] is None
    assert all(r["ambiguous"] is None and r["confidence"] is None
               for r in result["trials"] if r["method"] == "oracle")
    json.dumps(result, allow_nan=False)
