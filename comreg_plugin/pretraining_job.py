"""``comreg pretrain`` in a background process, for the ComReg module: start it, poll its
progress from the run's files, cancel it; nothing here blocks and nothing needs 3D Slicer.

:func:`launchPretraining` writes the CT mesh into the run folder and starts the process;
:class:`PretrainingJob` watches it (``poll()`` reads ``training_log.csv``, ``cancel()``) and
:class:`PretrainingStatus` is what a poll saw.
"""

import csv
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from comreg_core import runs
from comreg_core.errors import ComRegError
from comreg_core.io._files import atomic_output, check_output_folder, require_input_file

log = logging.getLogger(__name__)

#: The repository root (holds comreg_core/ and comreg_plugin/); put on the process's PYTHONPATH.
REPO_ROOT = Path(__file__).resolve().parents[1]


@dataclass
class PretrainingStatus:
    """What :meth:`PretrainingJob.poll` saw.

    Attributes:
        state: "running", "finished", "failed" or "cancelled".
        progress: 0..1 (epochs done of the total, or the time budget spent, whichever is
            further; 1 when finished).
        epoch, totalEpochs: epochs written to ``training_log.csv`` so far, and planned.
        loss: the last epoch's training loss (None before the first epoch).
        validation: the last ``val_*`` values of the log (median RTE mm, RRE deg, ...).
        elapsedSeconds: since the process started.
        returnCode: the process exit status (None while it runs).
        message: a line for the user (the CLI's error when it failed).
        runDirectory: the run folder.
    """

    state: str
    progress: float
    epoch: int
    totalEpochs: Optional[int]
    loss: Optional[float]
    validation: dict
    elapsedSeconds: float
    returnCode: Optional[int]
    message: str
    runDirectory: Path

    def describe(self) -> str:
        """One line for the user: state, epoch (of the total), loss, validation median RTE (mm)
        and RRE (deg), and the error of a failed run."""
        text = f"{self.state}: epoch {self.epoch}"
        if self.totalEpochs:
            text += f" of {self.totalEpochs}"
        if self.loss is not None:
            text += f", loss {self.loss:.4f}"
        if "val_RTE_mm_median" in self.validation:
            text += (f", validation RTE {self.validation['val_RTE_mm_median']:.2f} mm, RRE "
                     f"{self.validation.get('val_RRE_deg_median', float('nan')):.2f} deg")
        if self.state in ("failed",):
            text += f" - {self.message}"
        return text


