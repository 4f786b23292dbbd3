"""From the stream's frames to detected bone points, in a thread of its own
(:class:`DetectionPipeline`), so that the update loop only registers.

The pipeline's thread takes the frames the receiver paired (in stream order) and lets the
:class:`~comreg_core.live.intake.FrameGate` decide each one: skipped (no new bone), dropped (it
would be too old when used), or detected once a worker of the
:class:`~comreg_core.live.detection.DetectionPool` is free. It keeps the detections that come
back for the update loop (:meth:`DetectionPipeline.take`). Frames wait in a queue
(:attr:`DetectionPipeline.waiting`) only behind a frame with new bone while every worker is
busy; its length and the gate's counts are the status line's ``waiting``, ``skipped`` and
``dropped``.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

from comreg_core.live.detection import DetectionPool
from comreg_core.live.intake import DETECT, LAG, SKIPPED, FrameGate
from comreg_core.live.points import Detection


@dataclass
class PipelineBatch:
    """What :meth:`DetectionPipeline.take` hands over: ``detections`` (in the order they came),
    one-line ``notes``, ``received`` images so far, ``ended`` (the
    server closed the stream and every frame that came is decided), ``gave_up`` (why no first
    connection was made; empty otherwise), ``waiting`` frames (queued, not being detected),
    and the gate's counts when ``received`` was: frames ``skipped`` (no new bone) and
    ``dropped`` (lag)."""

    detections: list[Detection] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    received: int = 0
    ended: bool = False
    gave_up: str = ""
    waiting: int = 0
    skipped: int = 0
    dropped: int = 0


class DetectionPipeline:
    """The receiver's frames -> the gate -> detection -> the update loop (module docstring).

    Args:
        receiver: a :class:`~comreg_core.live.receiver.FrameReceiver` (anything with its ``take``).
        gate: the session's :class:`FrameGate`.
        pool: the :class:`DetectionPool` (``DetectionPool(0)``: detection in this thread).
        clock: the time source (s), ``time.monotonic`` by default.
    """

    def __init__(self, receiver, gate: FrameGate, pool: DetectionPool,
                 clock: Callable[[], float] = time.monotonic):
        self.receiver, self.gate, self.pool, self.clock = receiver, gate, pool, clock
        self._lock = threading.Lock()
        self._waiting: deque = deque()
        self._ready: list[Detection] = []
        self._out = PipelineBatch()
        self._stream_ended = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="comreg-detection-pipeline",
                                        daemon=True)

    def start(self) -> None:
        self.receiver.start()
        self._thread.start()

    @property
    def waiting(self) -> int:
        """Frames queued, not decided yet (behind a frame with new bone that waits for a
        worker); those being detected are not counted."""
        return len(self._waiting)

    def _run(self) -> None:
        while not self._stop.is_set():
            batch = self.receiver.take(0.0)
            self._waiting.extend(batch.frames)
            while self._waiting:  # in order; a frame with new bone waits for a worker
                fate = self.gate.decide(self._waiting[0], self.clock(), self.pool.free())
                if fate is None:
                    break
                frame = self._waiting.popleft()
                if fate == DETECT:
                    self.pool.submit(frame)
            found = self.pool.collect(0.0)
            for detection in found:
                self.gate.timed(detect_s=detection.detect_s)
            with self._lock:
                self._ready += found
                out = self._out
                out.notes += batch.notes + self.pool.notes
                out.received = batch.received
                out.skipped, out.dropped = self.gate.counts[SKIPPED], self.gate.counts[LAG]
                out.gave_up = out.gave_up or batch.gave_up
                self._stream_ended = self._stream_ended or batch.ended
                out.ended = self._stream_ended and not self._waiting and not self.pool.busy
            self.pool.notes = []
            if batch.gave_up:
                return
            if not batch.frames and not found:
                time.sleep(0.003)

    def take(self, timeout_s: float = 0.1) -> PipelineBatch:
        """The detections that came since the last call, with the notes and the stream's
        state; waits up to ``timeout_s`` for something to hand over."""
        end = self.clock() + timeout_s
        while True:
            with self._lock:
                out = self._out
                if self._ready or out.notes or out.ended or out.gave_up or \
                        self.clock() >= end or not self._thread.is_alive():
                    out.detections = self._ready
                    out.waiting = self.waiting
                    self._ready = []
                    self._out = PipelineBatch(received=out.received, gave_up=out.gave_up,
                                              skipped=out.skipped, dropped=out.dropped)
                    self._stream_ended = self._stream_ended and not out.ended
                    return out
            time.sleep(0.003)

    def stop(self, wait_s: float = 10.0) -> tuple[list, list[Detection]]:
        """Stop the thread and the receiver; returns what was still on its way: ``(frames not
        decided yet, detections not taken)``, the frames being detected waited for (up to
        ``wait_s``)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self.receiver.stop()
        end = self.clock() + wait_s
        found = list(self._ready)
        while self.pool.busy and self.clock() < end:
            found += self.pool.collect(0.05)
        found += self.pool.collect(0.0)
        frames = list(self._waiting) + self.receiver.take(0.0).frames
        self._ready, self._waiting = [], deque()
        return frames, found
