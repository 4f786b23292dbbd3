"""Bone detection off the update loop (:class:`DetectionPool`): worker processes that find the
bone in frames while the update loop registers.

Why processes: detection (~9 ms a fibula frame on an idle core of the test machine: numpy,
scipy and numba kernels) holds Python's lock for much of it, so a thread beside the update loop
would take turns with it. Each worker is started with ``spawn`` (as the full-search worker: a
fork of a process whose numba and torch pools run can hang), runs its kernels on one thread,
and answers one frame at a time, so a frame goes to a worker only when one is free (the age
limit is checked then: :class:`~comreg_core.live.intake.FrameGate`). A detection is a pure
function of the frame (:func:`~comreg_core.live.points.detect_frame`): a worker's answer is the
update loop's own, bit for bit, and which worker answers does not matter. ``workers=0`` detects
in the calling thread; a worker that cannot start or stops is let go (one note) and its frames
are detected in the calling thread from then on.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import time
from multiprocessing.connection import wait as wait_for

import numpy as np

from comreg_core.live.background import child_environment, close_process, keep_freed_memory
from comreg_core.live.points import Detection, detect_frame

log = logging.getLogger(__name__)

#: Detection workers at most (four keep up with 100 frames/s even at ~30 ms a frame).
MAX_WORKERS = 4
#: Seconds ``comreg live`` waits for the workers to start.
WORKER_START_S = 60.0


def default_workers(cores: int | None = None) -> int:
    """Detection workers for a machine with ``cores`` cores (None: those this process may
    use): one per core less one for the update loop, but two on 2 cores; at most
    :data:`MAX_WORKERS`, never more than the cores. Two on 2 cores because detection must keep
    up with every frame while the update loop waits between updates (``--update-every``): two
    workers detect in its pauses. On the stress set at 40 frames/s (search alone, 3 starts,
    idle) one worker let 29, 11 and 7 frames be dropped for lag, two none, with updates as
    late as before (median 0.37-0.63 s against 0.48-0.54 s; 2026-12-05)."""
    if cores is None:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            cores = os.cpu_count() or 1
    return max(1, min(MAX_WORKERS, cores, max(2, cores - 1)))


def _serve(config, connection) -> None:
    """A worker: say "ready" after a first detection (imports, compiled kernels), then answer
    frames with their :class:`Detection` until None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    keep_freed_memory()
    try:
        from comreg_core.live.stream import Frame
        from comreg_core.surfaces.us_detector import warm_up_frame

        first = detect_frame(Frame(-1, warm_up_frame(), np.array([0.1, 0.1]), np.eye(4), 0.0,
                                   0.0), config)
        if not len(first.points):
            raise RuntimeError("the detector found no bone in its warm-up frame")
    except Exception as exc:  # the parent detects itself then
        connection.send(("failed", f"{type(exc).__name__}: {exc}"))
        return
    connection.send(("ready", None))
    while True:
        try:
            frame = connection.recv()
        except EOFError:
            return
        if frame is None:
            return
        try:
            connection.send(detect_frame(frame, config))
        except Exception as exc:
            connection.send(("error", frame.index, f"{type(exc).__name__}: {exc}"))


class _Worker:
    def __init__(self, context, config):
        self.connection, child = context.Pipe()
        self.process = context.Process(target=_serve, args=(config, child),
                                       name="comreg-detection", daemon=True)
        self.process.start()
        child.close()
        self.ready = False
        self.frame = None  # the frame it is detecting


class DetectionPool:
    """Detection workers (module docstring): :meth:`submit` a frame when :meth:`free`,
    :meth:`collect` the detections that came. A context manager: leaving it closes the
    workers.

    Args:
        workers: processes (0: detect in the calling thread).
        config: the extraction settings (``comreg extract-us``'s).
    """

    def __init__(self, workers: int, config=None):
        from comreg_core.surfaces.us_config import USExtractionConfig

        self.config = config or USExtractionConfig()
        self.notes: list[str] = []
        self._done: list[Detection] = []
        self._workers: list[_Worker] = []
        if workers > 0:
            context = multiprocessing.get_context("spawn")
            with child_environment():
                self._workers = [_Worker(context, self.config) for _ in range(workers)]

    def __enter__(self) -> DetectionPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def workers(self) -> int:
        """Worker processes alive (0: detection in the calling thread)."""
        return len(self._workers)

    def wait_ready(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for every worker to start; those that failed are let go.
        Whether all are ready."""
        end = time.monotonic() + timeout_s
        while any(not w.ready for w in self._workers) and time.monotonic() < end:
            self._read(0.05)
        return all(w.ready for w in self._workers)

    def free(self) -> bool:
        """Whether a frame can be submitted now without waiting (a worker idle, or none)."""
        return not self._workers or any(w.ready and w.frame is None for w in self._workers)

    @property
    def busy(self) -> int:
        """Frames being detected."""
        return sum(w.frame is not None for w in self._workers)

    def submit(self, frame) -> None:
        """Detect ``frame``: in an idle worker, or here (no worker)."""
        for worker in self._workers:
            if worker.ready and worker.frame is None:
                try:
                    worker.connection.send(frame)
                    worker.frame = frame
                    return
                except (OSError, ValueError) as exc:
                    self._let_go(worker, f"{type(exc).__name__}")
        self._done.append(detect_frame(frame, self.config))

    def collect(self, wait_s: float = 0.0) -> list[Detection]:
        """The detections that came (waiting up to ``wait_s`` for one when none has)."""
        if not self._done:
            self._read(wait_s)
        done, self._done = self._done, []
        return done

    def _read(self, wait_s: float) -> None:
        alive = {w.connection: w for w in self._workers}
        for connection in wait_for(list(alive), timeout=wait_s) if alive else []:
            worker = alive[connection]
            try:
                message = connection.recv()
            except (EOFError, OSError) as exc:
                self._let_go(worker, type(exc).__name__)
                continue
            if isinstance(message, Detection):
                worker.frame = None
                self._done.append(message)
            elif message[0] == "ready":
                worker.ready = True
            elif message[0] == "error":  # detect it here: the same function, the same answer
                frame, worker.frame = worker.frame, None
                self.notes.append(f"a detection worker failed on frame {message[1]} "
                                  f"({message[2]}); detected in the update process")
                self._done.append(detect_frame(frame, self.config))
            else:
                self._let_go(worker, message[1])

    def _let_go(self, worker: _Worker, why: str) -> None:
        """Stop using ``worker``; its frame is detected here."""
        self._workers.remove(worker)
        self.notes.append(f"a detection worker stopped ({why}); "
                          + (f"{len(self._workers)} left" if self._workers
                             else "detection runs in the update process from now"))
        log.warning("%s", self.notes[-1])
        if worker.frame is not None:
            self._done.append(detect_frame(worker.frame, self.config))
        close_process(worker.process, worker.connection)

    def close(self) -> None:
        """Stop the workers (what they were detecting is not waited for)."""
        for worker in self._workers:
            close_process(worker.process, worker.connection)
        self._workers = []


