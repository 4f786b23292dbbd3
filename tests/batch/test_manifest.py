"""The cohort manifest of ``comreg batch``: read from CSV or YAML, every problem found before
anything runs, one line each with its row (data rows from 1, the CSV header is row 0)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from comreg_core.batch.manifest import COLUMNS, ManifestError, load_manifest
from comreg_core.cli import app

KNOWN = ", ".join(COLUMNS)


@pytest.fixture
def folder(tmp_path) -> Path:
    """Input files of every kind a manifest names (validation reads only names and kinds)."""
    for name in ("bone.stl", "labels.seg.nrrd", "us.ply", "sweep.igs.mha", "cal.xml",
                 "gt.tfm", "init.tfm", "ct.mrk.json", "us.fcsv", "notes.docx"):
        (tmp_path / name).write_text("x")
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "tracking.csv").write_text("x")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "checkpoint.pt").write_text("x")
    (tmp_path / "not_a_run").mkdir()
    return tmp_path


def _problems(path: Path) -> list[str]:
    with pytest.raises(ManifestError) as caught:
        load_manifest(path)
    return caught.value.lines


def test_a_full_csv_row_gives_a_case_with_absolute_paths(folder, monkeypatch):
    manifest = folder / "cohort.csv"
    manifest.write_text(
        "case, ct, us, label, calibration, model, gt, init, init_tolerance, landmarks_ct, "
        "landmarks_us\n"
        "p01, labels.seg.nrrd, sweep.igs.mha, 2, cal.xml, run, gt.tfm, init.tfm, \"20,15\", "
        "ct.mrk.json, us.fcsv\n"
        "\n"
        "p-02.b, bone.stl, frames,,,,,,,,\n")
    monkeypatch.chdir(folder / "not_a_run")  # relative paths are the manifest's, not the cwd's
    first, second = load_manifest(Path("..") / "cohort.csv")
    assert (first.name, first.row, first.label, first.init_tolerance) == ("p01", 1, 2, "20,15")
    assert first.ct == folder / "labels.seg.nrrd" and first.model == folder / "run"
    assert first.landmarks_us == folder / "us.fcsv" and first.ct.is_absolute()
    assert not first.ct_is_mesh and not first.us_is_points
    assert (second.name, second.row, second.us) == ("p-02.b", 2, folder / "frames")
    assert second.ct_is_mesh and second.us_is_tracked_sweep and second.gt is None


def test_header_problems_are_listed_together(folder):
    manifest = folder / "cohort.csv"
    manifest.write_text("case,ct,colour\np01,bone.stl,red\n")
    assert _problems(manifest) == [
        f"{manifest} row 0 (header): unknown column 'colour' (known: {KNOWN})",
        f"{manifest} row 0 (header): the required column 'us' is missing"]


def test_every_problem_of_every_row_is_one_line_with_its_row(folder):
    manifest = folder / "cohort.csv"
    rows = [
        "case,ct,us,label,calibration,model,init,init_tolerance,landmarks_ct,landmarks_us",
        "p01,bone.stl,us.ply,,,,,,,",                       # 1: fine
        "P01,bone.stl,us.ply,,,,,,,",                       # 2: the same name as row 1
        "a/b,missing.stl,us.ply,,,,,,,",                    # 3: unsafe name, missing file
        "p04,frames,,,,,,,,",                               # 4: a folder as ct, no us
        "p05,notes.docx,us.ply,x,,,,,,",                    # 5: a format ct cannot be; label
        "p06,bone.stl,us.ply,3,cal.xml,not_a_run,,,,",      # 6: label of a mesh, calibration
        "p07,bone.stl,sweep.igs.mha,,,,,abc,ct.mrk.json,",  # 7: tolerance, landmarks
        "p08,bone.stl,us.ply,,,,,,,,extra",                 # 8: one value too many
        "p09,bone.stl,frames,,,,init.tfm,\"30,30\",ct.mrk.json,us.fcsv",  # 9: fine
    ]
    manifest.write_text("\n".join(rows) + "\n")
    row = f"{manifest} row"
    assert _problems(manifest) == [
        f"{row} 2: case 'P01' is also in row 1",
        f"{row} 3: case name 'a/b' cannot be a folder name: use up to 100 letters, digits, '.', "
        "'_' and '-', starting with a letter or digit",
        f"{row} 3: 'ct' path 'missing.stl' does not exist",
        f"{row} 4: 'us' is missing or empty",
        f"{row} 4: 'ct' ('frames') is a folder, not a file",
        f"{row} 5: 'ct' ('notes.docx') is not a CT label map, .seg.nrrd or bone mesh (takes "
        ".mha, .mhd, .nhdr, .nrrd, .obj, .ply, .seg.nrrd, .stl, .vtk, .vtp)",
        f"{row} 5: 'label' is 'x', not a whole number >= 0",
        f"{row} 6: 'label'/'segment' pick a segment of a label map, but 'ct' is a mesh",
        f"{row} 6: 'calibration' belongs to a tracked sweep, but 'us' is a points file",
        f"{row} 6: 'model' ('not_a_run') is not a run folder of 'comreg pretrain' (no "
        "checkpoint.pt in it)",
        f"{row} 7: 'init_tolerance' is given without 'init'",
        f"{row} 7: 'init_tolerance' is 'abc', not DEG,MM (e.g. 30,30)",
        f"{row} 7: 'landmarks_ct' is given without 'landmarks_us' (landmarks come in pairs)",
        f"{row} 8: 1 more value(s) than the header has columns (a comma inside a value needs "
        "quotes)"]


def test_yaml_manifests_have_the_same_columns_and_row_numbers(folder):
    listed = folder / "cohort.yaml"
    listed.write_text("- {case: 17, ct: bone.stl, us: us.ply, label: null}\n"
                      "- {case: p02, ct: bone.stl, colour: red}\n"
                      "- {case: p03, ct: labels.seg.nrrd, us: us.ply, label: 4, "
                      "segment: fibula}\n")
    assert _problems(listed) == [
        f"{listed} row 2: unknown column 'colour' (known: {KNOWN})",
        f"{listed} row 2: 'us' is missing or empty"]
    wrapped = folder / "cohort.yml"
    wrapped.write_text("cases:\n  - {case: 17, ct: bone.stl, us: us.ply}\n"
                       "  - {case: p03, ct: labels.seg.nrrd, us: frames, label: 4, "
                       "segment: fibula, calibration: cal.xml}\n")
    first, second = load_manifest(wrapped)
    assert (first.name, second.label, second.segment) == ("17", 4, "fibula")
    assert second.calibration == folder / "cal.xml"


@pytest.mark.parametrize("name, text, problem", [
    ("cohort.csv", "case,ct,us\n", "has no cases"),
    ("cohort.txt", "case,ct,us\n", "a manifest is a .csv, .yaml or .yml file"),
    ("cohort.yaml", "case: [unclosed\n", "not valid YAML"),
    ("cohort.yaml", "case: p01\n", "a YAML manifest is a list of cases"),
    ("missing.csv", None, "does not exist"),
])
def test_a_file_that_is_no_manifest(folder, name, text, problem):
    path = folder / name
    if text is not None:
        path.write_text(text)
    lines = _problems(path)
    assert len(lines) == 1 and lines[0].startswith(f"{path}") and problem in lines[0], lines


def test_the_command_prints_every_problem_and_exits_2_before_any_work(folder):
    manifest = folder / "cohort.csv"
    manifest.write_text("case,ct,us\np01,bone.stl,nothing.ply\np01,bone.stl,us.ply\n")
    out = folder / "out"
    result = CliRunner().invoke(app, ["batch", str(manifest), "--out", str(out)])
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        f"error: {manifest} row 1: 'us' path 'nothing.ply' does not exist",
        f"error: {manifest} row 2: case 'p01' is also in row 1"]
    assert "Traceback" not in result.stdout + result.stderr
    assert not out.exists()
