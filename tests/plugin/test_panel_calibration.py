""""Calibrate verdict" (issue 50): `comreg calibrate` on the panel's CT model in a background
process, with progress (sweeps done) and Cancel; once finished its calibration.json judges the
panel's registrations (p_correct, as `comreg register --verdict-calibration`)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

from comreg_core.errors import ComRegError  # noqa: E402
from comreg_core.io.meshes import ct_fingerprint  # noqa: E402
from comreg_core.registration.judgement.calibration import Calibration  # noqa: E402
from comreg_core.transforms import apply_transform, space_change  # noqa: E402
from comreg_plugin.scene_io import arraysFromModelMesh  # noqa: E402


def _wait(logic, until, timeout_s: float = 300.0):
    deadline, seen = time.monotonic() + timeout_s, []
    while time.monotonic() < deadline:
        status = logic.pollCalibration()
        seen.append(status)
        if until(status):
            return seen
        time.sleep(0.5)
    logic.cancelCalibration()
    raise AssertionError(f"the calibration did not get there in {timeout_s} s: {seen[-1]}")


def test_the_verdict_calibration_runs_in_the_background_and_then_judges(logic, case, tmp_path):
    _, models = logic.loadSegmentation(case.segmentationPath)
    with pytest.raises(ComRegError, match="No verdict calibration was started"):
        logic.pollCalibration()
    job = logic.startCalibration(outDirectory=tmp_path / "calibration", sweeps=4)
    assert logic.getParameterNode().calibrationState == "running"
    with pytest.raises(ComRegError, match="already running"):
        logic.startCalibration(outDirectory=tmp_path / "other", sweeps=4)
    seen = _wait(logic, lambda s: s.state != "running")
    status = seen[-1]
    assert status.state == "finished", status.message
    assert status.progress == 1.0 and (status.epoch, status.totalEpochs) == (4, 4)
    assert all(0.0 <= s.progress <= 1.0 for s in seen)
    p = logic.getParameterNode()
    assert p.verdictCalibration == str(job.calibrationPath)
    calibration = Calibration.load(job.calibrationPath)
    vertices, faces = arraysFromModelMesh(models[0])
    lps = apply_transform(space_change("RAS", "LPS"), vertices)
    assert calibration.sweeps == 4 and calibration.prior_kind == "none"  # no prior in the scene
    assert calibration.ct_fingerprint["sha256"] == ct_fingerprint(lps, faces)["sha256"]
    summary = logic.register(logic.loadUSPoints(case.usPointsPath), "search",
                             ctModelNode=models[0])
    record = summary.record
    assert record["verdict_calibration"]["sweeps"] == 4
    expected = calibration.p_correct(record["uncertainty"]["p_raw"])
    assert record["p_correct"] == pytest.approx(expected, abs=1e-12)
    assert p.pCorrect == record["p_correct"] and np.isfinite(p.pCorrect)


def _landmarks(logic, name, point_ras):
    node = logic.scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", name)
    node.AddControlPoint(list(point_ras), "ankle")
    return node


def test_cancel_stops_the_calibration_and_leaves_no_calibration(logic, case, tmp_path):
    """Also: with landmarks in the scene, the calibration is for registrations with one
    (``comreg calibrate --prior landmark``), the kind the panel's registrations will have."""
    logic.loadSegmentation(case.segmentationPath)
    p = logic.getParameterNode()
    p.ctLandmarks = _landmarks(logic, "CT landmarks", (10.0, 20.0, 30.0))
    p.usLandmarks = _landmarks(logic, "US landmarks", (1.0, 2.0, 3.0))
    job = logic.startCalibration(outDirectory=tmp_path / "calibration", sweeps=60)
    p.ctLandmarks = p.usLandmarks = None
    assert job.command[job.command.index("--prior") + 1] == "landmark"
    _wait(logic, lambda s: s.epoch >= 1 or s.state != "running")
    status = logic.cancelCalibration()
    assert status.state == "cancelled" and not job.running
    assert 0.0 < status.progress < 1.0
    assert not job.calibrationPath.exists()
    assert logic.getParameterNode().calibrationState == "cancelled"
    assert logic.getParameterNode().verdictCalibration == ""
