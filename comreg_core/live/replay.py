"""``comreg replay``'s server side: a recorded sweep served over OpenIGTLink as PLUS Server
serves a tracked probe (:func:`replay_sweep`), through :class:`ReplayServer`.

:class:`ReplayServer` is pyigtl's server for one client at a time, with what a replay needs and
pyigtl 0.3.4 lacks: pyigtl's server sends with a 10 ms socket timeout (a 770 kB IMAGE to a busy
client can fail) and installs signal handlers (possible in the main thread only); this one
sends with :data:`~comreg_core.live.igtl.SEND_TIMEOUT_S` and installs none. It reads what the
client sends back (:attr:`ReplayServer.replies`) with :func:`~comreg_core.live.igtl.read_message`.

Per frame it sends what :func:`frame_messages` gives (the wire conventions of
:mod:`comreg_core.live.igtl`).
"""

from __future__ import annotations

import logging
import socket
import socketserver
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pyigtl
from pyigtl.comm import OpenIGTLinkBase

from comreg_core.errors import ComRegError
from comreg_core.live.igtl import (DEFAULT_PORT, IMAGE_DEVICE, IMAGE_POSE_DEVICE,
                                   PROBE_POSE_DEVICE, SEND_TIMEOUT_S, ConnectionClosed,
                                   MalformedMessage, crc64, read_message)

log = logging.getLogger(__name__)

#: How long the server waits for a message from its client before it sends what is queued (s).
READ_WAIT_S = 0.002
#: How long a closing server waits for its client to read the last frames and hang up (s).
HANG_UP_WAIT_S = 2.0


class _ReplayHandler(socketserver.BaseRequestHandler):
    """One client of a :class:`ReplayServer`: sends the queued messages, reads (and keeps) what
    the client sends back, until the client leaves or the server closes."""

    def handle(self) -> None:
        server: ReplayServer = self.server
        sock = self.request
        server._attach()
        try:
            while not server.closing.is_set():
                try:  # a short wait: frames queued meanwhile go out within ~2 ms
                    message = read_message(sock, READ_WAIT_S)
                except MalformedMessage as exc:
                    log.warning("replay: received %s", exc)
                    if not exc.in_sync:
                        return
                    continue
                if message is not None:
                    server.replies.append(message)
                sock.settimeout(SEND_TIMEOUT_S)
                while server._send_queued_message_from_socket(sock):
                    pass
        except (ConnectionClosed, OSError):
            pass
        finally:
            if server.closing.is_set():  # stop listening before the client learns of the end
                server.listener_down.wait(5.0)
                end_gently(sock)
            server._detach()


def end_gently(sock: socket.socket, wait_s: float = HANG_UP_WAIT_S) -> None:
    """End a stream without losing its last frames: the end goes out after them, then what the
    client still sends is read (and dropped) until it hangs up, for at most ``wait_s``. Closing
    with the client's messages unread would reset the connection, and the client's system
    would throw away the frames it had not read yet (seen once in 54 replays at 40 frames/s)."""
    try:
        sock.shutdown(socket.SHUT_WR)
        end = time.monotonic() + wait_s
        while (left := end - time.monotonic()) > 0:
            sock.settimeout(left)
            if not sock.recv(1 << 16):
                return
    except OSError:  # the client is gone already, or the wait is over
        pass


