"""The `comreg` command: version, help, info, and typed errors turned into exit status 2."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from comreg_core import __version__
from comreg_core.cli import app
from comreg_core.io import Volume, save_transform, write_volume
from comreg_core.registration.judgement.verdict import ambiguity_words, competitor_ruled_out
from tests.helpers import FIBULA_STL, assert_close

runner = CliRunner()


def test_version_and_help():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"comreg {__version__}"
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in ("extract-ct", "info"):
        assert command in result.output
    result = runner.invoke(app, ["extract-ct", "--help"])
    assert "--segment" in result.output and "--label" in result.output


def test_console_script_is_installed_and_fast_to_import():
    """`comreg --help` must not import VTK or torch (heavy imports live inside commands)."""
    code = ("import sys, comreg_core.cli; "
            "print(any(m in sys.modules for m in ('vtk', 'vtkmodules', 'torch', 'pyvista')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_calibrate_s_default_number_of_sweeps_is_the_library_s():
    """`comreg calibrate --sweeps` defaults to the library's CALIBRATION_SWEEPS (written out in
    the command line, which does not import the calibration), so the benchmark that defaults to
    that constant measures what a user gets."""
    from comreg_core.cli.evaluation import CALIBRATE_SWEEPS
    from comreg_core.evaluation.calibrate import CALIBRATION_SWEEPS, calibrate

    assert CALIBRATE_SWEEPS.default == CALIBRATION_SWEEPS == 60
    assert calibrate.__kwdefaults__["sweeps"] == CALIBRATION_SWEEPS


def test_calibrate_with_a_prior_registers_each_sweep_within_one_and_records_it(tmp_path):
    """`comreg calibrate --prior landmark` registers each simulated sweep within a simulated
    landmark and records the kind in the file; an unknown kind is one line, exit 2, and
    nothing is written. The simulated priors keep to their tolerances (scipy's angles)."""
    import json

    from scipy.spatial.transform import Rotation

    from comreg_core.evaluation.calibrate import simulated_prior
    from comreg_core.transforms import apply_transform, invert_rigid

    out = tmp_path / "calibration"
    result = runner.invoke(app, ["calibrate", str(FIBULA_STL), "--out", str(out), "--sweeps",
                                 "4", "--prior", "landmark"])
    assert result.exit_code == 0, result.output
    settings = json.loads((out / "calibration.json").read_text())["settings"]
    assert settings["prior"] == "landmark" and len(settings["trials"]) == 4
    bad = runner.invoke(app, ["calibrate", str(FIBULA_STL), "--out", str(tmp_path / "bad"),
                              "--sweeps", "4", "--prior", "pointer"])
    assert bad.exit_code == 2 and "Unknown calibration prior 'pointer'" in bad.output
    assert len(bad.output.strip().splitlines()) <= 2 and not (tmp_path / "bad").exists()
    rng = np.random.default_rng(0)
    moved = rng.normal(0.0, 20.0, (50, 3))
    T_true = np.eye(4)
    T_true[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    T_true[:3, 3] = [10.0, -40.0, 5.0]
    assert simulated_prior(rng, "none", T_true, moved, "LPS") is None
    centre = apply_transform(T_true, moved.mean(axis=0)[None])[0]
    for _ in range(20):
        init = simulated_prior(rng, "init", T_true, moved, "LPS")
        error = init.T_init @ invert_rigid(T_true)
        assert np.degrees(Rotation.from_matrix(error[:3, :3]).magnitude()) <= 30.0 + 1e-9
        assert np.linalg.norm(apply_transform(error, centre[None])[0] - centre) <= 30.0 + 1e-9
        assert (init.max_deg, init.max_mm) == (30.0, 30.0)
        (landmark,) = simulated_prior(rng, "landmark", T_true, moved, "LPS").landmarks
        truth = apply_transform(T_true, np.asarray(landmark.us)[None])[0]
        assert np.linalg.norm(np.asarray(landmark.ct) - truth) == pytest.approx(10.0)
        assert landmark.tolerance_mm == 15.0


def test_info_on_mesh_volume_and_transform(tmp_path):
    result = runner.invoke(app, ["info", str(FIBULA_STL)])
    assert result.exit_code == 0, result.output
    assert "triangles: 44194" in result.output and "space: LPS" in result.output
    volume = Volume.from_geometry(np.zeros((4, 5, 6), np.uint8), spacing=(0.5, 0.5, 2.0),
                                  origin=(1, 2, 3), space="RAS")
    write_volume(volume, tmp_path / "v.nrrd")
    result = runner.invoke(app, ["info", str(tmp_path / "v.nrrd")])
    assert "size (i j k): 4 5 6" in result.output and "spacing (mm): 0.5 0.5 2" in result.output
    assert "space: RAS" in result.output
    T = np.eye(4)
    T[:3, 3] = [10, 20, 30]
    save_transform(T, tmp_path / "t.tfm")
    result = runner.invoke(app, ["info", str(tmp_path / "t.tfm")])
    assert result.exit_code == 0, result.output
    assert "1 0 0 -10" in result.output and "0 0 1 -30" in result.output  # the inverse
    assert "1 0 0 10" in result.output  # back as the point mapping


@pytest.mark.parametrize("command", ["register", "evaluate"])
def test_the_older_run_dir_us_points_form_is_answered_with_the_new_one(tmp_path, command):
    """``comreg register RUN_DIR US_POINTS`` (a run folder, or its checkpoint, first) is no
    longer accepted: one line naming the form to use, exit 2, nothing written or loaded."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(b"not loaded")
    (tmp_path / "us.ply").write_bytes(b"not read")
    out = tmp_path / "out"
    for first, extra in ((run, []), (run / "checkpoint.pt", []), (run, ["--model", str(run)]),
                         (run, ["--ct", str(FIBULA_STL)])):
        result = runner.invoke(app, [command, str(first), str(tmp_path / "us.ply"), *extra,
                                     "--out", str(out)])
        assert result.exit_code == 2, (result.stdout, result.stderr)
        assert result.stdout == "" and "Traceback" not in result.stderr
        assert result.stderr.splitlines() == [
            f"error: 'comreg {command} RUN_DIR US_POINTS' is no longer accepted: use 'comreg "
            f"{command} US_POINTS --model RUN_DIR' (see 'comreg {command} --help')."]
        assert not out.exists()
    # a folder that is not a run is still only a folder where the US points go
    result = runner.invoke(app, [command, str(tmp_path), "--ct", str(FIBULA_STL), "--out",
                                 str(out)])
    assert result.exit_code == 2 and "no longer accepted" not in result.stderr, result.stderr


@pytest.mark.parametrize("name, content, message", [
    ("missing.nrrd", None, "does not exist"),
    ("a.png", b"x", "extension ComReg cannot use"),
    ("a.nrrd", b"NRRD0004\ntype: garbage\n", "corrupt or truncated"),
])
def test_user_errors_exit_2_with_one_line_and_no_traceback(tmp_path, name, content, message):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    for args in (["info", str(path)], ["extract-ct", str(path), "--out", str(tmp_path / "o.stl")]):
        result = runner.invoke(app, args)
        assert result.exit_code == 2, result.output
        assert message in result.output
        assert "Traceback" not in result.output
        assert not (tmp_path / "o.stl").exists()


def test_extract_ct_on_the_bundled_sample_matches_the_ct_model(tmp_path):
    """The README's main command: sample segmentation -> closed mesh near the original CT model."""
    import pyvista as pv

    from comreg_core.io import read_mesh
    from tests.helpers import SHARED_DATA

    sample = Path(__file__).resolve().parents[2] / "resources" / "sample" / "fibula.seg.nrrd"
    result = runner.invoke(app, ["extract-ct", str(sample), "--out", str(tmp_path / "bone.vtp")])
    assert result.exit_code == 0, result.output
    mesh = read_mesh(tmp_path / "bone.vtp")
    assert mesh.to_trimesh().is_watertight
    reference = read_mesh(SHARED_DATA / "ultrabones100k-fibula" / "fibula.stl")
    distance = np.abs(pv.PolyData(mesh.vertices).compute_implicit_distance(
        reference.to_pyvista())["implicit_distance"])
    assert np.percentile(distance, 95) < 0.4  # 0.8 mm voxels; measured 0.27 mm


def _two_segment_file(path, empty_second=False):
    from comreg_core.io import Segment, Segmentation, write_segmentation

    layers = np.zeros((1, 20, 20, 20), np.uint8)
    layers[0, 3:9, 3:9, 3:9] = 1
    if not empty_second:
        layers[0, 11:18, 11:18, 11:18] = 2
    seg = Segmentation(layers, np.diag([0.5, 0.5, 0.5, 1.0]), "LPS",
                       [Segment("tibia", 1), Segment("femur", 2)])
    write_segmentation(seg, path)
    return path


def test_extract_ct_segment_choice(tmp_path):
    path = _two_segment_file(tmp_path / "two.seg.nrrd")
    out = tmp_path / "bone.stl"
    result = runner.invoke(app, ["extract-ct", str(path), "--out", str(out)])
    assert result.exit_code == 2 and "which one is the bone" in result.output
    assert "'tibia'" in result.output and "'femur'" in result.output
    assert not out.exists()
    result = runner.invoke(app, ["extract-ct", str(path), "--out", str(out), "--segment", "femur"])
    assert result.exit_code == 0, result.output
    from comreg_core.io import read_mesh

    mesh = read_mesh(out)
    # voxels 11..17 at 0.5 mm: the surface runs half a voxel outside the centres, at 5.25 mm
    assert_close(mesh.vertices.min(0), [5.25, 5.25, 5.25], atol=0.15, what="femur corner mm")
    assert_close(mesh.vertices.max(0), [8.75, 8.75, 8.75], atol=0.15, what="femur corner mm")
    result = runner.invoke(app, ["extract-ct", str(path), "--out", str(out), "--label", "7"])
    assert result.exit_code == 2 and "No segment has label value 7" in result.output
    result = runner.invoke(app, ["extract-ct", str(path), "--out", str(out), "--segment", "ulna"])
    assert result.exit_code == 2 and "no segment named 'ulna'" in result.output


def test_extract_ct_empty_segment_and_mesh_passthrough(tmp_path):
    path = _two_segment_file(tmp_path / "two.seg.nrrd", empty_second=True)
    result = runner.invoke(app, ["extract-ct", str(path), "--out", str(tmp_path / "o.stl"),
                                 "--segment", "femur"])
    assert result.exit_code == 2 and "has no voxels" in result.output
    result = runner.invoke(app, ["extract-ct", str(FIBULA_STL), "--out", str(tmp_path / "f.ply")])
    assert result.exit_code == 0 and "44194 triangles" in result.output


def test_simulate_writes_reproducible_sweeps(tmp_path):
    args = ["simulate", str(FIBULA_STL), "--count", "2", "--seed", "5"]
    assert runner.invoke(app, [*args, "--out", str(tmp_path / "a")]).exit_code == 0
    assert runner.invoke(app, [*args, "--out", str(tmp_path / "b")]).exit_code == 0
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == ["config.yaml", "sweep_0000.ply", "sweep_0000_poses.npy",
                     "sweep_0000_slices.npy", "sweep_0001.ply", "sweep_0001_poses.npy",
                     "sweep_0001_slices.npy"]
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    result = runner.invoke(app, ["simulate", str(FIBULA_STL), "--out", str(tmp_path / "c"),
                                 "--config", str(tmp_path / "none.yaml")])
    assert result.exit_code == 2 and "does not exist" in result.output


def test_extract_us_on_the_real_fibula_sweep(tmp_path, shared_data):
    """Real tracked B-mode frames -> bone points near the CT surface (CT and tracking share a frame)."""
    import pyvista as pv

    from comreg_core.io import read_mesh, read_points, read_volume

    out = tmp_path / "us.ply"
    result = runner.invoke(app, ["extract-us", str(shared_data / "ultrabones100k-fibula"),
                                 "--out", str(out), "--compound", str(tmp_path / "us.nrrd"),
                                 "--compound-spacing", "2"])
    assert result.exit_code == 0, result.output
    points = read_points(out).points
    assert len(points) > 5000
    distance = np.abs(pv.PolyData(points).compute_implicit_distance(
        read_mesh(FIBULA_STL).to_pyvista())["implicit_distance"])
    assert np.median(distance) <= 0.8 and np.percentile(distance, 90) <= 3.0
    assert read_volume(tmp_path / "us.nrrd").array.max() > 100  # bright echoes compounded


def test_extract_us_bad_inputs(tmp_path):
    result = runner.invoke(app, ["extract-us", str(tmp_path / "nope"), "--out", str(tmp_path / "a.ply")])
    assert result.exit_code == 2 and "does not exist" in result.output
    (tmp_path / "frames").mkdir()
    result = runner.invoke(app, ["extract-us", str(tmp_path / "frames"), "--out", str(tmp_path / "a.ply")])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert not (tmp_path / "a.ply").exists()


def test_pretrain_register_evaluate_report_end_to_end(tmp_path):
    """The tiny shared run through the CLI: register a surface patch, evaluate with ComReg and the
    ICP-from-ground-truth baseline, then the report of the registration."""
    import json

    from comreg_core.io import (PointCloud, SurfaceMesh, load_transform, read_mesh, write_mesh,
                                write_points)
    from tests.training.tiny import TINY

    import yaml

    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY))
    run = tmp_path / "run"
    result = runner.invoke(app, ["pretrain", str(FIBULA_STL), "--out", str(run), "--preset", "cpu",
                                 "--epochs", "1", "--config", str(config), "--device", "cpu"])
    assert result.exit_code == 0, result.output
    assert "1 epochs" in result.output and (run / "checkpoint.pt").is_file()
    result = runner.invoke(app, ["pretrain", str(FIBULA_STL), "--out", str(run)])
    assert result.exit_code == 2 and "--resume" in result.output  # never overwrite a run

    mesh = read_mesh(FIBULA_STL).to_trimesh()
    points = mesh.sample(3000, seed=1)
    patch = points[points[:, 2] > np.percentile(points[:, 2], 70)]  # the distal third
    write_points(PointCloud(patch), tmp_path / "us.ply")
    out = tmp_path / "reg"
    result = runner.invoke(app, ["register", str(tmp_path / "us.ply"), "--model", str(run),
                                 "--out", str(out), "--ct", str(FIBULA_STL)])
    assert result.exit_code == 0, result.output
    saved = json.loads((out / "result.json").read_text())
    assert_close(load_transform(out / "transform.tfm"), np.asarray(saved["T_ct_us"]), atol=1e-9)
    T = np.asarray(saved["T_ct_us"])
    assert_close(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9, what="rigid")
    assert isinstance(saved["ambiguous"], bool) and "pose '" in result.output
    assert saved["search"]["chosen"] in saved["search"]["scores_mm"]
    polish = saved["search"]["polish"]  # the final exact-mesh ICP of the chosen pose
    assert 1 <= polish["iterations"] <= 100 and 0.5 < polish["inlier_fraction"] <= 1.0, polish
    result = runner.invoke(app, ["register", str(tmp_path / "us.ply"), "--model", str(run), "--out",
                                 str(tmp_path / "plain"), "--no-search"])
    assert result.exit_code == 0, result.output
    plain = json.loads((tmp_path / "plain" / "result.json").read_text())
    assert plain["ambiguous"] is None and plain["search"] is None
    assert plain["timings_s"]["search"] == 0.0
    # --config: the pose search's settings from YAML, the same loader as pretrain's; a
    # registration's config.yaml reads back; unknown keys are refused before any work
    search = tmp_path / "search.yaml"
    search.write_text(yaml.safe_dump({"search": {"shaft_rotations": 2, "slide_step_mm": 0,
                                                 "patch_max_share": 0.05}}))  # no patch starts
    result = runner.invoke(app, ["register", str(tmp_path / "us.ply"), "--model", str(run), "--out",
                                 str(tmp_path / "narrow"), "--config", str(search)])
    assert result.exit_code == 0, result.output
    narrow = json.loads((tmp_path / "narrow" / "result.json").read_text())["search"]
    # the search's own base, 2 turns x 2 flips per round (a second round when the first is
    # ambiguous), then the network's 3 poses
    assert narrow["starts_tried"] in (2 * 2 + 3, 2 * 2 * 2 + 3)
    assert narrow["starts_tried"] < saved["search"]["starts_tried"]
    recorded = yaml.safe_load((tmp_path / "narrow" / "config.yaml").read_text())
    assert recorded["search"]["shaft_rotations"] == 2
    result = runner.invoke(app, ["register", str(tmp_path / "us.ply"), "--model", str(run), "--out",
                                 str(tmp_path / "again"), "--config",
                                 str(tmp_path / "narrow" / "config.yaml")])
    assert result.exit_code == 0, result.output
    again = json.loads((tmp_path / "again" / "result.json").read_text())["search"]
    assert again["starts_tried"] == narrow["starts_tried"] and again["chosen"] == narrow["chosen"]
    search.write_text(yaml.safe_dump({"search": {"rotations": 2}}))
    for command in ("register", "evaluate"):
        result = runner.invoke(app, [command, str(tmp_path / "us.ply"), "--model", str(run),
                                     "--out", str(tmp_path / f"bad-{command}"), "--config",
                                     str(search)])
        assert result.exit_code == 2 and "Unknown config key" in result.output, result.output
        assert not (tmp_path / f"bad-{command}").exists()
    result = runner.invoke(app, ["evaluate", str(tmp_path / "us.ply"), "--model", str(run), "--out",
                                 str(tmp_path / "both"), "--trials", "1", "--method", "comreg",
                                 "--method", "comreg-plain", "--device", "cpu"])
    assert result.exit_code == 0, result.output
    both = json.loads((tmp_path / "both" / "metrics.json").read_text())
    assert list(both["summary"]) == ["comreg", "comreg-plain"]
    assert both["summary"]["comreg-plain"]["ambiguous_rate"] is None
    assert both["summary"]["comreg"]["ambiguous_rate"] is not None
    assert "flagged ambiguous" in result.output

    other = tmp_path / "other.stl"  # another CT: the fibula moved by 5 mm
    write_mesh(SurfaceMesh(mesh.vertices + 5.0, mesh.faces), other)
    result = runner.invoke(app, ["register", str(tmp_path / "us.ply"), "--model", str(run), "--out",
                                 str(tmp_path / "x"), "--ct", str(other)])
    assert result.exit_code == 2 and "trained for another CT" in result.output

    gate = tmp_path / "gate.yaml"  # the baselines' section reaches evaluate too
    gate.write_text(yaml.safe_dump({"baselines": {"icp_gt": {"max_iterations": 1}}}))
    result = runner.invoke(app, ["evaluate", str(tmp_path / "us.ply"), "--model", str(run),
                                 "--out", str(out), "--trials", "2", "--method", "icp-gt",
                                 "--config", str(gate)])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert {row["info"]["iterations"] for row in metrics["trials"]} == {1}
    result = runner.invoke(app, ["evaluate", str(tmp_path / "us.ply"), "--model", str(run),
                                 "--out", str(out), "--trials", "2", "--method", "icp-gt"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["summary"]["icp-gt"]["success_rate"] == 1.0
    assert len(metrics["trials"]) == 2

    result = runner.invoke(app, ["report", str(out)])
    assert result.exit_code == 0, result.output
    html = (out / "report.html").read_text()
    # the evaluation's metrics.json was not made for this registration: the report leaves it out
    assert "icp-gt" not in html and "registered_anterior.png" in html
    assert "Verdict: OK" in html or "Verdict: CHECK" in html
    # the pose search's choice is in the report
    record = json.loads((out / "result.json").read_text())
    search = record["search"]
    assert "Pose search / Confidence (0-1; below 0.3 is ambiguous)" in html
    assert f"in {search['polish']['iterations']} iterations" in html
    competitor = (record["uncertainty"] or {}).get("competitor")
    assert ambiguity_words(search["ambiguous"], competitor) in html
    assert ("YES: check the images" in html) == (search["ambiguous"]
                                                 and not competitor_ruled_out(competitor))
