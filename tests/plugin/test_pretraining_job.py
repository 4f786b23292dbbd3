"""``comreg pretrain`` in the background (comreg_plugin.pretraining_job): progress read from the
run's files, the user's status line, cancel, the run folder checks and the command it starts.
Fake trainer processes keep these fast; a real failed CLI run goes through the Logic."""

from __future__ import annotations

import os
import signal
import stat
import sys
from pathlib import Path

import pytest

from comreg_core.errors import ComRegError
from comreg_plugin.pretraining_job import (REPO_ROOT, PretrainingJob, PretrainingStatus,
                                           checkRunFolder, launchPretraining)

# A trainer stand-in: writes what comreg pretrain writes (config, log rows, checkpoint), exits 0.
FAKE_TRAINER = """
from pathlib import Path
Path("config.yaml").write_text("training:\\n  epochs: 4\\n  max_minutes: 0\\n")
Path("training_log.csv").write_text(
    "epoch,loss,val_RTE_mm_median,val_RRE_deg_median\\n1,0.5,,\\n2,0.25,3.5,4.25\\n")
Path("checkpoint.pt").write_bytes(b"a checkpoint")
print("pretraining done")
"""


def _job(tmp_path, code: str, **kwargs) -> PretrainingJob:
    return PretrainingJob([sys.executable, "-c", code], tmp_path / "run", **kwargs)


def _status(**kwargs) -> PretrainingStatus:
    values = dict(state="running", progress=0.5, epoch=3, totalEpochs=None, loss=None,
                  validation={}, elapsedSeconds=1.0, returnCode=None, message="",
                  runDirectory=Path("run"))
    values.update(kwargs)
    return PretrainingStatus(**values)


def test_a_finished_job_reports_its_epochs_loss_and_validation(tmp_path):
    job = _job(tmp_path, FAKE_TRAINER)
    status = job.wait(timeoutSeconds=60, intervalSeconds=0.05)
    assert status.state == "finished" and status.returnCode == 0 and status.progress == 1.0
    assert status.epoch == 2 and status.totalEpochs == 4  # the total from the run's config
    assert status.loss == 0.25
    assert status.validation == {"val_RTE_mm_median": 3.5, "val_RRE_deg_median": 4.25}
    assert status.message == "pretraining done" and status.runDirectory == tmp_path / "run"
    assert status.describe() == ("finished: epoch 2 of 4, loss 0.2500, validation RTE 3.50 mm, "
                                 "RRE 4.25 deg")
    assert not job.running and job.consolePath.read_text().strip() == "pretraining done"


def test_a_failed_job_reports_the_cli_error_line(tmp_path):
    job = _job(tmp_path, "print('reading'); print('error: the mesh is empty'); "
                         "raise SystemExit(2)", totalEpochs=5)
    status = job.wait(timeoutSeconds=60, intervalSeconds=0.05)
    assert status.state == "failed" and status.returnCode == 2 and status.epoch == 0
    assert status.message == "the mesh is empty"
    assert status.describe() == "failed: epoch 0 of 5 - the mesh is empty"


def test_status_lines():
    assert _status().describe() == "running: epoch 3"
    assert _status(totalEpochs=10, loss=0.123456).describe() == \
        "running: epoch 3 of 10, loss 0.1235"
    assert _status(validation={"val_RTE_mm_median": 2.0}).describe() == \
        "running: epoch 3, validation RTE 2.00 mm, RRE nan deg"
    assert _status(state="cancelled", message="cancelled").describe() == "cancelled: epoch 3"


def test_cancel_stops_the_process_and_removes_temporary_files(tmp_path):
    """Started as by a program a shell put in the background (SIGINT ignored, which children
    inherit), the job is still interrupted, not killed after the timeout."""
    ours = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        job = _job(tmp_path, "import time; time.sleep(120)")
    finally:
        signal.signal(signal.SIGINT, ours)
    assert job.running and job.poll().state == "running"
    leftover = job.runDirectory / ".checkpoint.pt.abc123.tmp.pt"
    leftover.write_bytes(b"half a checkpoint")
    assert job.temporaryFiles() == [leftover]
    status = job.cancel(timeoutSeconds=20)
    assert status.state == "cancelled" and status.returnCode == -signal.SIGINT  # not SIGKILL
    assert not job.running and not leftover.exists()
    with pytest.raises(ComRegError, match="not running"):
        job.cancel()


