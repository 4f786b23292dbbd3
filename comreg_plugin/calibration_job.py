"""``comreg calibrate`` in a background process, for the ComReg module's "Calibrate verdict":
start it, poll its progress from its console, cancel it, as the pretraining
(:mod:`comreg_plugin.pretraining_job`) runs; nothing here blocks and nothing needs 3D Slicer.

The process registers simulated sweeps of the CT by the pose search and writes
``OUT/calibration.json`` (:func:`comreg_core.evaluation.calibrate.calibrate_to_directory`), which
then judges the panel's registrations (``p_correct``; the parameter node's
``verdictCalibration``).
"""

import logging
import os
import re
import sys
from pathlib import Path
from typing import Optional

from comreg_core import runs
from comreg_plugin.pretraining_job import REPO_ROOT, PretrainingJob, PretrainingStatus

log = logging.getLogger(__name__)

#: The progress line ``comreg calibrate`` prints per sweep.
_SWEEP_LINE = re.compile(r"calibration sweep (\d+)/(\d+)")
#: Simulated sweeps of a panel calibration unless told (``comreg calibrate``'s default).
DEFAULT_SWEEPS = 60


class CalibrationJob(PretrainingJob):
    """``comreg calibrate`` running in a background process (:class:`PretrainingJob`'s
    process, cancel and wait); :meth:`poll` reads the sweeps done from its console
    (``calibrate_console.log`` in the output folder). Its status's ``epoch`` and
    ``totalEpochs`` are the sweeps done and planned."""

    CONSOLE_NAME = "calibrate_console.log"

    @property
    def calibrationPath(self) -> Path:
        """The ``calibration.json`` the process writes."""
        return self.runDirectory / runs.CALIBRATION

    def _sweeps(self) -> tuple:
        try:
            text = self.consolePath.read_text(encoding="utf-8", errors="replace")
        except OSError:
            return 0, self._totalEpochs
        found = _SWEEP_LINE.findall(text)
        if not found:
            return 0, self._totalEpochs
        return int(found[-1][0]), int(found[-1][1])

    def poll(self) -> PretrainingStatus:
        """The job's state now (reads its console; returns at once)."""
        import time

        code = self.process.poll()
        if code is not None and self._end is None:
            self._end = time.monotonic()
        elapsed = (self._end or time.monotonic()) - self._start
        done, total = self._sweeps()
        fraction = done / total if total else 0.0
        if code is None:
            state, progress, message = "running", min(fraction, 0.99), \
                f"calibration sweep {done} of {total}"
        elif self._cancelled:
            state, progress, message = "cancelled", min(fraction, 1.0), "cancelled"
        elif code == 0 and self.calibrationPath.is_file():
            state, progress, message = "finished", 1.0, self._message()
        else:
            state, progress = "failed", min(fraction, 1.0)
            message = self._message() or f"the process exited with status {code}"
        return PretrainingStatus(state, float(progress), done, total, None, {}, elapsed, code,
                                 message, self.runDirectory)


def launchCalibration(mesh, outDirectory: Path, *, sweeps: int = DEFAULT_SWEEPS,
                      seed: int = 0, lengths=(30.0, 80.0), prior: str = "none",
                      python: Optional[str] = None) -> CalibrationJob:
    """Start ``comreg calibrate`` in the background on the CT bone ``mesh``
    (:class:`~comreg_core.io.SurfaceMesh`, written to ``outDirectory/ct_bone.vtk``) into
    ``outDirectory`` (made if missing), for registrations with a ``prior`` of that kind
    (``--prior``); ``python``: the Python to run ComReg with (default ``sys.executable``,
    inside 3D Slicer its PythonSlicer)."""
    from comreg_core.io._files import check_output_folder
    from comreg_core.io.meshes import write_mesh

    outDirectory = check_output_folder(Path(outDirectory).resolve(),
                                       what="calibration folder")
    outDirectory.mkdir(parents=True, exist_ok=True)
    meshPath = write_mesh(mesh, outDirectory / "ct_bone.vtk")
    command = [python or sys.executable, "-m", "comreg_core.cli", "calibrate", str(meshPath),
               "--out", str(outDirectory), "--sweeps", str(int(sweeps)), "--seed",
               str(int(seed)), "--lengths", f"{float(lengths[0])!r},{float(lengths[1])!r}",
               "--prior", prior]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(REPO_ROOT)] + [x for x in env.get("PYTHONPATH", "").split(os.pathsep) if x])
    env["PYTHONUNBUFFERED"] = "1"
    return CalibrationJob(command, outDirectory, totalEpochs=int(sweeps), env=env)
