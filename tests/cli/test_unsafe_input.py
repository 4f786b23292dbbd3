"""Issue 46, no unsafe input, through the ``comreg`` command: a bad verdict calibration, prior
or US points file, and a command line click cannot parse, each end in exit status 2, exactly
one ``error:`` line on stderr and nothing in ``--out``; ``result.json`` is strict JSON, and a
``p_correct`` that is not finite is never OK."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from comreg_core.cli import app
from comreg_core.io import PointCloud, read_mesh, save_transform, write_points
from comreg_core.registration.judgement.calibration import fit_calibration
from tests.helpers import FIBULA_STL, SHARED_DATA

REPO = Path(__file__).resolve().parents[2]
SAMPLE_SEGMENTATION = REPO / "resources" / "sample" / "fibula.seg.nrrd"
FCSV = ("# Markups fiducial file version = 5.6\n# CoordinateSystem = LPS\n"
        "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n")

runner = CliRunner()


@pytest.fixture(scope="module")
def case(tmp_path_factory, shared_data):
    """``{"dir", "us", "calibration"}``: a patch of the fibula's CT surface (900 points, the CT
    frame) and the JSON of a valid verdict calibration of that CT."""
    import trimesh

    from comreg_core.training.checkpoint import mesh_fingerprint

    root = tmp_path_factory.mktemp("unsafe")
    mesh = read_mesh(FIBULA_STL)
    points = trimesh.Trimesh(mesh.vertices, mesh.faces).sample(3000, seed=1)
    patch = points[points[:, 2] > np.percentile(points[:, 2], 70)]
    us = write_points(PointCloud(patch, mesh.space), root / "us.ply")
    rng = np.random.default_rng(0)
    p_raw = rng.uniform(0, 1, 60)
    calibration = fit_calibration(p_raw, p_raw > 0.2, ct_length_mm=404.0,
                                  ct_fingerprint=mesh_fingerprint(mesh))
    return {"dir": root, "us": us, "calibration": calibration.to_json()}


def _refused(args, out: Path, *contains: str):
    """Run ``comreg ARGS``: exit 2, one ``error:`` line on stderr holding ``contains``, no
    usage box or traceback, and ``out`` not made."""
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 2, (result.exit_code, result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "Traceback" not in result.stderr and "╭" not in result.stderr
    for text in contains:
        assert text in lines[0], (text, lines[0])
    assert not out.exists(), sorted(p.name for p in out.iterdir())
    return lines[0]


def _register(case, out: Path, *extra):
    return ["register", case["us"], "--ct", FIBULA_STL, "--out", out, *extra]


# --- 1. the verdict calibration ----------------------------------------------------------------

def _changed(data: dict, key: str, value) -> dict:
    changed = dict(data)
    if value is _DROP:
        del changed[key]
    else:
        changed[key] = value
    return changed


_DROP = object()
BAD_CALIBRATIONS = {  # name: (key, value, what the error says)
    "NaN knots": ("knots", {"p_raw": [0.0, 1.0], "p_correct": [math.nan] * 2}, "'NaN'"),
    "knots of two lengths": ("knots", {"p_raw": [0.0, 1.0], "p_correct": [0.5]},
                             "not two lists of the same length"),
    "knots as text": ("knots", "0 1", "'knots' is not {p_raw, p_correct}"),
    "knot as text": ("knots", {"p_raw": [0.0, 1.0], "p_correct": [0.1, "2"]},
                     "'knots p_correct' is '2'"),
    "falling knots": ("knots", {"p_raw": [0.0, 1.0], "p_correct": [0.9, 0.1]}, "falls"),
    "knots not from 0 to 1": ("knots", {"p_raw": [0.2, 1.0], "p_correct": [0.1, 0.9]},
                              "does not rise from 0 to 1"),
    "infinite CT length": ("ct_length_mm", math.inf, "'Infinity'"),
    "CT length of 0": ("ct_length_mm", 0.0, "'ct_length_mm' is 0"),
    "share above 1": ("correct_share", 1.5, "'correct_share' is 1.5"),
    "low OK probability": ("ok_probability", 0.2, "'ok_probability' is 0.2"),
    "null OK probability": ("ok_probability", None, "'ok_probability' is None"),
    "no sweeps": ("sweeps", 0, "'sweeps' is 0"),
    "sweeps as text": ("sweeps", "60", "'sweeps' is '60'"),
    "reliability row": ("reliability", [{"p_low": 0.0}], "'reliability' row"),
    "no knots": ("knots", _DROP, "lacks 'knots'"),
    "unknown entry": ("scale", 2.0, "unknown entry 'scale'"),
    "another format": ("format", 5, "'format' is not 4"),
    "the oldest format": ("format", 1, "older ComReg (format 1)"),
    "the older format": ("format", 2, "older ComReg (format 2"),
    "the last format": ("format", 3, "older ComReg (format 3"),
    "bad fingerprint": ("ct_fingerprint", {"sha256": "abc"}, "'ct_fingerprint'"),
    "unknown prior": ("settings", {"prior": "pointer"}, "'settings prior' is 'pointer'"),
}


@pytest.mark.parametrize("name", BAD_CALIBRATIONS)
def test_a_bad_verdict_calibration_is_refused_before_anything_is_written(case, name):
    key, value, message = BAD_CALIBRATIONS[name]
    path = case["dir"] / f"calibration {name}.json"
    path.write_text(json.dumps(_changed(case["calibration"], key, value)))  # NaN as 'NaN'
    out = case["dir"] / f"out {name}"
    _refused(_register(case, out, "--verdict-calibration", path), out, message, str(path))


def test_a_calibration_of_another_ct_is_refused_before_anything_is_written(case):
    other = dict(case["calibration"], ct_fingerprint={"sha256": "0" * 64})
    path = case["dir"] / "other_ct.json"
    path.write_text(json.dumps(other))
    out = case["dir"] / "out other ct"
    _refused(_register(case, out, "--verdict-calibration", path), out, "another CT mesh")


def test_live_refuses_a_calibration_of_another_ct_before_it_listens(case):
    """``comreg live --verdict-calibration`` checks the calibration's CT before it connects:
    one line, exit 2, nothing written (no server is needed to find out)."""
    other = dict(case["calibration"], ct_fingerprint={"sha256": "0" * 64})
    path = case["dir"] / "other_ct_live.json"
    path.write_text(json.dumps(other))
    out = case["dir"] / "out live other ct"
    _refused(["live", "--igtl", "127.0.0.1:9", "--ct", FIBULA_STL, "--out", out,
              "--verdict-calibration", path, "--inline-search", "--connect-timeout", "1"],
             out, "another CT mesh")


def test_a_calibration_for_registrations_that_know_more_is_refused(case):
    """A calibration fitted with landmarks (``comreg calibrate --prior landmark``) would
    over-rate a registration without them: register and live refuse it before any work."""
    landmark = dict(case["calibration"], settings={"prior": "landmark"})
    path = case["dir"] / "landmark.json"
    path.write_text(json.dumps(landmark))
    out = case["dir"] / "out landmark"
    line = _refused(_register(case, out, "--verdict-calibration", path), out,
                    "prior of kind 'landmark', this one has 'none'", "--prior none")
    assert str(path) in line
    out = case["dir"] / "out live landmark"
    _refused(["live", "--igtl", "127.0.0.1:9", "--ct", FIBULA_STL, "--out", out,
              "--verdict-calibration", path, "--inline-search", "--connect-timeout", "1"],
             out, "prior of kind 'landmark', this one has 'none'")


def test_a_calibration_for_registrations_that_know_less_is_used_with_a_warning(case):
    """A calibration fitted without a prior under-rates a registration with an initial pose:
    it is used, and result.json's warnings say so."""
    path = case["dir"] / "no_prior.json"
    path.write_text(json.dumps(case["calibration"]))
    init = case["dir"] / "init.tfm"
    save_transform(np.eye(4), init)  # the patch is in the CT frame: the truth
    out = case["dir"] / "out init"
    result = runner.invoke(app, [str(a) for a in _register(
        case, out, "--verdict-calibration", path, "--init", init)])
    assert result.exit_code == 0, (result.stdout, result.stderr)
    saved = _strict((out / "result.json").read_text())
    notes = [w for w in saved["warnings"] if "under-rates" in w]
    assert len(notes) == 1 and "kind 'none', this one has 'init'" in notes[0], saved["warnings"]
    assert saved["prior"]["T_init"] is not None


