"""Registration with a pretrained run: Registrar, result files, CT fingerprint, input checks."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from comreg_core.errors import InvalidGeometryError
from comreg_core.register import Registrar
from comreg_core.register import register_to_directory
from comreg_core.registration.geometry.icp import refine_on_mesh
from comreg_core.io import load_transform, read_points
from comreg_core.io.meshes import SurfaceMesh, write_mesh
from comreg_core.io.pointclouds import PointCloud, write_points
from comreg_core.training import CheckpointError
from comreg_core.training.data import validation_samples
from comreg_core.transforms import apply_transform, check_rigid, orthonormalize
from tests.helpers import FIBULA_STL, assert_close
from tests.training.tiny import tiny_run

TIMING_KEYS = {"preprocess", "completion_and_coarse_pose", "icp", "search", "postprocess",
               "total", "residuals"}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return tiny_run(tmp_path_factory)[1]


@pytest.fixture(scope="module")
def registrar(run):
    return Registrar.from_run(run, device="cpu")


@pytest.fixture(scope="module")
def us_cloud(registrar):
    """A held-out simulated sweep (mm), moved by a paper-sampler pose."""
    from comreg_core.training.data import TrainingCT

    ct = TrainingCT(registrar._ct_vertices, registrar._ct_faces, registrar.ct_points,
                    registrar.normalization)
    s = validation_samples(ct, registrar.config.simulation, "paper", 123, 1)[0]
    return registrar.normalization.points_to_mm(s.source)


def test_register_returns_a_rigid_transform_and_consistent_outputs(registrar, us_cloud):
    res = registrar.register(us_cloud, seed=0)
    T = check_rigid(res.T_ct_us)
    assert_close(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    check_rigid(res.T_ct_us_coarse)
    assert_close(res.registered_points, apply_transform(T, us_cloud), atol=1e-9)
    assert res.completion_ct.shape == (registrar.model.config.completion.dense_points, 3)
    assert set(res.timings) == TIMING_KEYS and res.runtime_s == res.timings["total"]
    assert res.device == "cpu" and res.n_points == len(us_cloud)
    assert set(res.residuals) == {"mean", "median", "p90", "p95", "max", "rmse",
                                  "inlier_fraction"}
    assert 0 <= res.residuals["median"] <= res.residuals["p95"] <= res.residuals["max"]
    # deterministic, and the CT half is encoded once
    enc = registrar.encoding
    again = registrar.register(us_cloud, seed=0)
    assert registrar.encoding is enc
    assert np.array_equal(again.T_ct_us, res.T_ct_us)


def test_staged_forward_equals_the_network_forward(registrar, us_cloud):
    res = registrar.register(us_cloud, search=False)  # the paper's plain pipeline
    norm = registrar.normalization
    src = torch.from_numpy(norm.points_to_model(us_cloud)).float()[None]
    with torch.no_grad(), registrar.deterministic_forward():  # the registrar's one thread
        out = registrar.model(src, registrar.encoding)
    fine = norm.transform_to_mm(orthonormalize(out.fine_transform[0].double().numpy()))
    assert registrar.model.config.icp.mesh_refine  # the cpu preset: then refined on the mesh
    assert_close(refine_on_mesh(us_cloud, fine, registrar.surface.matcher())[0], res.T_ct_us,
                 atol=1e-3)
    assert_close(norm.transform_to_mm(out.coarse_transform[0].double().numpy()),
                 res.T_ct_us_coarse, atol=1e-3)


def test_the_pose_search_is_on_by_default_and_recorded(registrar, us_cloud):
    res = registrar.register(us_cloud)
    hyp = res.search
    assert registrar.search_config.enabled and hyp is not None
    assert res.timings["search"] > 0 and res.runtime_s == res.timings["total"]
    assert_close(res.T_ct_us, hyp.T_ct_us, atol=0)
    assert_close(res.registered_points, apply_transform(res.T_ct_us, us_cloud), atol=1e-9)
    # the search alone ran with all its starts (the same as without a network), then the
    # network's three poses were refined as further starts; the chosen score is never worse
    alone = Registrar.from_ct((registrar._ct_vertices, registrar._ct_faces)).register(us_cloud)
    config = registrar.search_config
    assert hyp.starts_tried == alone.search.starts_tried + 3
    assert list(hyp.scores)[-3:] == ["network", "coarse", "completion"]
    assert set(alone.search.scores) < set(hyp.scores)
    assert hyp.best.score_mm <= alone.search.best.score_mm
    if hyp.chosen not in ("network", "coarse", "completion"):  # the search's own choice
        assert_close(res.T_ct_us, alone.T_ct_us, atol=0)
    assert res.confidence == hyp.confidence and res.ambiguous == hyp.ambiguous
    # the chosen pose was polished against the mesh: the reported residual is the polish's
    assert hyp.polish is not None and hyp.chosen in hyp.polished
    assert res.icp_rmse == hyp.polish["rmse_mm"] and 0.5 < hyp.polish["inlier_fraction"] <= 1
    data = json.loads(json.dumps(res.to_json(), allow_nan=False))
    assert data["ambiguous"] == hyp.ambiguous and data["confidence"] == hyp.confidence
    assert data["search"]["chosen"] == hyp.chosen
    assert set(data["search"]["scores_mm"]) == set(hyp.scores)
    assert res.info["search"] == hyp.to_json()
    assert res.info["ambiguous"] == hyp.ambiguous and res.info["confidence"] == hyp.confidence


def test_the_pose_search_off_is_the_plain_pipeline(run, registrar, us_cloud):
    plain = Registrar.from_run(run, device="cpu", search=False)
    assert not plain.search_config.enabled
    a = plain.register(us_cloud, seed=3)
    b = registrar.register(us_cloud, seed=3, search=False)
    for res in (a, b):
        assert res.search is None and res.confidence is None and res.ambiguous is None
        assert res.timings["search"] == 0.0
        data = res.to_json()
        assert data["ambiguous"] is None and data["search"] is None
        assert "ambiguous" not in res.info and res.info["search"] is None
    assert np.array_equal(a.T_ct_us, b.T_ct_us) and np.array_equal(a.completion_ct,
                                                                   b.completion_ct)
    assert a.icp_rmse == b.icp_rmse
    # and the plain Registrar can still run the search for one call
    assert plain.register(us_cloud, search=True).search is not None


def test_register_to_directory_writes_the_result_folder(run, registrar, us_cloud, tmp_path):
    us_path = write_points(PointCloud(us_cloud, registrar.space), tmp_path / "us.ply")
    out = tmp_path / "out"
    res = register_to_directory(run, us_path, out, device="cpu", seed=7, ct_mesh=FIBULA_STL)
    data = json.loads((out / "result.json").read_text())
    for key in ("T_ct_us", "T_ct_us_coarse", "timings_s", "runtime_s", "device", "seed",
                "residuals_mm", "n_points", "space", "ct_fingerprint", "files", "confidence",
                "ambiguous", "search"):
        assert key in data, key
    assert data["ambiguous"] == res.ambiguous and data["search"]["chosen"] == \
        res.search.chosen
    assert data["seed"] == 7 and data["device"] == "cpu" and data["n_points"] == len(us_cloud)
    assert set(data["timings_s"]) == TIMING_KEYS
    assert_close(np.array(data["T_ct_us"]), res.T_ct_us, atol=0)
    assert_close(load_transform(out / "transform.tfm", space=registrar.space), res.T_ct_us,
                 atol=1e-9)
    registered = read_points(out / "registered_us.ply")
    assert_close(registered.points, apply_transform(res.T_ct_us, us_cloud), atol=1e-3)
    assert len(read_points(out / "completion_ct.ply").points) == len(res.completion_ct)
    import yaml

    settings = yaml.safe_load((out / "config.yaml").read_text())
    assert settings["search"]["enabled"] is True and settings["inputs"]["seed"] == 7
    from comreg_core.registration.search.config import load_register_config

    assert load_register_config(out / "config.yaml").search == registrar.search_config
    assert not list(out.glob(".*tmp*"))
    plain = register_to_directory(run, us_path, tmp_path / "plain", device="cpu",
                                  search=False)
    data = json.loads((tmp_path / "plain" / "result.json").read_text())
    assert data["ambiguous"] is None and data["search"] is None
    assert plain.search is None


def test_results_written_under_the_older_key_names_read_the_same(run, us_cloud, tmp_path):
    """A result.json written when the pose search was called ``hypotheses`` (its block and
    its time) reads as today's: the folder's reader, the judge's evidence, the report."""
    from comreg_core.register.folder import read_result
    from comreg_core.register.judge import Evidence
    from comreg_core.report.registration import registration_metrics_table

    us_path = write_points(PointCloud(us_cloud, "LPS"), tmp_path / "us.ply")
    register_to_directory(run, us_path, tmp_path / "new", device="cpu", ct_mesh=FIBULA_STL)
    text = (tmp_path / "new" / "result.json").read_text()
    assert '"hypotheses"' not in text
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "result.json").write_text(text.replace('"search"', '"hypotheses"'))
    new, old = read_result(tmp_path / "new"), read_result(tmp_path / "old")
    assert old == new and list(old) == list(new) and list(old["timings_s"]) == \
        list(new["timings_s"])
    raw = json.loads((tmp_path / "old" / "result.json").read_text())
    assert "hypotheses" in raw and "hypotheses" in raw["timings_s"]
    assert Evidence.from_json(raw) == Evidence.from_json(new)
    assert Evidence.from_json(raw).confidence == new["search"]["confidence"] is not None
    figures = new["verdict_figures"]
    assert registration_metrics_table(raw, figures) == registration_metrics_table(new, figures)


