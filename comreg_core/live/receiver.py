"""The receiving side of ``comreg live`` (:class:`FrameReceiver`): the OpenIGTLink client's
thread reads every message, pairs images with their poses and queues the frames for the update
loop (:func:`~comreg_core.live.run.run_live`), which takes them in batches (:class:`Batch`) and
sends each update back (:func:`slicer_transform`). A full queue (:data:`MAX_QUEUED` frames)
drops its oldest frame, and says so."""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pyigtl

from comreg_core.live.igtl import LiveClient, UnknownMessage, SEND_DEVICE, STATUS_DEVICE
from comreg_core.live.stream import Frame, FrameAssembler
from comreg_core.live.updates import LiveUpdate
from comreg_core.transforms import space_change

#: Frames the receiver holds for the update loop at most (the oldest is dropped beyond).
MAX_QUEUED = 200


def slicer_transform(T_ct_us: np.ndarray, space: str) -> np.ndarray:
    """``(4, 4)`` the pose ``T_ct_us`` (stream reference coordinates, taken as LPS as
    ``extract-us`` takes a recording's, -> the CT in its ``space``) as 3D Slicer applies a
    transform it receives: to the stream's coordinates as they come (Slicer puts them straight
    into its RAS scene) -> the CT in RAS."""
    return space_change(space, "RAS") @ np.asarray(T_ct_us) @ space_change("LPS", space)


@dataclass
class Batch:
    """What :meth:`FrameReceiver.take` hands over: ``frames`` (in order), one-line ``notes``,
    ``received`` images so far, ``ended`` (the server closed the stream) and ``gave_up``
    (why no first connection was made within the connect timeout; empty otherwise)."""

    frames: list[Frame] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    received: int = 0
    ended: bool = False
    gave_up: str = ""


class FrameReceiver:
    """The receiving side of ``comreg live`` (module docstring).

    Args:
        host, port: the OpenIGTLink server (PLUS Server, ``comreg replay``, Slicer).
        image_device: the IMAGE device of the B-mode frames.
        pose_device: the TRANSFORM device of their poses.
        T_probe_pixel: the probe calibration when ``pose_device`` is the probe's pose.
        max_queued: frames held for the update loop at most.
        reconnect: connect again after the server closed the stream (``--until-end``: not).
        connect_timeout_s: give up when no first connection was made within this many seconds
            of :meth:`start` (None: try for ever); later reconnects are not limited.
    """

    def __init__(self, host: str, port: int, image_device: str, pose_device: str,
                 T_probe_pixel: np.ndarray | None = None, max_queued: int = MAX_QUEUED,
                 reconnect: bool = True, clock: Callable[[], float] = time.monotonic,
                 connect_timeout_s: float | None = None):
        self.image_device, self.pose_device = image_device, pose_device
        self.clock = clock
        self.assembler = FrameAssembler(pose_device, T_probe_pixel)
        self._lock = threading.Lock()
        self._frames: deque[Frame] = deque()
        self._notes: list[str] = []
        self._told: set = set()
        self._ended = False
        self._gave_up = ""
        self.max_queued = int(max_queued)
        self.dropped = 0
        self.client = LiveClient(host, port, self._on_message, self._on_event, self._idle,
                                 reconnect=reconnect, connect_timeout_s=connect_timeout_s)

    def start(self) -> None:
        self.client.start()

    def stop(self) -> None:
        self.client.stop()

    def _note(self, text: str) -> None:
        with self._lock:
            self._notes.append(text)

    def _note_once(self, key, text: str) -> None:
        if key not in self._told:
            self._told.add(key)
            self._note(text)

    def _push(self, frames: list[Frame], notes: list[str]) -> None:
        with self._lock:
            self._notes.extend(notes)
            for frame in frames:
                if len(self._frames) >= self.max_queued:
                    old = self._frames.popleft()
                    self.dropped += 1
                    self._notes.append(f"LAGGING: the frame queue is full; dropped frame "
                                       f"{old.index} ({self.dropped} so far)")
                self._frames.append(frame)

    def _on_message(self, message) -> None:
        now = self.clock()
        expected = (f"live reads IMAGE '{self.image_device}' and TRANSFORM "
                    f"'{self.pose_device}'")
        if isinstance(message, UnknownMessage):
            self._note_once(("?", message.message_type, message.device_name),
                            f"ignoring the unexpected {message.message_type or '?'} messages "
                            f"of '{message.device_name}' ({expected})")
        elif isinstance(message, pyigtl.ImageMessage) and \
                message.device_name == self.image_device:
            self._push(*self.assembler.add_image(message.image, message.ijk_to_world_matrix,
                                                 message.timestamp, now))
        elif isinstance(message, pyigtl.TransformMessage) and \
                message.device_name == self.pose_device:
            status = str(message.metadata.get("TransformStatus", "OK")).upper()
            if status not in ("OK", "VALID"):
                self._note_once(("invalid", message.device_name),
                                f"the {message.device_name} pose is sent as {status}; frames "
                                "without a valid pose are skipped")
                return
            self._push(*self.assembler.add_pose(message.device_name, message.matrix,
                                                message.timestamp, now))
        elif not isinstance(message, pyigtl.TransformMessage):
            self._note_once((message.message_type, message.device_name),
                            f"ignoring the {message.message_type} messages of "
                            f"'{message.device_name}' ({expected})")

    def _on_event(self, kind: str, text: str) -> None:
        if kind == "timeout":
            with self._lock:
                self._gave_up = text
            return
        if kind == "closed" or (kind == "lost" and not self.client.reconnect):
            self._push(*self.assembler.expire(float("inf")))
            with self._lock:
                self._ended = True
        self._note(text)

    def _idle(self) -> None:
        frames, notes = self.assembler.expire(self.clock())
        if frames or notes:
            self._push(frames, notes)

    def take(self, timeout_s: float = 0.1) -> Batch:
        """Everything queued since the last call (waiting up to ``timeout_s`` for something)."""
        end = self.clock() + timeout_s
        while True:
            with self._lock:
                if self._frames or self._notes or self._ended or self._gave_up or \
                        self.clock() >= end:
                    batch = Batch(list(self._frames), self._notes, self.assembler.images,
                                  self._ended, self._gave_up)
                    self._frames.clear()
                    self._notes = []
                    self._ended = False
                    return batch
            time.sleep(0.005)

    def send(self, update: LiveUpdate, space: str, send_device: str = SEND_DEVICE) -> bool:
        """Send ``update`` back: a TRANSFORM ``send_device`` (:func:`slicer_transform`) and a
        STRING :data:`~comreg_core.live.igtl.STATUS_DEVICE` (its JSON); False when not
        connected (nothing is sent then)."""
        return self.client.send(
            pyigtl.TransformMessage(slicer_transform(update.T_ct_us, space),
                                    device_name=send_device),
            pyigtl.StringMessage(update.message_text(), device_name=STATUS_DEVICE))
