"""``comreg live``: the stream in, the registration out, until the user or the stream stops.

Threads and processes: the OpenIGTLink client's thread
(:class:`~comreg_core.live.receiver.FrameReceiver`) reads every message, pairs images with poses
and queues the frames; it never waits for the registration. The detection pipeline's thread
(:class:`~comreg_core.live.pipeline.DetectionPipeline`) decides each frame (skipped: no new
bone; dropped: too old; :class:`~comreg_core.live.intake.FrameGate`) and has the bone detected
in worker processes (:class:`~comreg_core.live.detection.DetectionPool`). The update loop
(:func:`run_live`, the caller's thread) takes the detections that came, or the answer of a full
search running beside it (with the next frame of new bone, or alone once none came for
:data:`RESTING_S`: a probe held still sends frames without new bone), registers, sends a
TRANSFORM and a STRING back, writes a row of ``updates.csv`` and a status line. No server
within the connect timeout (``--connect-timeout``, the first connection only) ends the loop
with :class:`NoServerError` before anything is written. A lost connection loses nothing
registered (the client reconnects); ``--until-end`` stops when the server closes the stream
(after the answers of the full searches the last updates ask for, up to
:data:`FINAL_ANSWERS`). ``updates.csv`` is made at the first update. On stop, frames on their
way are detected; :func:`finish_live` writes what ``comreg register`` and ``comreg report``
would for the points (:func:`~comreg_core.register.register_to_directory`) and each frame's
fate (``frames.csv``).
"""

from __future__ import annotations

import logging
import math
import signal
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.io import PointCloud, write_points
from comreg_core.io._files import atomic_output
from comreg_core.live.detection import DetectionPool
from comreg_core.live.igtl import SEND_DEVICE
from comreg_core.live.intake import LAG, SKIPPED
from comreg_core.live.pipeline import DetectionPipeline
from comreg_core.live.receiver import FrameReceiver
from comreg_core.live.session import LiveSession
from comreg_core.live.updates import UpdatesLog, write_frames_csv

log = logging.getLogger(__name__)

#: Seconds ``--until-end`` waits, once the stream ended, for the answer of a full search still
#: running in the background (an update uses it); and how many such answers it waits for.
FINAL_SEARCH_WAIT_S = 60.0
FINAL_ANSWERS = 3
#: Seconds without a frame of new bone after which a full search's answer makes an update alone
#: (the probe rests); before, it waits for the next frame's update. An update with an answer is
#: judged as a full search (0.3-0.8 s on 2 cores), and a frame coming meanwhile would wait for
#: it: a sweep's short pauses are left to the frames (docs/live.md).
RESTING_S = 1.0
#: File names of a live folder, besides those of a registration folder.
UPDATES = "updates.csv"
US_POINTS = "us_points.ply"
US_POINT_FRAMES = "us_points_frames.npy"
FRAMES = "frames.csv"


class NoServerError(ComRegError):
    """No OpenIGTLink server answered within the connect timeout (nothing was received)."""


@dataclass
class LiveSummary:
    """How a live run ended: ``updates`` sent, images ``received``, frames ``used``, and those
    not: ``waiting`` (still on their way, used by :func:`finish_live`), ``skipped`` (no new
    bone: not a loss), ``dropped`` (while lagging), ``without_pose`` (or with an unusable
    one)."""

    updates: int
    received: int
    used: int
    waiting: int
    dropped: int
    without_pose: int
    skipped: int = 0

    def line(self) -> str:
        lost = self.received - self.used - self.waiting - self.skipped
        other = lost - self.dropped - self.without_pose
        return (f"{self.updates} updates; {self.used} of {self.received} frames registered"
                + (f", {self.waiting} waiting" if self.waiting else "")
                + f"; {self.skipped} skipped (no new bone)"
                + (f"; {lost} not used: {self.dropped} dropped while lagging, "
                   f"{self.without_pose} without a usable pose"
                   + (f", {other} other" if other else "") if lost else ""))


class SignalStop(threading.Event):
    """:func:`run_live`'s stop set by a signal; ``reason``: "Ctrl-C" or e.g. "SIGTERM"."""

    reason: str | None = None