def _interruptible() -> None:
    """In the child before it runs: SIGINT to its default, which Python turns into
    KeyboardInterrupt. A program started in the background by a shell (a test run, a script)
    inherits SIGINT ignored, and :meth:`PretrainingJob.cancel`'s interrupt would then wait its
    timeout and kill the process."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class PretrainingJob:
    """``comreg pretrain`` running in a background process; nothing here blocks.

    The process writes its console output to ``RUN_DIR/pretrain_console.log``; progress comes from
    the run's ``training_log.csv`` (one row per epoch, flushed) and ``config.yaml``. The trainer
    writes every checkpoint atomically (temporary file, then rename); :meth:`cancel` interrupts it
    with SIGINT (the temporary file of a checkpoint being written is removed by the interrupted
    writer), then removes any temporary file left if it had to be killed, so the run folder holds
    either the previous complete checkpoint or none, never a half-written one.
    """

    LOG_NAME = runs.TRAINING_LOG
    CONFIG_NAME = runs.CONFIG
    CHECKPOINT_NAME = runs.CHECKPOINT
    CONSOLE_NAME = "pretrain_console.log"  # the plugin's own: the process's console output

    def __init__(self, command: list, runDirectory: Path, *, totalEpochs: Optional[int] = None,
                 maxMinutes: Optional[float] = None, env: Optional[dict] = None):
        self.command = [str(c) for c in command]
        self.runDirectory = Path(runDirectory)
        self.runDirectory.mkdir(parents=True, exist_ok=True)
        self.consolePath = self.runDirectory / self.CONSOLE_NAME
        self._totalEpochs = totalEpochs
        self._maxMinutes = maxMinutes
        self._cancelled = False
        self._start = time.monotonic()
        self._end: Optional[float] = None
        console = open(self.consolePath, "w", encoding="utf-8")
        kwargs: dict = {}
        if os.name == "nt":  # pragma: no cover - Windows
            kwargs["creationflags"] = subprocess.CREATE_NEW_PROCESS_GROUP
        else:
            kwargs["start_new_session"] = True  # its own process group: signals reach only it
            kwargs["preexec_fn"] = _interruptible  # cancel's SIGINT must reach it
        try:
            self.process = subprocess.Popen(self.command, stdout=console, stderr=subprocess.STDOUT,
                                            stdin=subprocess.DEVNULL, env=env,
                                            cwd=str(self.runDirectory), **kwargs)
        except OSError as exc:
            console.close()
            raise ComRegError(f"Cannot start the pretraining process ({exc}).",
                              "Check that the Python executable exists and that ComReg is "
                              "installed for it.") from None
        finally:
            console.close()  # the child holds its own handle
        log.info("Pretraining started (pid %d): %s", self.process.pid, " ".join(self.command))

    # -- state ------------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self.process.poll() is None

    def _rows(self) -> list:
        path = self.runDirectory / self.LOG_NAME
        if not path.is_file():
            return []
        try:
            with path.open(newline="", encoding="utf-8") as f:
                rows = list(csv.DictReader(f))
        except (OSError, csv.Error):
            return []
        good = []
        for row in rows:  # the last line may be half-written while the trainer appends
            try:
                int(row.get("epoch") or "")
            except ValueError:
                continue
            good.append(row)
        return good

    def _planned(self) -> tuple:
        epochs, minutes = self._totalEpochs, self._maxMinutes
        path = self.runDirectory / self.CONFIG_NAME
        if path.is_file():
            try:
                import yaml

                training = (yaml.safe_load(path.read_text(encoding="utf-8")) or {}).get(
                    "training", {})
                epochs = int(training.get("epochs", epochs or 0)) or epochs
                budget = float(training.get("max_minutes", 0) or 0)
                minutes = budget if budget > 0 else minutes
            except Exception:  # a config being replaced: keep what we knew
                pass
        return epochs, minutes

    def _message(self) -> str:
        try:
            lines = [line.strip() for line in
                     self.consolePath.read_text(encoding="utf-8", errors="replace").splitlines()
                     if line.strip()]
        except OSError:
            return ""
        errors = [line for line in lines if line.startswith("error:")]
        if errors:
            return errors[-1][len("error:"):].strip()
        return lines[-1] if lines else ""

    def poll(self) -> PretrainingStatus:
        """The job's state now (reads two small files; returns at once)."""
        code = self.process.poll()
        if code is not None and self._end is None:
            self._end = time.monotonic()
        elapsed = (self._end or time.monotonic()) - self._start
        rows = self._rows()
        last = rows[-1] if rows else {}
        epoch = int(last["epoch"]) if last else 0
        loss = float(last["loss"]) if last.get("loss") else None
        validation = {k: float(v) for row in rows for k, v in row.items()
                      if k.startswith("val_") and v}
        epochs, minutes = self._planned()
        fraction = epoch / epochs if epochs else 0.0
        if minutes:
            fraction = max(fraction, elapsed / (60.0 * minutes))
        if code is None:
            state, progress, message = "running", min(fraction, 0.99), f"epoch {epoch}"
        elif self._cancelled:
            state, progress, message = "cancelled", min(fraction, 1.0), "cancelled"
        elif code == 0 and (self.runDirectory / self.CHECKPOINT_NAME).is_file():
            state, progress, message = "finished", 1.0, self._message()
        else:
            state, progress = "failed", min(fraction, 1.0)
            message = self._message() or f"the process exited with status {code}"
        return PretrainingStatus(state, float(progress), epoch, epochs, loss, validation,
                                 elapsed, code, message, self.runDirectory)

    def wait(self, timeoutSeconds: Optional[float] = None, intervalSeconds: float = 0.5,
             callback: Optional[Callable[[PretrainingStatus], None]] = None) -> PretrainingStatus:
        """Poll until the job ends (for batch scripts); ``callback(status)`` after each poll.
        Raises :class:`ComRegError` after ``timeoutSeconds`` (the job keeps running)."""
        deadline = None if timeoutSeconds is None else time.monotonic() + timeoutSeconds
        while True:
            status = self.poll()
            if callback is not None:
                callback(status)
            if status.state != "running":
                return status
            if deadline is not None and time.monotonic() > deadline:
                raise ComRegError(f"Pretraining is still running after {timeoutSeconds:.0f} s.",
                                  "Wait longer or cancel it.")
            time.sleep(intervalSeconds)

    def cancel(self, timeoutSeconds: float = 20.0) -> PretrainingStatus:
        """Stop the process: SIGINT (Python unwinds, the atomic writer removes its temporary
        file), then SIGKILL after ``timeoutSeconds``; then remove any leftover temporary file.
        Raises :class:`ComRegError` if the job is not running."""
        if not self.running:
            status = self.poll()
            raise ComRegError(f"The pretraining in '{self.runDirectory}' is not running (it has "
                              f"{status.state}).", "Start a new pretraining to cancel it.")
        self._cancelled = True
        try:
            if os.name == "nt":  # pragma: no cover - Windows
                self.process.send_signal(signal.CTRL_BREAK_EVENT)
            else:
                os.killpg(self.process.pid, signal.SIGINT)
            self.process.wait(timeoutSeconds)
        except subprocess.TimeoutExpired:
            log.warning("Pretraining did not stop on interrupt within %.0f s; killing it",
                        timeoutSeconds)
            if os.name == "nt":  # pragma: no cover
                self.process.kill()
            else:
                os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()
        except ProcessLookupError:
            self.process.wait()
        for leftover in self.temporaryFiles():
            leftover.unlink(missing_ok=True)
        return self.poll()

    def temporaryFiles(self) -> list:
        """Temporary files of unfinished atomic writes in the run folder (``.NAME.*.tmp*``)."""
        return sorted(p for p in self.runDirectory.glob(".*.tmp*") if p.is_file())