def test_a_calibration_that_is_not_a_json_object_is_refused(case):
    path = case["dir"] / "list.json"
    path.write_text("[1, 2, 3]")
    out = case["dir"] / "out list"
    _refused(_register(case, out, "--verdict-calibration", path), out, "not a JSON object")


def _strict(text: str):
    """``json.loads`` that refuses NaN and Infinity (what every strict JSON reader does)."""
    def refuse(token):
        raise ValueError(f"{token} in strict JSON")

    return json.loads(text, parse_constant=refuse)


def test_a_p_correct_that_is_not_finite_is_check_and_null_in_strict_json(case, monkeypatch):
    """Defence in depth: whatever makes ``p_correct`` NaN, the verdict is CHECK and result.json
    stays strict JSON, the null's reason recorded."""
    path = case["dir"] / "calibration.json"
    path.write_text(json.dumps(case["calibration"]))
    import sys

    import comreg_core.register.judge  # noqa: F401  (the module, shadowed by its function)

    monkeypatch.setattr(sys.modules["comreg_core.register.judge"], "calibrated",
                        lambda p_raw, knots: math.nan)
    out = case["dir"] / "nan p_correct"
    result = runner.invoke(app, [str(a) for a in _register(case, out, "--verdict-calibration",
                                                           path)])
    assert result.exit_code == 0, (result.stdout, result.stderr)
    saved = _strict((out / "result.json").read_text())
    assert saved["verdict"] == "check" and saved["p_correct"] is None
    assert any("probability of only nan" in reason for reason in saved["verdict_reasons"])
    assert saved["verdict_figures"]["p_correct"] is None
    assert saved["null_reasons"].items() >= {"/p_correct": "not finite (NaN)",
                                             "/verdict_figures/p_correct": "not finite (NaN)"
                                             }.items()


