"""The ComReg module's live session in a second process, so that 3D Slicer's GUI thread only
draws.

:class:`LiveProcess` (the GUI side) starts ``python -m comreg_plugin.live_process`` with the
Python that runs the module (``sys.executable``: inside 3D Slicer its PythonSlicer, as the
background pretraining runs), sends it the session's :class:`LiveSetup` and then the frames as
they come, and collects its answers; nothing on the GUI side waits for a registration. The
process (:func:`serve`) runs :class:`comreg_core.live.session.LiveSession`, the update loop of
``comreg live`` (detection, warm or full registration, the one judge's verdict, the advice),
its full searches between its updates or, when told (``background``), in a third process like
``comreg live``'s (:class:`comreg_core.live.background.FullSearchWorker`).

Messages are pickles with a length prefix over the process's stdin and stdout (its console,
stderr, goes to a log file). To the process: the :class:`LiveSetup`, then ``("frames", seq,
frames, received)`` and ``("stop",)``. From it: ``("ready", pid)`` or ``("failed", text)``, then
per batch of frames ``("update", seq, LiveUpdate or None, waiting, notes, bone)`` (``seq``: the
last batch it took, ``waiting``: frames left in its backlog, ``bone``: frames with bone and
frames used so far) and ``("error", seq, text)``. Nothing here needs 3D Slicer.
"""

import logging
import os
import pickle
import queue
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

log = logging.getLogger(__name__)

_HEADER = struct.Struct("<Q")
#: Seconds :meth:`LiveProcess.close` waits for the process to stop before killing it.
CLOSE_WAIT_S = 5.0


@dataclass
class LiveSetup:
    """The session the process runs: its registrar (``recipe``, a
    :class:`~comreg_core.live.background.RegistrarRecipe`: the CT mesh file, the run or none,
    the device), the verdict's ``calibration`` file (None: the run's own, if any), the
    ``prior`` (:class:`~comreg_core.registration.search.priors.Prior`) or None, the ``seed``,
    the frames an update takes at most and whether full searches run in a third process
    (``background``, as ``comreg live``)."""

    recipe: object
    calibration: Optional[str] = None
    prior: object = None
    seed: int = 0
    max_frames_per_update: int = 16
    background: bool = False


def _send(stream, message) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_HEADER.pack(len(data)) + data)
    stream.flush()


def _receive(stream):
    """The next message of ``stream``, or None at its end."""
    header = stream.read(_HEADER.size)
    if len(header) < _HEADER.size:
        return None
    size = _HEADER.unpack(header)[0]
    data = stream.read(size)
    if len(data) < size:
        return None
    return pickle.loads(data)  # noqa: S301 - our own child process, over its own pipe


class LiveProcess:
    """The live session's process, seen from the GUI (module docstring). :meth:`send` and
    :meth:`messages` never wait for the process; a thread writes the frames and another reads
    the answers.

    Args:
        setup: the session to run.
        logPath: where the process's console goes.
        python: the Python to run it with (default ``sys.executable``).
    """

    def __init__(self, setup: LiveSetup, logPath, python: Optional[str] = None):
        from comreg_plugin.pretraining_job import REPO_ROOT

        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(
            [str(REPO_ROOT)] + [x for x in env.get("PYTHONPATH", "").split(os.pathsep) if x])
        self.logPath = Path(logPath)
        with open(self.logPath, "w", encoding="utf-8") as console:
            self.process = subprocess.Popen(
                [python or sys.executable, "-m", "comreg_plugin.live_process"],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=console, env=env,
                start_new_session=os.name != "nt")
        self._answers: "queue.Queue" = queue.Queue()
        self._outgoing: "queue.Queue" = queue.Queue()
        _send(self.process.stdin, setup)
        self._reader = threading.Thread(target=self._read, name="ComReg live reader",
                                         daemon=True)
        self._writer = threading.Thread(target=self._write, name="ComReg live writer",
                                        daemon=True)
        self._reader.start()
        self._writer.start()

    def _read(self) -> None:
        while True:
            try:
                message = _receive(self.process.stdout)
            except (OSError, ValueError, pickle.UnpicklingError, EOFError):
                message = None
            if message is None:
                self._answers.put(("failed", f"the live process stopped (see '{self.logPath}')"))
                return
            self._answers.put(message)

    def _write(self) -> None:
        while True:
            message = self._outgoing.get()
            try:
                _send(self.process.stdin, message)
            except (OSError, ValueError):
                return
            if message == ("stop",):
                return

    def send(self, seq: int, frames: list, received: int) -> None:
        """Hand the batch ``seq`` of frames (and the count received so far) to the process."""
        self._outgoing.put(("frames", seq, frames, received))

    def messages(self, timeout: float = 0.0) -> list:
        """The answers that came (waiting up to ``timeout`` s for the first)."""
        out = []
        try:
            out.append(self._answers.get(timeout=timeout) if timeout > 0
                       else self._answers.get_nowait())
            while True:
                out.append(self._answers.get_nowait())
        except queue.Empty:
            pass
        return out

    @property
    def running(self) -> bool:
        return self.process.poll() is None

    def close(self) -> None:
        """Stop the process (it finishes the update under way first)."""
        self._outgoing.put(("stop",))
        try:
            self.process.wait(CLOSE_WAIT_S)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