def test_ct_fingerprint_mismatch_is_a_clear_error(run, tmp_path):
    import trimesh

    capsule = trimesh.creation.capsule(height=60.0, radius=10.0)
    other = write_mesh(SurfaceMesh(np.asarray(capsule.vertices), np.asarray(capsule.faces)),
                       tmp_path / "other.stl")
    with pytest.raises(CheckpointError, match="trained for another CT"):
        Registrar.from_run(run, device="cpu", ct_mesh=other)
    Registrar.from_run(run, device="cpu", ct_mesh=FIBULA_STL)  # the right CT passes


def test_missing_or_corrupt_checkpoint(tmp_path):
    with pytest.raises(CheckpointError, match="No checkpoint"):
        Registrar.from_run(tmp_path)
    (tmp_path / "checkpoint.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="Cannot read"):
        Registrar.from_run(tmp_path)
    torch.save({"format": "something else"}, tmp_path / "checkpoint.pt")
    with pytest.raises(CheckpointError, match="not a ComReg checkpoint"):
        Registrar.from_run(tmp_path)


@pytest.mark.parametrize("case, match", [
    ("few", "needs at least"),
    ("nan", "non-finite"),
    ("metres", "metres"),
    ("shape", "expected \\(N, 3\\)"),
    ("huge", "over 10 times"),
])
def test_bad_inputs(registrar, us_cloud, case, match):
    pts = {"few": us_cloud[:10], "metres": us_cloud / 1000.0, "shape": us_cloud[:, :2],
           "huge": us_cloud * 100.0}.get(case)
    if case == "nan":
        pts = us_cloud.copy()
        pts[3, 1] = np.nan
    with pytest.raises(InvalidGeometryError, match=match):
        registrar.register(pts)


def test_device_cuda_without_cuda_is_a_clear_error(run):
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    from comreg_core.config import ConfigError

    with pytest.raises(ConfigError, match="CUDA"):
        Registrar.from_run(run, device="cuda")


def test_the_ct_fingerprint_is_the_bone_not_the_file(tmp_path):
    """The bundled model was trained on the sample's CT extracted from its segmentation; the
    shared STL is the same bone meshed by another tool, a decimated RAS copy is the same bone
    again; the same bone moved 3 mm, and another bone, are refused."""
    import pyvista as pv

    from comreg_core.demo import SAMPLE_MODEL
    from comreg_core.io.meshes import read_mesh
    from comreg_core.training.checkpoint import check_same_bone, load_checkpoint
    from tests.helpers import tibia_like_mesh

    state = load_checkpoint(SAMPLE_MODEL)
    shared = read_mesh(FIBULA_STL)
    assert 0.1 < check_same_bone(state, shared) < 0.5  # measured 0.23 mm
    decimated = pv.PolyData.from_regular_faces(shared.vertices, shared.faces).decimate(0.5)
    copy = SurfaceMesh(np.asarray(decimated.points, float),
                       np.asarray(decimated.regular_faces), "LPS").in_space("RAS")
    write_mesh(copy, tmp_path / "fibula_ras.vtp")
    assert read_mesh(tmp_path / "fibula_ras.vtp").space == "RAS"
    assert check_same_bone(state, tmp_path / "fibula_ras.vtp") < 0.5
    moved = SurfaceMesh(shared.vertices + [3.0, 0.0, 0.0], shared.faces)
    with pytest.raises(CheckpointError, match=r"lies [23]\.\d mm from the run's CT bone"):
        check_same_bone(state, moved)
    with pytest.raises(CheckpointError, match="trained for another CT"):
        check_same_bone(state, SurfaceMesh(*tibia_like_mesh()))
    exact = SurfaceMesh(state["ct_vertices"].numpy(), state["ct_faces"].numpy())
    assert check_same_bone(state, exact) == 0.0
    registrar = Registrar.from_run(SAMPLE_MODEL, device="cpu", ct_mesh=tmp_path / "fibula_ras.vtp")
    assert registrar.fingerprint == state["ct_fingerprint"]