# --- 2. priors and US points -------------------------------------------------------------------

def _fcsv(path: Path, rows) -> Path:
    path.write_text(FCSV + "".join(f"{i},{x},{y},{z},0,0,0,1,1,1,0,{label},,\n"
                                   for i, (x, y, z, label) in enumerate(rows)))
    return path


def _write(path: Path, data) -> Path:
    path.write_text(json.dumps(data))
    return path


def _mrk_json(path: Path, positions) -> Path:
    points = [{"label": label, "position": position} for label, position in positions]
    return _write(path, {"markups": [{"coordinateSystem": "LPS", "controlPoints": points}]})


def test_bad_priors_and_points_are_refused_before_anything_is_written(case):
    d = case["dir"]
    far = np.eye(4)
    far[:3, 3] = [1e200, 0.0, 0.0]
    us_lm = _fcsv(d / "us_landmarks.fcsv", [(0, 0, 0, "a"), (10, 0, 0, "b")])
    far_points = read_mesh(FIBULA_STL).vertices[:100] + [0.0, 0.0, 1e200]
    cases = {
        "init beyond 1 km": (["--init", save_transform(far, d / "far.tfm")],
                             "more than 1 km from the origin"),
        "landmark beyond 1 km": (["--landmarks", _fcsv(d / "far.fcsv", [(1e300, 0, 0, "a"),
                                                                       (10, 0, 0, "b")]), us_lm],
                                 "more than 1 km from the origin"),
        "controlPoints not a list": (["--landmarks", _write(d / "five.mrk.json", {
            "markups": [{"controlPoints": 5}]}), us_lm], "'controlPoints' is not a list"),
        "a coordinate as text": (["--landmarks", _mrk_json(d / "text.mrk.json", [
            ("a", ["1", 0, 0]), ("b", [10, 0, 0])]), us_lm], "three numbers"),
    }
    for k, (name, (extra, message)) in enumerate(cases.items()):
        out = d / f"out prior {k}"
        _refused(_register(case, out, *extra), out, message)
    us_far = d / "far_us.xyz"  # written by hand: ComReg writes no such file
    np.savetxt(us_far, far_points, header="SPACE=LPS")
    out = d / "out far us"
    _refused(["register", us_far, "--ct", FIBULA_STL, "--out", out], out,
             "more than 1 km from the origin", str(us_far))


def test_a_sweep_the_report_cannot_read_is_refused_before_anything_is_written(case):
    """``register --sweep`` records the sweep for the report's frames: a folder without the
    sweep's files, or a probe calibration that does not read, is refused by ``register``
    itself, not by ``report`` after the registration."""
    d = case["dir"]
    (d / "no sweep").mkdir()
    out = d / "out bad sweep"
    _refused(_register(case, out, "--sweep", d / "no sweep"), out, "tracking.csv",
             "does not exist")
    (d / "bad calibration.json").write_text("{not json")
    _refused(_register(case, out, "--sweep", SHARED_DATA / "ultrabones100k-fibula",
                       "--probe-calibration", d / "bad calibration.json"), out,
             "bad calibration.json")


# --- 4. command lines click cannot parse ------------------------------------------------------

def test_usage_errors_are_one_line_naming_the_command_help(case):
    out = case["dir"] / "out usage"
    ct = FIBULA_STL
    cases = {
        "calibrate": [["calibrate", ct, "--sweeps", "0", "--out", out],  # out of range
                      ["calibrate", ct, "--sweeps", "many", "--out", out],  # not a number
                      ["calibrate", "--out", out],  # missing argument
                      ["calibrate", ct],  # missing option
                      ["calibrate", ct, "--out", out, "--bogus"]],  # unknown option
        "register": [["register", case["us"], "--ct", ct, "--out", out, "--landmarks", "a"],
                     ["register", case["us"], "--ct", ct, "--out", out,
                      "--landmark-tolerance", "nan"]],
        "extract-ct": [["extract-ct", SAMPLE_SEGMENTATION, "--out", out / "bone.stl",
                        "--method", "nope"]],
        "": [["nosuch"], ["--bogus"]],
    }
    for command, argument_lists in cases.items():
        where = f"comreg {command}".strip()
        for args in argument_lists:
            line = _refused(args, out, f"(see '{where} --help').")
            assert "Usage:" not in line


def test_the_console_command_prints_one_line_and_help_is_unchanged(tmp_path):
    out = tmp_path / "calibration"
    comreg = Path(sys.executable).with_name("comreg")  # the console script, as users run it
    done = subprocess.run([str(comreg), "calibrate", str(FIBULA_STL), "--sweeps", "0", "--out",
                           str(out)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines() == [
        "error: Invalid value for '--sweeps': Input should be greater than or equal to 4 "
        "(see 'comreg calibrate --help')."]
    assert not out.exists()
    shown = runner.invoke(app, ["calibrate", "--help"])
    assert shown.exit_code == 0 and "Usage: comreg calibrate" in shown.stdout
    assert "--sweeps" in shown.stdout and not shown.stderr