class ReplayServer(pyigtl.OpenIGTLinkServer):
    """An OpenIGTLink server for one client at a time on ``host:port`` (``port`` 0: a free port;
    :attr:`port` is the one bound). :meth:`send_now` sends to the connected client and waits;
    :attr:`replies` keeps the last 1,000 messages the client sent. :meth:`close` ends the
    connection (the client sees the stream end) and frees the port."""

    allow_reuse_address = True

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT):
        OpenIGTLinkBase.__init__(self)
        self.host = host
        self.closing = threading.Event()
        self.listener_down = threading.Event()
        self.replies: deque = deque(maxlen=1000)
        self.clients = 0
        self._lock = threading.Lock()
        crc64(b"")  # compiled (or loaded) now: the first reply read would stall sending ~0.3 s
        try:
            socketserver.TCPServer.__init__(self, (host, int(port)), _ReplayHandler)
        except OSError as exc:
            raise ComRegError(f"Cannot serve on {host}:{port} ({exc.strerror or exc}).",
                              "Choose another --port (or stop what uses this one).") from None
        self.port = int(self.server_address[1])
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.05},
                                        daemon=True)
        self._thread.start()

    def _attach(self) -> None:
        with self._lock:
            self.clients += 1
            self._connected = True

    def _detach(self) -> None:
        with self._lock:
            self._connected = False
            with self.lock_outgoing_messages:
                self.outgoing_messages.clear()

    def wait_for_client(self, timeout_s: float | None = None) -> bool:
        """Whether a client is connected, waiting up to ``timeout_s`` (None: for ever)."""
        end = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._connected:
            if self.closing.is_set() or (end is not None and time.monotonic() > end):
                return False
            time.sleep(0.01)
        return True

    def send_now(self, *messages, timeout_s: float = 2 * SEND_TIMEOUT_S) -> bool:
        """Send ``messages`` to the connected client and wait until they are written; False
        (nothing sent) when no client is connected or it left meanwhile."""
        if not self._connected:
            return False
        for message in messages:
            self._add_message_to_send_queue(message, wait=False)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            with self.lock_outgoing_messages:
                if not self.outgoing_messages:
                    return self._connected
            if not self._connected:
                return False
            time.sleep(0.002)
        return False

    def close(self) -> None:
        """Close the connection and the server (idempotent)."""
        if self.closing.is_set():
            return
        self.closing.set()
        try:  # refuse new connections first: a client reconnecting at once must not be
            self.socket.shutdown(socket.SHUT_RDWR)  # accepted by a server that is going away
        except OSError:
            pass
        self.listener_down.set()
        self.shutdown()
        self.server_close()
        self._thread.join(timeout=5.0)


@dataclass
class ReplayStats:
    """What :func:`replay_sweep` did: ``frames`` served (sent or not), ``sent`` to a client,
    ``unsent`` (no client connected then), ``without_pose`` (invalid frames: IMAGE only),
    ``without_probe`` (valid frames sent without a probe pose), ``duration_s``, and how late
    the frames were sent against their schedule: ``late_median_s``, ``late_max_s`` (from a
    frame's due time to its messages written)."""

    frames: int = 0
    sent: int = 0
    unsent: int = 0
    without_pose: int = 0
    without_probe: int = 0
    duration_s: float = 0.0
    late_median_s: float = 0.0
    late_max_s: float = 0.0


def frame_messages(sweep, index: int, timestamp: float, T_ref_probe: np.ndarray | None = None,
                   image_device: str = IMAGE_DEVICE, pose_device: str = IMAGE_POSE_DEVICE,
                   probe_device: str = PROBE_POSE_DEVICE) -> list:
    """The messages of frame ``index`` of a :class:`~comreg_core.io.sweeps.TrackedSweep`, as
    PLUS Server sends a tracked frame: an IMAGE (``(1, H, W)``, identity matrix: pixel units)
    and, for a valid frame, a TRANSFORM ``pose_device`` = ``T_ref_pixel`` (pixel -> reference
    mm) and, when ``T_ref_probe`` ``(4, 4)`` (probe mm -> reference mm) is given and finite, a
    TRANSFORM ``probe_device`` = it; all stamped ``timestamp`` (s)."""
    image = np.ascontiguousarray(sweep.frames[index])[None]
    messages = [pyigtl.ImageMessage(image, ijk_to_world_matrix=np.eye(4), timestamp=timestamp,
                                    device_name=image_device)]
    if sweep.valid[index]:
        messages.append(pyigtl.TransformMessage(sweep.T_ref_pixel[index], timestamp=timestamp,
                                                device_name=pose_device))
        if T_ref_probe is not None and np.isfinite(T_ref_probe).all():
            messages.append(pyigtl.TransformMessage(T_ref_probe, timestamp=timestamp,
                                                    device_name=probe_device))
    return messages


