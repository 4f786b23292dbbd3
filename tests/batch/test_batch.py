"""Issue 36: ``comreg batch`` runs a cohort through the shipped Snakefile (Snakemake).

A 3-case cohort from shared data: the real fibula sweep (frames, tracking, calibration; truth:
identity), a simulated sweep of a tibia-like bone moved by a known transform (truth: its
inverse), and a case whose points file exists but holds no points (fails at run time). All are
registered by the pose search alone (no pretraining). The run is shared by the tests of this
module (about a minute on 2 cores); later tests rerun it.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from comreg_core.cli import app
from tests.batch.cohort import HEADER, fibula_row, identity_truth, simulated_case, write_tibia
from tests.helpers import assert_close

REPO = Path(__file__).resolve().parents[2]
SLURM_PROFILE = REPO / "examples" / "slurm"
SAMPLE_MODEL = REPO / "resources" / "sample" / "fibula_cpu.pt"

runner = CliRunner()


def _invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def _summary(out: Path) -> dict[str, dict[str, str]]:
    with open(out / "summary.csv", newline="", encoding="utf-8") as handle:
        return {row["case"]: row for row in csv.DictReader(handle)}


def _mtimes(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*")
            if p.is_file()}


@pytest.fixture(scope="module")
def cohort(tmp_path_factory, shared_data):
    """``(manifest, folder, tibia US points (n, 3))``: the 3-case manifest (relative paths for
    the files made here, absolute ones into the shared data)."""
    folder = tmp_path_factory.mktemp("cohort")
    write_tibia(folder)
    _, _, tibia_points = simulated_case(folder, "tibia", seed=3)
    identity_truth(folder)
    (folder / "empty.xyz").write_text("# no points\n")
    manifest = folder / "cohort.csv"
    manifest.write_text("\n".join([HEADER, fibula_row("fibula", "identity.tfm"),
                                   "tibia,tibia.stl,tibia_us.ply,,,tibia_gt.tfm",
                                   "empty,tibia.stl,empty.xyz,,,"]) + "\n")
    return manifest, folder, tibia_points


@pytest.fixture(scope="module")
def first_run(cohort, tmp_path_factory):
    """``(CLI result, output folder)`` of the first ``comreg batch`` of the cohort."""
    out = tmp_path_factory.mktemp("batch") / "out"
    result = _invoke("batch", cohort[0], "--out", out, "--cores", "2")
    assert result.exit_code == 0, (result.stdout, result.stderr)
    return result, out


def test_a_cohort_runs_end_to_end_and_records_the_failing_case(cohort, first_run):
    manifest, folder, tibia_points = cohort
    result, out = first_run
    # 3 x extract-ct, 1 x extract-us (the fibula's frames), 3 x register, 3 x report, summary
    assert "ran 11 job(s)" in result.stdout
    assert "2 of 3 cases registered; failed: empty" in result.stdout
    rows = _summary(out)
    assert list(rows) == ["fibula", "tibia", "empty"]
    # the failing case: its own one-line error, the same that 'comreg register' prints for it
    empty = rows["empty"]
    assert (empty["status"], empty["failed_stage"]) == ("failed", "register")
    alone = _invoke("register", folder / "empty.xyz", "--ct", out / "cases/empty/ct_bone.stl",
                    "--out", folder / "alone")
    assert alone.exit_code == 2
    assert empty["error"] == alone.stderr.strip().removeprefix("error: ")
    assert empty["time_extract_ct_s"] and empty["time_register_s"] and not empty["time_report_s"]
    assert empty["verdict"] == "" and empty["success"] == ""  # no truth given, nothing known
    # the registered cases: figures from their result.json, errors against an independent
    # computation of RTE (at the US centroid) and RRE (the angle of R_est^T R_true)
    from comreg_core.io import load_transform, read_points

    for name, us_points in (("tibia", tibia_points),
                            ("fibula", read_points(out / "cases/fibula/us_points.ply").points)):
        row = rows[name]
        saved = json.loads((out / f"cases/{name}/registration/result.json").read_text())
        assert row["status"] == "ok" and row["error"] == ""
        assert row["verdict"] == saved["verdict"] and int(row["n_points"]) == len(us_points)
        assert_close(float(row["residual_median_mm"]), saved["residuals_mm"]["median"],
                     atol=1e-4, what=f"{name} median residual")
        assert_close(float(row["extent_share"]), saved["extent_share"], atol=1e-4)
        T_est = np.asarray(saved["T_ct_us"])
        T_true = load_transform(folder / ("identity.tfm" if name == "fibula"
                                          else "tibia_gt.tfm"))
        centroid = np.append(us_points.mean(axis=0), 1.0)
        rte = np.linalg.norm((T_est @ centroid - T_true @ centroid)[:3])
        cos = (np.trace(T_est[:3, :3].T @ T_true[:3, :3]) - 1.0) / 2.0
        rre = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        assert_close(float(row["RTE_mm"]), rte, atol=2e-4, what=f"{name} RTE")
        assert_close(float(row["RRE_deg"]), rre, atol=2e-3, what=f"{name} RRE")
        assert row["success"] == ("true" if rte < 4 and rre < 5 else "false")
        assert float(row["time_register_s"]) > 0 and float(row["time_report_s"]) > 0
        assert (out / row["report"]).is_file()
    assert rows["tibia"]["success"] == "true"  # a simulated sweep the search gets right
    assert rows["tibia"]["time_extract_us_s"] == ""  # points given: nothing extracted
    assert float(rows["fibula"]["time_extract_us_s"]) > 0
    # summary.html: one row per case, thumbnails and links that exist, the cohort on top
    page = (out / "summary.html").read_text()
    assert page.count("<tr><td>fibula</td>") == page.count("<tr><td>empty</td>") == 1
    assert "cases registered" in page and "success rate" in page
    for name in ("fibula", "tibia"):
        thumbnail = f"cases/{name}/registration/report_images/registered_anterior.png"
        assert f'src="{thumbnail}"' in page and (out / thumbnail).is_file()
        assert f'href="cases/{name}/registration/report.html"' in page


def test_a_rerun_does_nothing(cohort, first_run):
    _, out = first_run
    before = _mtimes(out / "cases")
    planned = _invoke("batch", cohort[0], "--out", out, "--dry-run")
    assert planned.exit_code == 0, planned.stderr
    assert "0 job(s) would run (everything is up to date)" in planned.stdout
    again = _invoke("batch", cohort[0], "--out", out, "--cores", "2")
    assert again.exit_code == 0 and "nothing to do" in again.stdout, again.stderr
    assert _mtimes(out / "cases") == before


def test_a_changed_input_reruns_only_its_case(cohort, first_run):
    """The tibia's points file rewritten without its last point: its register and report and
    the summary run again; the other cases' files are untouched. (Touching a small file without
    changing it does not count: Snakemake compares checksums of files under 1 MB.)"""
    from comreg_core.io import PointCloud, write_points

    manifest, folder, tibia_points = cohort
    _, out = first_run
    write_points(PointCloud(tibia_points[:-1]), folder / "tibia_us.ply")
    planned = _invoke("batch", manifest, "--out", out, "--dry-run")
    assert planned.exit_code == 0, planned.stderr
    jobs = [line.split()[:2] for line in planned.stdout.splitlines()[1:]]
    assert jobs == [["register", "tibia"], ["report", "tibia"], ["summary", "(cohort)"]]
    before = _mtimes(out / "cases")
    result = _invoke("batch", manifest, "--out", out, "--cores", "2")
    assert result.exit_code == 0 and "ran 3 job(s)" in result.stdout, result.stderr
    after = _mtimes(out / "cases")
    changed = {name for name in after if after[name] != before.get(name)}
    assert changed and all(name.startswith("tibia/") for name in changed), changed
    assert "tibia/status/register.json" in changed
    assert int(_summary(out)["tibia"]["n_points"]) == len(tibia_points) - 1


def test_dry_run_on_the_slurm_profile_lists_the_jobs_and_their_resources(cohort, tmp_path,
                                                                          monkeypatch):
    """No sbatch needed (taken off the PATH): a dry run plans with the slurm executor's
    settings and runs nothing. A case with its own model is not pretrained."""
    monkeypatch.setenv("PATH", os.pathsep.join(
        folder for folder in os.environ["PATH"].split(os.pathsep)
        if not (Path(folder) / "sbatch").exists()))
    assert shutil.which("sbatch") is None
    manifest, folder, _ = cohort
    with_model = folder / "with_model.csv"
    with_model.write_text(manifest.read_text() + f"given,tibia.stl,tibia_us.ply,,"
                          f"{SAMPLE_MODEL},\n")
    out = tmp_path / "out"
    result = _invoke("batch", with_model, "--out", out, "--dry-run", "--profile", SLURM_PROFILE,
                     "--pretrain-minutes", "5")
    assert result.exit_code == 0, (result.stdout, result.stderr)
    lines = result.stdout.splitlines()
    assert lines[0] == "17 job(s) would run:"  # 4 + 1 + 3 pretrain + 4 + 4 + summary
    jobs = [line.split() for line in lines[1:]]
    assert sorted(job[1] for job in jobs if job[0] == "pretrain") == ["empty", "fibula", "tibia"]
    for job in jobs:
        fields = dict(item.split("=", 1) for item in job[2:])
        if job[0] == "pretrain":  # the GPU job: the profile sends it to the GPU partition
            assert fields == {"threads": "4", "mem_mb": "16000", "gpu": "1", "runtime": "35",
                              "slurm_partition": "gpu"}, job
        else:
            assert fields["slurm_partition"] == "cpu" and "gpu" not in fields, job
    assert [job[0] for job in jobs].count("register") == 4
    assert not out.exists()  # a dry run does not make the folder


def test_the_snakefile_runs_with_snakemake_itself(cohort, first_run):
    """``snakemake -s SNAKEFILE --config manifest=... out=...`` plans the same (up to date)."""
    from comreg_core.batch import SNAKEFILE

    _, out = first_run
    done = subprocess.run([sys.executable, "-m", "snakemake", "-s", str(SNAKEFILE), "-d",
                           str(out), "-n", "--config", f"manifest={cohort[0]}", f"out={out}"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "Nothing to be done" in done.stdout + done.stderr


def test_comreg_core_imports_without_snakemake():
    code = ("import sys; sys.modules['snakemake'] = None\n"
            "import comreg_core.cli, comreg_core.batch.runner, comreg_core.batch.summary\n"
            "import comreg_core.batch.stage\n"
            "assert sys.modules['snakemake'] is None")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr


def test_without_snakemake_the_command_says_what_to_install(cohort, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "snakemake.api", None)  # import snakemake.api fails
    result = _invoke("batch", cohort[0], "--out", tmp_path / "out")
    assert result.exit_code == 2
    assert result.stderr.strip().splitlines() == [
        "error: 'comreg batch' needs Snakemake, which is not installed. Install the batch "
        "extra: pip install 'comreg[batch]'."]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("profile, message", [
    ("nowhere", "was not found"),
    ("bad", "Snakemake cannot read the profile"),
])
def test_a_profile_snakemake_cannot_use_is_one_line(cohort, tmp_path, profile, message):
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "config.yaml").write_text("executor: slurm\nno-such-option: 3\n")
    result = _invoke("batch", cohort[0], "--out", tmp_path / "out", "--dry-run", "--profile",
                     tmp_path / profile)
    assert result.exit_code == 2, (result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], lines
    assert "Traceback" not in result.stderr