@contextmanager
def stop_on_signals():
    """Yields a :class:`SignalStop` that Ctrl-C and SIGTERM set (not raise: an exception raised
    inside a compiled kernel's call surfaces as a SystemError), so that :func:`run_live` stops
    between updates and its folder is still written; a second signal raises KeyboardInterrupt.
    Main thread only; the previous handlers come back on leaving."""
    stop = SignalStop()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def _stop(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.reason = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        stop.set()

    previous = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def run_live(session: LiveSession, receiver: FrameReceiver, *, out_dir: str | Path | None = None,
             until_end: bool = False, stop: threading.Event | None = None,
             send_device: str = SEND_DEVICE, on_status: Callable[[str], None] | None = None,
             on_note: Callable[[str], None] | None = None,
             pool: DetectionPool | None = None, update_every_s: float = 0.0) -> LiveSummary:
    """The update loop (module docstring) until ``stop`` is set, Ctrl-C, or (``until_end``) the
    server closed the stream and the frames that came are registered (with the answers of the
    full searches still asked for, up to :data:`FINAL_ANSWERS`). ``out_dir``: gets
    ``updates.csv`` at the first update, then a row per update, flushed. ``on_status`` gets
    each update's status line, ``on_note`` each one-line note. ``pool``: the detection workers
    (None: detection in the pipeline's thread). ``update_every_s``: while frames wait for
    detection, an update starts at least this long after the one before (the frames detected
    meanwhile wait for it), leaving the processor to detection. Frames still on their way when
    it stops are detected then (no update), for :func:`finish_live`. Raises :class:`NoServerError` when the
    receiver's connect timeout passed without a connection (``out_dir`` untouched then)."""
    on_status = on_status or (lambda line: log.info("%s", line))
    on_note = on_note or (lambda line: log.warning("%s", line))
    stop = stop or threading.Event()
    pipeline = DetectionPipeline(receiver, session.gate, pool or DetectionPool(0),
                                 session.clock)
    state = {"log": None, "told": set()}
    ended, final_answers, new_bone_s = False, 0, -math.inf
    next_update_s = -math.inf
    session.gate.update_every_s = update_every_s
    pipeline.start()
    try:
        while not stop.is_set():
            stop.wait(max(0.0, next_update_s - session.clock()))
            batch = pipeline.take(0.1)
            for note in batch.notes:
                on_note(note)
            if batch.gave_up:
                raise NoServerError(f"{batch.gave_up[0].upper()}{batch.gave_up[1:]}.",
                                    "Start PLUS Server (or 'comreg replay') there first, check "
                                    "--igtl, or wait longer (--connect-timeout).")
            if stop.is_set():  # a signal came during the wait
                break
            if batch.detections:
                new_bone_s = session.clock()
            resting = ended or session.clock() - new_bone_s >= RESTING_S
            if batch.detections or (resting and session.answer_waiting()):
                start = session.clock()
                _one_update(session, receiver, batch, state, out_dir, send_device, on_status,
                            on_note)
                if pipeline.waiting:  # detection lags: the next update waits a while
                    next_update_s = start + update_every_s
            ended = ended or batch.ended
            if ended and until_end:
                if session.searching and final_answers < FINAL_ANSWERS \
                        and session.worker.wait(FINAL_SEARCH_WAIT_S):  # an update with it
                    final_answers += 1
                    continue
                break
        if getattr(stop, "reason", None):
            on_note(f"stopping ({stop.reason})")
    except KeyboardInterrupt:
        on_note("stopping (Ctrl-C)")
    finally:
        frames, found = pipeline.stop()
        session.drain(frames, found)
        if state["log"] is not None:
            state["log"].close()
    return LiveSummary(len(session.updates), receiver.assembler.images,
                       session.points.frames_used, len(session.backlog),
                       receiver.dropped + session.dropped + session.gate.counts[LAG],
                       receiver.assembler.without_pose + receiver.assembler.bad_poses,
                       session.gate.counts[SKIPPED])


def _one_update(session: LiveSession, receiver: FrameReceiver, batch, state: dict, out_dir,
                send_device: str, on_status, on_note) -> None:
    """One update of :func:`run_live` with the ``batch``'s detections: sent back, logged
    (``state``: the ``updates.csv`` log, made at the first update; the waits told) and
    told."""
    update = session.update(received=batch.received, detections=batch.detections)
    for note in session.take_notes():
        on_note(note)
    if update is None:
        waiting = ("first" if session.searching and session.last is None else "bone")
        if waiting not in state["told"]:
            on_status(f"waiting for bone: {session.points.frames_with_bone} of "
                      f"{session.points.frames_used} frames show it so far" if waiting == "bone"
                      else f"registering {session.points.frames_used} frames: the first full "
                      "search runs in the background")
            state["told"].add(waiting)
        return
    update.waiting, update.skipped = batch.waiting, batch.skipped
    update.dropped_lag = batch.dropped + receiver.dropped
    update.dropped_no_pose = receiver.assembler.without_pose + receiver.assembler.bad_poses
    receiver.send(update, session.registrar.space, send_device)
    update.latency_s = session.clock() - update.newest_s
    if out_dir is not None and state["log"] is None:
        state["log"] = UpdatesLog(Path(out_dir) / UPDATES)
    if state["log"] is not None:
        state["log"].write(update)
    on_status(update.status_line())


def finish_live(session: LiveSession, out_dir: str | Path, *, run_dir=None, ct_mesh=None,
                device: str = "auto", calibration=None, prior=None, report: bool = True):
    """Write what ``comreg register`` (and ``comreg report``) would for the sweep's points into
    ``out_dir``: ``us_points.ply`` (tracker frame, LPS, beam origins), ``us_points_frames.npy``
    (each point's frame, ``(N,)``), ``frames.csv`` (:func:`write_frames_csv`), then
    ``register_to_directory``'s files by the session's own registrar (its CT side ready; within
    ``prior``, a search ``Prior``, or None) and ``report.html``. Frames still in the backlog are
    detected first. Returns ``(RegistrationResult, report path or None)``; raises
    :class:`ComRegError` when no bone points were received."""
    from comreg_core.register import register_to_directory  # torch: only when stopping

    session.drain()
    cloud = session.points.cloud()
    if cloud is None:
        raise ComRegError(f"No bone points were received ({session.points.frames_used} frames "
                          "used), so nothing was registered.",
                          "Check that the stream sends B-mode frames with their poses "
                          "(--image-device, --transform-device) and that the bone is in view.")
    out = Path(out_dir)
    points_path = write_points(PointCloud(cloud.points, "LPS",
                                          beam_origins=session.points.beam_origins(cloud)),
                               out / US_POINTS)
    with atomic_output(out / US_POINT_FRAMES) as tmp:
        np.save(tmp, cloud.frame_index.astype(np.int64))
    with atomic_output(out / FRAMES) as tmp:
        write_frames_csv(session.gate.fates, session.points.records, session.started_s, tmp)
    result = register_to_directory(run_dir, points_path, out, device=device, seed=session.seed,
                                   ct_mesh=ct_mesh, calibration=calibration, prior=prior,
                                   registrar=session.registrar)
    path = None
    if report:
        from comreg_core.report import write_report_for_registration  # VTK

        path = write_report_for_registration(out, ct_mesh=ct_mesh)
    return result, path