def test_the_run_folder_check(tmp_path):
    run = tmp_path / "run"
    assert checkRunFolder(run) == run.resolve() and not run.exists()  # nothing made yet
    run.mkdir()
    (run / PretrainingJob.CHECKPOINT_NAME).write_bytes(b"a checkpoint")
    with pytest.raises(ComRegError, match="already holds a training run"):
        checkRunFolder(run)
    assert checkRunFolder(run, resume=True) == run.resolve()
    (tmp_path / "a file").write_text("not a folder")
    with pytest.raises(ComRegError, match="is not a folder"):
        checkRunFolder(tmp_path / "a file")


def _fake_python(tmp_path) -> Path:
    """An executable that prints its arguments and PYTHONPATH, then exits 0."""
    path = tmp_path / "fake_python"
    path.write_text('#!/bin/sh\necho "$@"\necho "PYTHONPATH=$PYTHONPATH"\n')
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return path


@pytest.mark.skipif(os.name == "nt", reason="a POSIX shell script stands in for Python")
def test_the_command_it_starts(tmp_path):
    python, mesh = _fake_python(tmp_path), tmp_path / "ct.stl"
    mesh.write_bytes(b"")
    run = tmp_path / "run"
    job = launchPretraining(None, mesh, run, preset="cpu", device="cpu", maxMinutes=2.5,
                            epochs=3, seed=7, config={"training": {"batch_size": 2}},
                            python=str(python))
    job.wait(timeoutSeconds=60, intervalSeconds=0.05)
    overrides = run / "overrides.yaml"
    assert job.command == [str(python), "-m", "comreg_core.cli", "pretrain", str(mesh),
                           "--out", str(run), "--device", "cpu", "--preset", "cpu",
                           "--seed", "7", "--max-minutes", "2.5", "--epochs", "3",
                           "--config", str(overrides)]
    assert overrides.read_text() == "training:\n  batch_size: 2\n"
    pythonPath = job.consolePath.read_text().splitlines()[-1]
    assert pythonPath.split("=", 1)[1].split(os.pathsep)[0] == str(REPO_ROOT)

    resumed = launchPretraining(None, mesh, run, preset="cpu", device="cpu", maxMinutes=0,
                                epochs=None, seed=7, resume=True, python=str(python))
    resumed.wait(timeoutSeconds=60, intervalSeconds=0.05)
    assert resumed.command == [str(python), "-m", "comreg_core.cli", "pretrain", str(mesh),
                               "--out", str(run), "--device", "cpu", "--resume"]


def test_a_failed_start_removes_only_the_folder_it_made(tmp_path):
    missing = str(tmp_path / "no_such_python")
    run = tmp_path / "run"
    with pytest.raises(ComRegError, match="Cannot start the pretraining process"):
        launchPretraining(None, tmp_path / "ct.stl", run, preset="cpu", device="cpu",
                          maxMinutes=0, epochs=1, seed=0, python=missing)
    assert not run.exists()
    run.mkdir()
    with pytest.raises(ComRegError, match="Cannot start the pretraining process"):
        launchPretraining(None, tmp_path / "ct.stl", run, preset="cpu", device="cpu",
                          maxMinutes=0, epochs=1, seed=0, python=missing)
    assert run.is_dir()


def test_pretraining_job_reports_a_failed_run(logic, tmp_path):
    (tmp_path / "empty.stl").write_bytes(b"")
    job = logic.startPretraining(tmp_path / "empty.stl", tmp_path / "run", epochs=1,
                                 device="cpu")
    status = job.wait(timeoutSeconds=120, intervalSeconds=0.2)
    assert status.state == "failed" and status.returnCode == 2
    assert "empty.stl" in status.message  # the CLI's one-line error, not a traceback
    assert isinstance(job, PretrainingJob)
