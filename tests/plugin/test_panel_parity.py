"""The panel's registration is `comreg register`'s (issue 50), headless on real MRML nodes: on
the bundled sample, a simulated short sweep (with a verdict calibration: p_correct) and two real
sweeps registered as one body, the Logic gives the bit-identical T_ct_us and the same verdict,
reasons, p_correct, advice and competitor as the command line on the same files; its saved
result folder holds the CLI's keys and values (paths aside); a saved and reloaded scene keeps
the verdict attributes."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

from comreg_core.cli import app  # noqa: E402
from comreg_core.io import (PointCloud, read_mesh, read_points,  # noqa: E402
                            read_segmentation, write_points)
from comreg_core.io.meshes import write_mesh  # noqa: E402
from comreg_core.registration.judgement.calibration import fit_calibration  # noqa: E402
from comreg_core.surfaces.ct import extract_bone_surface  # noqa: E402
from comreg_core.surfaces.us import extract_us_to_file  # noqa: E402
from comreg_core.transforms import T_RAS_LPS, apply_transform  # noqa: E402
from comreg_plugin import testing  # noqa: E402
from comreg_plugin.logic import ComRegLogic  # noqa: E402
from comreg_plugin.scene_io import transformToParentRAS  # noqa: E402
from comreg_plugin.verdict_record import figuresFromNode, recordAdvice  # noqa: E402
from tests.helpers import FIBULA_STL  # noqa: E402

runner = CliRunner()

#: Keys of result.json that name files or folders (the panel's inputs are its own files) or
#: time a run: left out of the comparison with the CLI's.
PATH_KEYS = {"us_points", "ct_mesh", "run_dir", "path", "runtime_s", "timings_s"}


def _cli(args: list) -> None:
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output


def _without(value, keys=PATH_KEYS):
    """``value`` (JSON-like) without the entries named in ``keys``, at any depth."""
    if isinstance(value, dict):
        return {k: _without(v, keys) for k, v in value.items() if k not in keys}
    if isinstance(value, list):
        return [_without(v, keys) for v in value]
    return value


def _calibration(folder, ct_length_mm: float):
    """A verdict calibration fitted on 60 synthetic rows (as the CLI's own test makes one)."""
    rng = np.random.default_rng(0)
    p_raw = rng.uniform(0, 1, 60)
    return fit_calibration(p_raw, rng.uniform(0, 1, 60) < p_raw ** 2,
                           ct_length_mm=ct_length_mm).save(folder / "calibration.json")


def _check_same_as_cli(summary, cli_out, saved_out) -> dict:
    """The panel's summary and saved folder against the CLI's folder: the same transform bits,
    verdict, reasons, p_correct, advice and competitor; the same keys and values (paths and
    timings aside) in result.json and config.yaml; the figures on the transform node."""
    cli = json.loads((cli_out / "result.json").read_text())
    assert np.array_equal(summary.T_ct_us, np.asarray(cli["T_ct_us"]))  # bit-identical
    node_lps = T_RAS_LPS @ transformToParentRAS(summary.transformNode) @ T_RAS_LPS
    assert np.abs(node_lps - summary.T_ct_us).max() < 1e-9
    record = summary.record
    for key in ("verdict", "verdict_reasons", "p_correct", "competitor", "extent_share"):
        assert record[key] == cli[key], key
    assert recordAdvice(record) == recordAdvice(cli)
    figures = figuresFromNode(summary.transformNode)
    assert figures["verdict"] == cli["verdict"]
    assert figures["verdict_reasons"] == cli["verdict_reasons"]
    assert figures["p_correct"] == cli["p_correct"]  # every digit kept in the attribute
    assert (figures["advice"] or "") == recordAdvice(cli)
    assert (figures["uncertainty"] is None) == (cli.get("uncertainty") is None)
    assert figures["scan_next"] == cli.get("scan_next")
    saved = json.loads((saved_out / "result.json").read_text())
    assert saved.keys() == cli.keys()
    assert _without(saved) == _without(cli)
    assert sorted(p.name for p in cli_out.iterdir()) == sorted(
        p.name for p in saved_out.iterdir() if p.name != "inputs")
    cli_config = yaml.safe_load((cli_out / "config.yaml").read_text())
    saved_config = yaml.safe_load((saved_out / "config.yaml").read_text())
    assert _without(saved_config) == _without(cli_config)
    for path in [saved["us_points"]] if isinstance(saved["us_points"], str) else \
            saved["us_points"]:  # the saved folder names its own copies of the inputs
        assert path.startswith(str(saved_out.resolve())), path
    return cli


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """The bundled sample as the CLI takes it: the CT bone mesh of the segmentation, the
    sweep's bone points by `extract-us` (with beam origins), a verdict calibration."""
    folder = tmp_path_factory.mktemp("sample")
    seg = read_segmentation(testing.SAMPLE_SEGMENTATION)
    ct = write_mesh(extract_bone_surface(seg, segment=seg.segments[0]), folder / "ct.vtk")
    us = folder / "us.ply"
    extract_us_to_file(testing.SAMPLE_SWEEP, us)
    calibration = _calibration(folder, 400.0)
    out = folder / "cli"
    _cli(["register", us, "--ct", ct, "--verdict-calibration", calibration, "--out", out])
    return folder, ct, us, calibration, out


def test_the_bundled_sample_registers_in_the_panel_as_on_the_command_line(sample, tmp_path):
    folder, ct, us, calibration, cli_out = sample
    logic = ComRegLogic()
    logic.getParameterNode().resultDirectory = str(tmp_path / "registrations")
    _, models = logic.loadSegmentation(testing.SAMPLE_SEGMENTATION)
    points, _ = logic.loadTrackedSweep(testing.SAMPLE_SWEEP)
    summary = logic.register(points, "search", ctModelNode=models[0],
                             verdictCalibration=calibration)
    assert summary.resultFolder.parent == tmp_path / "registrations"
    saved = logic.saveResultFolder(tmp_path / "saved")
    cli = _check_same_as_cli(summary, cli_out, saved)
    assert cli["p_correct"] is not None and cli["verdict_calibration"]["sweeps"] == 60
    assert read_mesh(saved / "inputs" / "ct_bone.vtk").vertices.shape == \
        read_mesh(ct).vertices.shape
    p = logic.getParameterNode()
    assert p.verdict == cli["verdict"] and p.pCorrect == cli["p_correct"]
    assert f"Verdict: {cli['verdict'].upper()}" in summary.describe(p.ambiguous, p.confidence)

    node = summary.transformNode  # no absolute path on the node: a saved scene moves
    names = list(node.GetAttributeNames())
    assert "ComReg.verdict" in names and "ComReg.result_folder" in names
    for name in names:
        assert str(tmp_path) not in node.GetAttribute(name), name
    assert node.GetAttribute("ComReg.result_folder") == summary.resultFolder.name

    # the scene keeps the figures: saved, reloaded by another logic
    logic.saveScene(tmp_path / "scene" / "panel.mrml")
    other = ComRegLogic()
    other.loadScene(tmp_path / "scene" / "panel.mrml")
    node = other.scene.GetFirstNodeByName(summary.transformNode.GetName())
    assert figuresFromNode(node) == figuresFromNode(summary.transformNode)
    assert node.GetAttribute("ComReg.verdict") == cli["verdict"]


@pytest.fixture(scope="module")
def short_sweep(tmp_path_factory, shared_data):
    """A 40-50 mm simulated one-face sweep of the fibula moved by a known pose, registered by
    the CLI with a verdict calibration."""
    from comreg_core.config import from_dict
    from comreg_core.simulation.config import SimulationConfig
    from tests.benchmarks.bench_partial import PARTIAL_SWEEPS, simulated_runs

    config = from_dict(SimulationConfig, PARTIAL_SWEEPS, "simulation")
    points, origins = simulated_runs(FIBULA_STL, 1, 11, config)[0]
    T = np.eye(4)
    T[:3, 3] = [20.0, -10.0, 5.0]
    folder = tmp_path_factory.mktemp("short")
    us = write_points(PointCloud(apply_transform(T, points), "LPS",
                                 beam_origins=apply_transform(T, origins)), folder / "us.ply")
    calibration = _calibration(folder, 404.0)
    out = folder / "cli"
    _cli(["register", us, "--ct", FIBULA_STL, "--verdict-calibration", calibration,
          "--out", out])
    return us, calibration, out


def test_a_short_sweep_registers_in_the_panel_as_on_the_command_line(short_sweep, tmp_path):
    us, calibration, cli_out = short_sweep
    logic = ComRegLogic()
    ct = logic.loadBoneMesh(FIBULA_STL)
    node = logic.loadUSPoints(us)
    summary = logic.register(node, "search", ctModelNode=ct, verdictCalibration=calibration)
    cli = _check_same_as_cli(summary, cli_out, logic.saveResultFolder(tmp_path / "saved"))
    assert cli["p_correct"] is not None and 0.0 < cli["extent_share"] < 0.5


@pytest.fixture(scope="module")
def two_sweeps(tmp_path_factory, shared_data):
    """Two runs of the real fibula sweep 150+ mm apart, moved by one pose, registered by
    `comreg register A B --ct`."""
    from comreg_core.simulation import sample_initial_pose
    from tests.benchmarks.bench_partial import real_runs
    from tests.test_register_sweeps import RUNS

    runs = real_runs(shared_data)
    chosen = [runs[k] for k in RUNS]
    points = np.vstack([p for p, _ in chosen])
    T = sample_initial_pose(np.random.default_rng(3), "full", center=points.mean(axis=0))
    folder = tmp_path_factory.mktemp("two")
    paths = [write_points(PointCloud(apply_transform(T, p), "LPS",
                                     beam_origins=apply_transform(T, o)), folder / name)
             for name, (p, o) in zip(("first.ply", "second.ply"), chosen)]
    out = folder / "cli"
    _cli(["register", *paths, "--ct", FIBULA_STL, "--out", out])
    return paths, out


def test_two_sweeps_register_in_the_panel_as_one_body_as_on_the_command_line(two_sweeps,
                                                                            tmp_path):
    paths, cli_out = two_sweeps
    logic = ComRegLogic()
    ct = logic.loadBoneMesh(FIBULA_STL)
    nodes = [logic.loadUSPoints(path, name=path.stem) for path in paths]
    summary = logic.register(nodes, "search", ctModelNode=ct)
    saved = logic.saveResultFolder(tmp_path / "saved")
    cli = _check_same_as_cli(summary, cli_out, saved)
    assert [r["n_points"] for r in cli["us_inputs"]] == [
        n.GetPolyData().GetNumberOfPoints() for n in nodes]
    assert cli["beam_origins_used"] is True  # the nodes kept the files' beam origins
    for node in nodes:  # both under the one transform, coloured by distance
        assert node.GetParentTransformNode() is summary.transformNode
        assert node.GetDisplayNode().GetActiveScalarName() == "ComReg distance to CT (mm)"
    assert (saved / "registered_us_1.ply").is_file() and (saved / "registered_us_2.ply").is_file()


def test_write_report_renders_the_command_lines_report(short_sweep, tmp_path):
    """"Write report" on the panel's registration writes the pages and screenshots `comreg
    report` writes on the CLI's folder; each image within the report tests' tolerance (mean
    absolute difference <= 1.5 of 255, <= 0.5 % of pixels off by more than 40)."""
    import shutil

    from PIL import Image

    from tests.report.support import compare_images
    from tests.report.test_scenes import BAD_PIXELS_MAX, MEAN_DIFF_MAX

    us, calibration, cli_out = short_sweep
    cli_copy = tmp_path / "cli"
    shutil.copytree(cli_out, cli_copy)
    _cli(["report", cli_copy])
    logic = ComRegLogic()
    ct = logic.loadBoneMesh(FIBULA_STL)
    logic.register(logic.loadUSPoints(us), "search", ctModelNode=ct,
                   verdictCalibration=calibration)
    page = logic.writeReport(tmp_path / "panel")
    assert page == tmp_path / "panel" / "report.html" and page.is_file()
    cli_images = sorted((cli_copy / "report_images").glob("*.png"))
    panel_images = sorted((tmp_path / "panel" / "report_images").glob("*.png"))
    assert [p.name for p in panel_images] == [p.name for p in cli_images] and cli_images
    for a, b in zip(panel_images, cli_images):
        mean, bad = compare_images(np.asarray(Image.open(a).convert("RGB")),
                                   np.asarray(Image.open(b).convert("RGB")))
        assert mean <= MEAN_DIFF_MAX and bad <= BAD_PIXELS_MAX, (a.name, mean, bad)
    assert "Verdict" in page.read_text()


def test_two_sequence_browsers_register_as_the_command_line_registers_their_points(
        shared_data, tmp_path):
    """Two Sequence browsers (two stretches of the real sweep) picked as two sweeps: their bone
    points are extracted and registered as one body, as `comreg extract-us` then `comreg
    register A B --ct` do (the points through the scene's RAS agree to 1e-6 mm, so the pose
    to 1e-6 mm and deg, and the verdict is the same)."""
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
    from tests.helpers import cut_sweep

    folders = [cut_sweep(tmp_path / name, start, 20) for name, start in (("a", 0), ("b", 60))]
    paths = [tmp_path / f"{folder.name}.ply" for folder in folders]
    for folder, path in zip(folders, paths):
        extract_us_to_file(folder, path)
    _cli(["register", *paths, "--ct", FIBULA_STL, "--out", tmp_path / "cli"])
    cli = json.loads((tmp_path / "cli" / "result.json").read_text())
    logic = ComRegLogic()
    ct = logic.loadBoneMesh(FIBULA_STL)
    browsers = [logic.addSweepSequence(folder, name=folder.name) for folder in folders]
    summary = logic.register(browsers, "search", ctModelNode=ct)
    T_cli = np.asarray(cli["T_ct_us"])
    centroid = np.vstack([read_points(path).points for path in paths]).mean(axis=0)
    assert rotation_error_deg(summary.T_ct_us, T_cli) < 1e-6
    assert translation_error_mm(summary.T_ct_us, T_cli, centroid) < 1e-6
    assert summary.record["verdict"] == cli["verdict"]
    assert summary.record["verdict_reasons"] == cli["verdict_reasons"]
    assert [r["n_points"] for r in summary.record["us_inputs"]] == \
        [r["n_points"] for r in cli["us_inputs"]]
    assert summary.record["beam_origins_used"] is cli["beam_origins_used"] is True
