"""What the Snakefile runs per case (:mod:`comreg_core.batch.plan`) and how a stage records its
outcome (:mod:`comreg_core.batch.stage`): the same ``comreg`` commands a user would type, and
a status file whether they succeed or fail."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from comreg_core.batch.plan import CasePlan, plan_cases
from comreg_core.batch.stage import read_status, run_stage
from comreg_core.batch.summary import cohort_figures
from comreg_core.cli import app
from tests.helpers import FIBULA_STL


@pytest.fixture
def folder(tmp_path) -> Path:
    for name in ("labels.seg.nrrd", "bone.stl", "us.ply", "init.tfm", "ct.mrk.json",
                 "us.mrk.json", "cal.json"):
        (tmp_path / name).write_text("x")
    (tmp_path / "sweep frames").mkdir()  # a space in the name: quoting
    for name in ("tracking.csv", "a.png", ".hidden"):
        (tmp_path / "sweep frames" / name).write_text("x")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "checkpoint.pt").write_text("x")
    (tmp_path / "cohort.csv").write_text(
        "case,ct,us,label,calibration,model,init,init_tolerance,landmarks_ct,landmarks_us\n"
        "full,labels.seg.nrrd,sweep frames,3,cal.json,,init.tfm,\"20,10\",ct.mrk.json,"
        "us.mrk.json\n"
        "points,bone.stl,us.ply,,,,,,,\n"
        "given,bone.stl,us.ply,,,run,,,,\n")
    return tmp_path


def test_the_commands_of_each_stage(folder):
    out = folder / "out"
    plans = plan_cases(folder / "cohort.csv", out, pretrain_minutes=20)
    full, points, given = plans["full"], plans["points"], plans["given"]
    case = out / "cases" / "full"
    assert full.stages == ["extract_ct", "pretrain", "extract_us", "register", "report"]
    assert full.command("extract_ct") == ["extract-ct", str(folder / "labels.seg.nrrd"),
                                          "--out", str(case / "ct_bone.stl"), "--label", "3"]
    assert full.command("pretrain") == ["pretrain", str(case / "ct_bone.stl"), "--out",
                                        str(case / "run"), "--max-minutes", "20", "--preset",
                                        "cpu"]
    assert full.command("extract_us") == ["extract-us", str(folder / "sweep frames"), "--out",
                                          str(case / "us_points.ply"), "--probe-calibration",
                                          str(folder / "cal.json")]
    assert full.command("register") == [
        "register", str(case / "us_points.ply"), "--out", str(case / "registration"), "--ct",
        str(case / "ct_bone.stl"), "--model", str(case / "run"), "--sweep",
        str(folder / "sweep frames"), "--probe-calibration", str(folder / "cal.json"), "--init",
        str(folder / "init.tfm"), "--init-tolerance", "20,10", "--landmarks",
        str(folder / "ct.mrk.json"), str(folder / "us.mrk.json")]
    assert full.command("report") == ["report", str(case / "registration")]
    assert full.after("register") == [full.status(s) for s in
                                      ("extract_ct", "pretrain", "extract_us")]
    # a folder input is the files in it (hidden ones aside), so a changed frame counts
    assert full.input_files("extract_us") == [folder / "sweep frames" / "a.png",
                                              folder / "sweep frames" / "tracking.csv",
                                              folder / "cal.json"]
    # points given: nothing to extract; a model given: not pretrained, registered with it
    assert points.stages == ["extract_ct", "pretrain", "register", "report"]
    assert points.command("register")[:2] == ["register", str(folder / "us.ply")]
    assert points.input_files("register") == [folder / "us.ply"]
    assert given.stages == ["extract_ct", "register", "report"]
    assert given.command("register")[-2:] == ["--model", str(folder / "run")]
    # without a budget: the pose search alone (--ct, no --model)
    alone = CasePlan(points.case, out)
    assert alone.stages == ["extract_ct", "register", "report"]
    assert "--model" not in alone.command("register")


def test_the_shell_command_quotes_every_path(folder):
    plan = plan_cases(folder / "cohort.csv", folder / "out dir")["full"]
    words = shlex.split(plan.shell_command("register", python="/opt/py thon"))
    assert words[:3] == ["/opt/py thon", "-m", "comreg_core.batch.stage"]
    split = words.index("--")
    assert words[split + 1:-3] == plan.command("register")
    assert words[-3:] == [">", str(plan.log("register")), "2>&1"]


def test_a_failing_command_is_recorded_with_its_own_error_line(tmp_path):
    status = tmp_path / "cases" / "c" / "status" / "extract_ct.json"
    command = ["extract-ct", str(tmp_path / "missing.stl"), "--out", str(tmp_path / "x.stl")]
    record = run_stage("c", "extract_ct", status, command)
    alone = CliRunner().invoke(app, command)  # the same command typed by a user
    assert alone.exit_code == 2
    assert read_status(status) == record
    assert record["status"] == "failed" and record["failed_stage"] == "extract_ct"
    assert record["exit_code"] == 2 and record["command"] == ["comreg", *command]
    assert record["error"] == alone.stderr.strip().removeprefix("error: ")


def test_a_stage_after_a_failed_one_passes_the_failure_on_without_running(tmp_path):
    upstream = tmp_path / "cases" / "c" / "status" / "extract_ct.json"
    upstream.parent.mkdir(parents=True)
    upstream.write_text(json.dumps({"status": "failed", "failed_stage": "extract_ct",
                                    "error": "The mesh is not closed."}))
    mesh = tmp_path / "cases" / "c" / "ct_bone.stl"
    record = run_stage("c", "register", upstream.with_name("register.json"),
                       ["extract-ct", str(FIBULA_STL), "--out", str(mesh)], after=[upstream])
    assert (record["status"], record["failed_stage"], record["error"]) == (
        "failed", "extract_ct", "The mesh is not closed.")
    assert record["exit_code"] is None and not mesh.exists()  # the command did not run


def test_a_stage_clears_only_its_own_outputs_in_its_case_folder(tmp_path):
    status = tmp_path / "cases" / "c" / "status" / "register.json"
    stale = tmp_path / "cases" / "c" / "registration"
    stale.mkdir(parents=True)
    (stale / "completion_ct.ply").write_text("from an earlier run")
    outside = tmp_path / "keep.txt"
    outside.write_text("not ours")
    with pytest.raises(ValueError, match="not inside the case folder"):
        run_stage("c", "register", status, ["info", str(FIBULA_STL)], fresh=[outside])
    assert outside.exists() and not status.exists()
    record = run_stage("c", "register", status, ["info", str(FIBULA_STL)], fresh=[stale])
    assert record["status"] == "ok" and record["exit_code"] == 0 and record["error"] is None
    assert not stale.exists()


def test_the_stage_runs_as_a_module(tmp_path):
    """How the Snakefile's rules call it: a process that exits 0 once the status is written."""
    status = tmp_path / "cases" / "c" / "status" / "report.json"
    done = subprocess.run([sys.executable, "-m", "comreg_core.batch.stage", "--case", "c",
                           "--stage", "report", "--status", str(status), "--", "report",
                           str(tmp_path / "no_registration")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    record = read_status(status)
    assert record["status"] == "failed" and "result.json" in record["error"]
    assert done.stdout.strip() == f"c report: failed (report: {record['error']})"


def test_the_cohort_success_rate_counts_failed_cases_with_a_truth():
    rows = [{"status": "ok", "verdict": "ok", "success": True},
            {"status": "ok", "verdict": "check", "success": False},
            {"status": "failed", "verdict": None, "success": False},  # a truth, but failed
            {"status": "failed", "verdict": None, "success": None}]   # no truth
    for row in rows:
        row.update({f"time_{stage}_s": None for stage in
                    ("extract_ct", "pretrain", "extract_us", "register", "report")})
    rows[0]["time_register_s"], rows[1]["time_register_s"] = 2.0, 4.0
    figures = cohort_figures(rows)
    assert (figures["cases"], figures["registered"], figures["failed"]) == (4, 2, 2)
    assert figures["verdict OK"] == 1 and figures["cases with a gt"] == 3
    assert figures["success rate"] == pytest.approx(1 / 3)
    assert figures["register median s"] == 3.0 and figures["register total s"] == 6.0
    assert "report median s" not in figures