def replay_sweep(sweep, server: ReplayServer, *, rate: float = 1.0, first_frame: int = 0,
                 wait_s: float | None = None, stop: threading.Event | None = None,
                 on_frame: Callable[[int, bool], None] | None = None,
                 probe_poses: np.ndarray | None = None, fps: float | None = None
                 ) -> ReplayStats:
    """Serve ``sweep`` (a :class:`~comreg_core.io.sweeps.TrackedSweep`) from frame
    ``first_frame`` on through ``server`` as PLUS Server would (:func:`frame_messages`; with
    ``probe_poses`` ``(N, 4, 4)``, probe mm -> reference mm, NaN where unknown, each frame's
    ProbeToReference too), at its recorded rate times ``rate`` (timestamps in s; unknown ones
    at 10 frames/s) or, with ``fps``, at that fixed frame rate (the time stamps sent are the
    recorded ones either way), then close the server. Each frame is due at its scheduled time
    from the first frame's; a frame sent late does not delay the later ones. Waits for a client
    first (up to ``wait_s``; None: for ever); frames due while no client is connected are
    counted ``unsent``, as a live server would lose them. ``on_frame(index, sent)`` after each
    frame; ``stop`` ends it early."""
    if not 0 <= first_frame < sweep.n_frames:
        raise ComRegError(f"--first-frame {first_frame} is outside the sweep's "
                          f"{sweep.n_frames} frames.",
                          f"Give a frame number from 0 to {sweep.n_frames - 1}.")
    if not (np.isfinite(rate) and rate > 0):
        raise ComRegError(f"--rate {rate:g} is not a positive speed.", "Give e.g. --rate 1.")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise ComRegError(f"--fps {fps:g} is not a positive frame rate.", "Give e.g. --fps 40.")
    stop = stop or threading.Event()
    stats = ReplayStats()
    try:
        if not server.wait_for_client(wait_s):
            if stop.is_set() or server.closing.is_set():
                return stats
            raise ComRegError(f"No client connected to {server.host}:{server.port} within "
                              f"{wait_s:g} s.", "Start 'comreg live' (or 3D Slicer's "
                              "OpenIGTLink connector) first, or wait longer (--wait).")
        times = _schedule(sweep.timestamps[first_frame:], rate) if fps is None else \
            np.arange(sweep.n_frames - first_frame) / float(fps)
        late = []
        start = time.monotonic()
        for k, due in enumerate(times):
            index = first_frame + k
            while (pause := start + due - time.monotonic()) > 0 and not stop.is_set():
                time.sleep(min(pause, 0.05))
            if stop.is_set():
                break
            stamp = sweep.timestamps[index]
            stamp = float(stamp) if np.isfinite(stamp) else time.time()
            probe = None if probe_poses is None else probe_poses[index]
            sent = server.send_now(*frame_messages(sweep, index, stamp, probe))
            late.append(time.monotonic() - start - due)
            stats.frames += 1
            stats.sent += int(sent)
            stats.unsent += int(not sent)
            stats.without_pose += int(not sweep.valid[index])
            stats.without_probe += int(bool(sweep.valid[index]) and (
                probe is None or not np.isfinite(probe).all()))
            if on_frame is not None:
                on_frame(index, sent)
        stats.duration_s = time.monotonic() - start
        if late:
            stats.late_median_s, stats.late_max_s = float(np.median(late)), float(max(late))
    finally:
        server.close()
    return stats


def _schedule(timestamps: np.ndarray, rate: float) -> np.ndarray:
    """``(N,)`` send times (s from the first frame) of frames recorded at ``timestamps`` (s,
    NaN = unknown), played ``rate`` times as fast; non-increasing steps count as 0."""
    t = np.asarray(timestamps, dtype=np.float64)
    steps = np.diff(t)
    good = np.isfinite(steps) & (steps >= 0)
    fallback = float(np.median(steps[good])) if good.any() else 0.1
    steps = np.where(good, steps, fallback)
    return np.concatenate([[0.0], np.cumsum(steps)]) / rate