def checkRunFolder(runDirectory, resume: bool = False) -> Path:
    """The resolved run folder, checked before anything is written (a writable folder, made
    later if missing; a run folder is fine); refuses one that already holds a checkpoint unless
    ``resume``. Raises :class:`ComRegError` (OutputPlaceError for the place)."""
    runDirectory = check_output_folder(Path(runDirectory).resolve(), what="run folder",
                                       run_folder_ok=True)
    checkpoint = runDirectory / PretrainingJob.CHECKPOINT_NAME
    if checkpoint.exists() and not resume:
        raise ComRegError(f"'{runDirectory}' already holds a training run.",
                          "Resume it, register with it, or choose an empty folder.")
    return runDirectory


def launchPretraining(mesh, meshPath: Path, runDirectory: Path, *, preset: str, device: str,
                      maxMinutes: Optional[float], epochs: Optional[int], seed: int, config=None,
                      resume: bool = False, python: Optional[str] = None) -> PretrainingJob:
    """Start ``comreg pretrain`` in the background on a checked run folder; the running job.

    Args:
        mesh: the CT bone :class:`~comreg_core.io.SurfaceMesh`, written to ``meshPath``; or None
            when ``meshPath`` is an existing mesh file.
        meshPath: the CT mesh file the process reads.
        runDirectory: the run folder (made if missing; removed again if the start fails).
        preset, device, seed: as ``comreg pretrain`` (``preset`` and ``seed`` unless
            ``resume``). maxMinutes (minutes), epochs: limits; 0 or None = the preset's.
        config: YAML overrides file, or a dict written to ``RUN_DIR/overrides.yaml``.
        resume: continue the run in ``runDirectory``.
        python: the Python to run ComReg with (default ``sys.executable``).
    """
    created = not runDirectory.exists()
    runDirectory.mkdir(parents=True, exist_ok=True)
    try:
        if mesh is not None:
            from comreg_core.io.meshes import write_mesh

            write_mesh(mesh, meshPath)
        command = [python or sys.executable, "-m", "comreg_core.cli", "pretrain", str(meshPath),
                   "--out", str(runDirectory), "--device", device]
        if resume:
            command.append("--resume")
        else:
            command += ["--preset", preset, "--seed", str(int(seed))]
        if maxMinutes:
            command += ["--max-minutes", repr(float(maxMinutes))]
        if epochs:
            command += ["--epochs", str(int(epochs))]
        if isinstance(config, dict):
            import yaml

            with atomic_output(runDirectory / "overrides.yaml") as tmp:
                tmp.write_text(yaml.safe_dump(config, sort_keys=False), encoding="utf-8")
            config = runDirectory / "overrides.yaml"
        if config is not None:
            command += ["--config", str(require_input_file(config, "pretraining config"))]
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(
            [str(REPO_ROOT)] + [x for x in env.get("PYTHONPATH", "").split(os.pathsep) if x])
        env["PYTHONUNBUFFERED"] = "1"
        return PretrainingJob(command, runDirectory, totalEpochs=epochs or None,
                              maxMinutes=maxMinutes or None, env=env)
    except BaseException:
        if created:  # a failed start leaves no folder of its own behind
            shutil.rmtree(runDirectory, ignore_errors=True)
        raise
