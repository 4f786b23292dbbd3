"""Issue 15: no traceback, no data loss, outputs checked before the work, bounded inputs.

Bad inputs and unusable output places through the ``comreg`` command: exit status 2, one
``error:`` line on stderr, no traceback, nothing of the command's own left behind.

The run folder of these tests is the bundled sample model (``resources/sample/fibula_cpu.pt``)
laid out as ``comreg pretrain`` writes a run (checkpoint.pt, config.yaml, ct_fingerprint.json), so
no training is needed.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from comreg_core.cli import app
from comreg_core.demo import SAMPLE_MODEL, SAMPLE_SWEEP
from comreg_core.io import PointCloud, SurfaceMesh, write_mesh, write_points
from tests.helpers import FIBULA_STL, immutable, paths_under


runner = CliRunner()  # click >= 8.2: result.stderr apart from result.stdout


# --- helpers --------------------------------------------------------------------------------------

def _refused(args, *contains: str):
    """Run ``comreg ARGS``; assert exit 2 with one ``error:`` line holding ``contains``."""
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 2, (result.exit_code, result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    for text in contains:
        assert text in result.stderr, (text, result.stderr)
    return result


def _make_run(run: Path) -> Path:
    """A run folder holding the bundled model, as 'comreg pretrain' lays one out."""
    from comreg_core.training.checkpoint import ct_fingerprint, load_checkpoint, write_fingerprint

    run.mkdir(parents=True)
    shutil.copy(SAMPLE_MODEL, run / "checkpoint.pt")
    state = load_checkpoint(run)
    (run / "config.yaml").write_text(state["config_yaml"], encoding="utf-8")
    write_fingerprint(ct_fingerprint(state["ct_vertices"].numpy(), state["ct_faces"].numpy()), run)
    return run


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """``(run folder, us.ply)``: the sample run and a patch of its CT surface (900 points)."""
    import trimesh

    from comreg_core.training import run_ct_mesh

    root = tmp_path_factory.mktemp("sample_run")
    run = _make_run(root / "run")
    ct = run_ct_mesh(run)
    points = trimesh.Trimesh(ct.vertices, ct.faces).sample(3000, seed=1)
    patch = points[points[:, 2] > np.percentile(points[:, 2], 70)]
    us = write_points(PointCloud(patch, ct.space), root / "us.ply")
    return run, us


@pytest.fixture
def no_model_loading(monkeypatch):
    """Fail the test if a command loads a checkpoint (its checks must come before the work):
    ``load_checkpoint`` is replaced in its module and wherever a loaded module bound it."""
    import comreg_core.register.network  # noqa: F401  (imported unpatched: binds load_checkpoint)
    from comreg_core.training import checkpoint

    def refuse(*args, **kwargs):
        raise AssertionError("a checkpoint was loaded before the output place was checked")

    original = checkpoint.load_checkpoint
    for name, module in list(sys.modules.items()):
        if name.startswith("comreg_core") and getattr(module, "load_checkpoint", None) is original:
            monkeypatch.setattr(module, "load_checkpoint", refuse)


# --- 1. data loss ------------------------------------------------------------------------------

def test_register_into_the_run_folder_is_refused_and_the_run_is_kept(sample, no_model_loading):
    run, us = sample
    before = {name: (run / name).read_bytes() for name in paths_under(run)}
    _refused(["register", us, "--model", run, "--out", run], "is the pretraining run folder")
    _refused(["register", us, "--model", run, "--out", run / "registration"],
             "inside the pretraining run")
    _refused(["evaluate", us, "--model", run, "--out", run, "--trials", "1"], "run folder")
    _refused(["simulate", FIBULA_STL, "--out", run], "run folder")
    _refused(["extract-ct", FIBULA_STL, "--out", run / "bone.stl"], "run folder")
    _refused(["extract-us", SAMPLE_SWEEP, "--out", run / "us.ply"], "run folder")
    assert {name: (run / name).read_bytes() for name in paths_under(run)} == before  # byte-identical


def test_pretrain_does_not_overwrite_another_commands_config(tmp_path):
    folder = tmp_path / "registration"
    folder.mkdir()
    (folder / "config.yaml").write_text("register: {seed: 0}\n")
    _refused(["pretrain", FIBULA_STL, "--out", folder], "config.yaml", "no checkpoint.pt")
    assert (folder / "config.yaml").read_text() == "register: {seed: 0}\n"
    assert paths_under(folder) == {"config.yaml"}


@pytest.mark.parametrize("options, message", [
    (["--calibration-sweeps", "3"], "at least 4"),
    (["--calibration-sweeps", "4", "--calibration-prior", "atlas"], "Unknown --calibration-prior"),
    (["--calibration-prior", "init"], "needs --calibration-sweeps"),
])
def test_pretrain_refuses_calibration_options_before_training(tmp_path, options, message):
    _refused(["pretrain", FIBULA_STL, "--out", tmp_path / "run", "--epochs", "1", *options],
             message)
    assert not (tmp_path / "run").exists()


def test_an_output_that_is_an_input_is_refused(tmp_path):
    mesh = shutil.copy(FIBULA_STL, tmp_path / "bone.stl")
    before = Path(mesh).read_bytes()
    _refused(["extract-ct", mesh, "--out", mesh], "is also an input")
    assert Path(mesh).read_bytes() == before


# --- 2. unwritable output places, every command --------------------------------------------------

def _command_args(name: str, out: Path, run: Path, us: Path) -> list:
    return {
        "extract-ct": ["extract-ct", FIBULA_STL, "--out", out / "bone.stl"],
        "simulate": ["simulate", FIBULA_STL, "--out", out],
        "extract-us": ["extract-us", SAMPLE_SWEEP, "--out", out / "us.ply"],
        "pretrain": ["pretrain", FIBULA_STL, "--out", out, "--epochs", "1"],
        "register": ["register", us, "--model", run, "--out", out],
        "evaluate": ["evaluate", us, "--model", run, "--out", out, "--trials", "1"],
        "demo": ["demo", "--out", out],
        "report": ["report", out],
        "calibrate": ["calibrate", FIBULA_STL, "--out", out, "--sweeps", "4"],
        "live": ["live", "--igtl", "127.0.0.1:1", "--ct", FIBULA_STL, "--out", out],
        "batch": ["batch", us.with_name("cohort.csv"), "--out", out],
    }[name]


def _every_command():
    """Every command of the CLI that writes (all but 'info' and 'replay'), read from the app, so a
    new command fails this test until it is added to :func:`_command_args`."""
    names = sorted(c.name for c in app.registered_commands)
    assert "info" in names
    return [n for n in names if n not in ("info", "replay")]  # replay writes nothing


@pytest.mark.parametrize("command", _every_command())
def test_every_command_refuses_an_output_place_it_cannot_write(command, sample, tmp_path,
                                                               no_model_loading, monkeypatch):
    """The output place lies under a regular FILE: the folder cannot be made whoever runs the
    test (chmod would not stop root, who runs these tests in CI). Exit 2, one line, no
    traceback, nothing left, and no checkpoint loaded first (checked before the work).

    'report' writes into the existing registration folder it reads, so a file cannot stand in
    the way there: its folder is made to look read-only by patching the write probe (the real
    probe is exercised by the immutable-folder test below and tests/io/test_output_places.py)."""
    run, us = sample
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    out, expected = blocker / "out", ("a_file", "is a file, not a folder")
    if command == "report":
        out, expected = tmp_path / "registration", ("not writable", "read-only file system")
        out.mkdir()
        (out / "result.json").write_text("{}")
        monkeypatch.setattr("comreg_core.io._files._unwritable",
                            lambda folder: "read-only file system")
    before = paths_under(tmp_path)
    _refused(_command_args(command, out, run, us), *expected)
    assert paths_under(tmp_path) == before


@pytest.mark.parametrize("command", _every_command())
def test_every_command_refuses_an_immutable_folder(command, sample, tmp_path, no_model_loading):
    """The issue's case: an immutable folder (``chattr +i``, which stops root too; skipped
    where the file system or container does not allow it)."""
    run, us = sample
    locked = tmp_path / "locked"
    locked.mkdir()
    if command == "report":
        (locked / "result.json").write_text("{}")
    out = locked if command == "report" else locked / "out"
    before = paths_under(tmp_path)
    with immutable(locked):
        _refused(_command_args(command, out, run, us), "not writable")
        assert paths_under(tmp_path) == before


# --- 3. checkpoints that load but are unusable ----------------------------------------------------

def _broken_run(root: Path, change) -> Path:
    run = root / "broken_run"
    run.mkdir()
    state = torch.load(SAMPLE_MODEL, weights_only=True)
    change(state)
    torch.save(state, run / "checkpoint.pt")
    return run


def test_a_checkpoint_with_nan_weights_is_refused_before_the_work(sample, tmp_path):
    def nan_weight(state):
        name = next(k for k, t in state["model"].items() if t.is_floating_point())
        state["model"][name].view(-1)[0] = float("nan")

    run = _broken_run(tmp_path, nan_weight)
    _refused(["register", sample[1], "--model", run, "--out", tmp_path / "out"], "NaN",
             "Train again")
    assert not (tmp_path / "out").exists()


def test_a_checkpoint_whose_weights_do_not_fit_its_config_is_refused(sample, tmp_path):
    run = _broken_run(tmp_path, lambda state: state["model"].pop(next(iter(state["model"]))))
    _refused(["register", sample[1], "--model", run, "--out", tmp_path / "out"], "does not fit")
    assert not (tmp_path / "out").exists()


def test_a_checkpoint_with_a_bad_ct_entry_is_refused(tmp_path):
    from comreg_core.training.checkpoint import CheckpointError, load_checkpoint

    def bad_scale(state):
        state["norm_scale"] = float("inf")

    run = _broken_run(tmp_path, bad_scale)
    with pytest.raises(CheckpointError, match="norm_scale"):
        load_checkpoint(run)


def test_a_random_file_as_checkpoint_never_suggests_unsafe_loading(sample, tmp_path):
    run = tmp_path / "random_run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(np.random.default_rng(0).bytes(5000))
    result = _refused(["register", sample[1], "--model", run, "--out", tmp_path / "out"],
                      "Cannot read the checkpoint", "never runs code")
    assert "weights_only" not in result.stderr


# --- 4. evaluate where every trial fails ------------------------------------------------------------

def test_evaluate_where_every_trial_fails_is_an_error_and_writes_nothing(sample, tmp_path,
                                                                          monkeypatch):
    """A cloud every registration refuses is refused before the trials; when every trial fails
    anyway (here: a method that always raises), nothing is measured, so nothing is written."""
    from comreg_core.errors import InvalidGeometryError
    from comreg_core.register.registrar import Registrar

    same = write_points(PointCloud(np.tile([[10.0, 20.0, 30.0]], (400, 1))), tmp_path / "same.ply")
    _refused(["evaluate", same, "--model", sample[0], "--out", tmp_path / "ev", "--trials", "2",
              "--method", "comreg-plain"], "distinct")

    def always_fails(self, points, seed=0, **kwargs):
        raise InvalidGeometryError("This trial cannot be registered.", "")

    monkeypatch.setattr(Registrar, "register", always_fails)
    result = runner.invoke(app, ["evaluate", str(sample[1]), "--model", str(sample[0]), "--out",
                                 str(tmp_path / "ev"), "--trials", "2", "--method", "comreg-plain"])
    assert result.exit_code == 2, (result.stdout, result.stderr)
    error_lines = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert error_lines == ["error: Every trial failed, so there is nothing to measure; the "
                           "first: This trial cannot be registered. Fix the input above and run "
                           "again."]
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "ev").exists()


def test_evaluate_summary_line_with_no_values():
    from comreg_core.evaluation.evaluate import summary_line as _summary_line

    empty = {"mean": None, "std": None, "median": None}
    summary = {"RTE_mm": empty, "RRE_deg": empty, "runtime_s": empty, "success_rate": 0.0,
               "flip_rate": 0.0, "ambiguous_rate": None, "unflagged_flip_rate": None,
               "failures": 3}
    line = _summary_line(summary)
    assert "median RTE n/a mm" in line and "3 failed" in line


# --- 5. output places of the wrong kind -------------------------------------------------------------

def test_outputs_of_the_wrong_kind(tmp_path):
    (tmp_path / "x.stl").mkdir()
    _refused(["extract-ct", FIBULA_STL, "--out", tmp_path / "x.stl"], "is an existing folder")
    (tmp_path / "taken").write_text("a file")
    _refused(["simulate", FIBULA_STL, "--out", tmp_path / "taken"], "is not a folder")
    (tmp_path / "u.ply").mkdir()
    _refused(["extract-us", SAMPLE_SWEEP, "--out", tmp_path / "u.ply"], "is an existing folder")
    assert paths_under(tmp_path) == {"x.stl", "taken", "u.ply"}


# --- 6. headers that claim more points than the file holds -------------------------------------------

def _huge_ply(path: Path) -> Path:
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\n"
                     b"property float x\nproperty float y\nproperty float z\nelement face 1\n"
                     b"property list uchar int vertex_indices\nend_header\n" + bytes(49))
    return path


def _huge_pcd(path: Path) -> Path:
    path.write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                     b"WIDTH 4000000000\nHEIGHT 1\nPOINTS 4000000000\nDATA binary\n" + bytes(36))
    return path


def test_a_header_claiming_billions_of_points_is_refused(sample, tmp_path):
    for path in (_huge_ply(tmp_path / "huge.ply"), _huge_pcd(tmp_path / "huge.pcd")):
        _refused(["register", path, "--model", sample[0], "--out", tmp_path / "out"],
                 "4,000,000,000", "follow")
    assert not (tmp_path / "out").exists()


def test_info_on_a_huge_ply_header_does_not_crash(tmp_path):
    """In a subprocess: VTK's PLY reader used to crash (segmentation fault) on such a file."""
    path = _huge_ply(tmp_path / "huge.ply")
    done = subprocess.run([sys.executable, "-m", "comreg_core.cli", "info", str(path)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, (done.returncode, done.stderr)
    assert done.stderr.startswith("error: ") and "4,000,000,000" in done.stderr
    assert "Traceback" not in done.stderr


# --- 8. the limit on US points ------------------------------------------------------------------------

def test_limit_us_points_keeps_a_seeded_uniform_subset():
    from comreg_core.registration.geometry.inputs import MAX_US_POINTS, limit_us_points

    points = np.arange(3000 * 3, dtype=np.float64).reshape(3000, 3)
    assert limit_us_points(points) is points and MAX_US_POINTS >= 100_000
    subset = limit_us_points(points, seed=4, limit=1000)
    assert subset.shape == (1000, 3)
    assert np.all(np.diff(subset[:, 0]) > 0)  # original order, no repeats
    assert np.array_equal(subset, limit_us_points(points, seed=4, limit=1000))


def test_register_uses_at_most_the_limit_and_says_so(sample, tmp_path, monkeypatch):
    import json

    monkeypatch.setattr("comreg_core.registration.geometry.inputs.MAX_US_POINTS", 500)
    result = runner.invoke(app, ["register", str(sample[1]), "--model", str(sample[0]), "--out",
                                 str(tmp_path / "reg"), "--no-search", "--device", "cpu"])
    assert result.exit_code == 0, (result.stdout, result.stderr)
    saved = json.loads((tmp_path / "reg" / "result.json").read_text())
    assert saved["n_points"] == 500
    assert any("registered a uniform random subset of 500" in w for w in saved["warnings"])


# --- 9. failed commands leave nothing of their own ------------------------------------------------------

def _sphere(radius: float, open_: bool = False) -> SurfaceMesh:
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    faces = np.asarray(sphere.faces)[:-40] if open_ else np.asarray(sphere.faces)
    return SurfaceMesh(np.asarray(sphere.vertices), faces)


@pytest.mark.parametrize("mesh, message", [
    (_sphere(20.0, open_=True), "not closed"),
    (_sphere(0.02), "metres"),
])
def test_pretrain_on_an_unusable_mesh_makes_no_run_folder(tmp_path, mesh, message):
    path = write_mesh(mesh, tmp_path / "bone.stl")
    _refused(["pretrain", path, "--out", tmp_path / "run", "--epochs", "1"], message)
    assert not (tmp_path / "run").exists()


def test_extract_us_checks_the_compound_output_before_the_work(tmp_path):
    _refused(["extract-us", SAMPLE_SWEEP, "--out", tmp_path / "us.ply", "--compound",
              tmp_path / "vol.foo"], "vol.foo", "extension")
    assert paths_under(tmp_path) == set()


@pytest.mark.parametrize("mesh, message", [
    (_sphere(0.02), "metres"),
    (SurfaceMesh(np.array([[0.0, 0, 0], [30, 0, 0], [0, 30, 0]]), np.array([[0, 1, 2]])),
     "encloses no volume"),
])
def test_extract_ct_refuses_a_metre_scale_mesh_and_a_single_triangle(tmp_path, mesh, message):
    path = write_mesh(mesh, tmp_path / "in.stl")
    _refused(["extract-ct", path, "--out", tmp_path / "out.stl"], message)
    assert not (tmp_path / "out.stl").exists()


# --- 10. messages that say what is wrong -----------------------------------------------------------------

def test_a_folder_given_as_a_file_is_called_a_folder(sample, tmp_path):
    _refused(["info", tmp_path], "is a folder, not a file")
    _refused(["register", tmp_path, "--model", sample[0], "--out", tmp_path / "out"], "is a folder")


def test_identical_points_are_not_called_metres(sample, tmp_path):
    same = write_points(PointCloud(np.tile([[10.0, 20.0, 30.0]], (400, 1))), tmp_path / "same.ply")
    result = _refused(["register", same, "--model", sample[0], "--out", tmp_path / "out",
                       "--device", "cpu"], "1 distinct point")
    assert "metres" not in result.stderr


def test_a_seg_nrrd_without_segment_fields_is_a_label_map(tmp_path):
    from comreg_core.io import Volume, read_segmentation, write_volume

    labels = np.zeros((24, 24, 24), np.uint8)
    labels[6:18, 6:18, 4:20] = 1
    path = write_volume(Volume.from_geometry(labels, spacing=(1.0, 1.0, 1.0)),
                        tmp_path / "bone.seg.nrrd")
    assert not any(line.startswith(b"Segment0_") for line in path.read_bytes().split(b"\n")[:40])
    seg = read_segmentation(path)
    assert [s.label_value for s in seg.segments] == [1]
    result = runner.invoke(app, ["extract-ct", str(path), "--out", str(tmp_path / "bone.stl")])
    assert result.exit_code == 0, result.stderr
    assert "contains no labelled voxels" not in result.stderr


def test_vtk_errors_come_without_vtk_noise(tmp_path):
    path = tmp_path / "huge.vtk"
    path.write_text("# vtk DataFile Version 4.2\nx\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n"
                    "0 0 0 1 0 0 0 1 0\nPOLYGONS 4000000000 16000000000\n3 0 1 2\n")
    result = _refused(["info", path], "Cannot read")
    for noise in ("0x", "vtkInformation", "vtkExecutive", "Modified Time"):
        assert noise not in result.stderr, result.stderr


# --- the one error handler ------------------------------------------------------------------------------

def test_the_error_handler_turns_os_errors_into_one_line_and_bugs_into_exit_1(tmp_path):
    import errno

    from comreg_core.cli.errors import CommandApp

    demo = CommandApp()

    @demo.command("denied")
    def denied():
        raise PermissionError(errno.EROFS, "Read-only file system", str(tmp_path / "x"))

    @demo.command("bug")
    def bug():
        raise TypeError("unsupported format string passed to NoneType.__format__")

    result = runner.invoke(demo, ["denied"])
    assert result.exit_code == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [
        f"error: Read-only file system: '{tmp_path / 'x'}'. The file system is read-only; "
        "choose a place on a writable disk."]
    result = runner.invoke(demo, ["bug"])
    assert result.exit_code == 1 and "Traceback" not in result.stderr
    assert "internal error (TypeError" in result.stderr and "--verbose" in result.stderr