# -- the process ---------------------------------------------------------------------------------

def _session(setup: LiveSetup):
    """``(LiveSession, FullSearchWorker or None)`` of ``setup``, the CT side prepared (as
    ``comreg live`` prepares it)."""
    from comreg_core.live.background import (WORKER_START_S, FullSearchWorker,
                                             build_registrar)
    from comreg_core.live.session import LiveSession
    from comreg_core.register.inputs import calibration_path, find_calibration
    from comreg_core.registration.search.priors import prior_kind

    recipe = setup.recipe
    calibration = find_calibration(setup.calibration, recipe.run_dir)
    registrar = build_registrar(recipe)
    if calibration is not None:
        note = calibration.check_fits(registrar.fingerprint, prior_kind(setup.prior),
                                      calibration_path(setup.calibration, recipe.run_dir))
        if note:
            log.warning("%s", note)
    session = LiveSession(registrar, calibration=calibration, prior=setup.prior,
                          seed=setup.seed, max_frames_per_update=setup.max_frames_per_update)
    worker = FullSearchWorker(recipe, session.prior) if setup.background else None
    session.worker = worker
    session.warm_up()
    if worker is not None:
        worker.wait_ready(WORKER_START_S)
    return session, worker


def _updates(session, incoming: "queue.Queue", answer) -> None:
    """Answer batches of frames until told to stop: each batch (all that came meanwhile, in
    order) is one update; a backlog left is worked off by further updates."""
    seq, stop = 0, False
    while not stop:
        idle = not session.backlog
        try:
            messages = [incoming.get(timeout=None if idle and session.worker is None
                                     else 0.1)] if idle else []
        except queue.Empty:
            messages = []
        while not incoming.empty():
            messages.append(incoming.get_nowait())
        frames, received = [], None
        for message in messages:
            if message is None or message[0] == "stop":
                stop = True
                break
            _, seq, batch, received = message
            frames += batch
        if stop or not (frames or session.backlog or messages):
            continue
        try:
            update = session.update(frames, received=received)
        except Exception as exc:  # noqa: BLE001 - said to the GUI, which stops the mode
            answer(("error", seq, f"{type(exc).__name__}: {exc}"))
            continue
        answer(("update", seq, update, len(session.backlog), session.take_notes(),
                (session.points.frames_with_bone, session.points.frames_used)))


def serve(stdin, stdout) -> None:
    """The process: read the :class:`LiveSetup`, prepare the session, answer frames."""
    setup = _receive(stdin)
    lock = threading.Lock()

    def answer(message) -> None:
        with lock:
            _send(stdout, message)

    try:
        session, worker = _session(setup)
    except Exception as exc:  # noqa: BLE001 - said to the GUI
        answer(("failed", f"{type(exc).__name__}: {exc}"))
        return
    incoming: "queue.Queue" = queue.Queue()

    def read() -> None:
        while True:
            message = _receive(stdin)
            incoming.put(message)
            if message is None or message == ("stop",):
                return

    threading.Thread(target=read, name="frames", daemon=True).start()
    answer(("ready", os.getpid()))
    from contextlib import nullcontext

    from comreg_core.live.background import one_thread

    try:
        with one_thread() if worker is not None else nullcontext():  # the worker: the other core
            _updates(session, incoming, answer)
    finally:
        if worker is not None:
            worker.close()


def main() -> None:
    """``python -m comreg_plugin.live_process``: the protocol on the real stdout; anything
    else printed goes to the console (stderr)."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    protocol = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    started = time.monotonic()
    serve(sys.stdin.buffer, protocol)
    log.info("live process done after %.1f s", time.monotonic() - started)


if __name__ == "__main__":
    main()
