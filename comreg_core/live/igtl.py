"""OpenIGTLink glue (pyigtl): the live client, the replay server and :func:`replay_sweep`.

pyigtl gives the messages (``ImageMessage``, ``TransformMessage``, ``StringMessage``: packing,
header parsing, unpacking, the CRC) and the client and server classes, which ComReg subclasses
for what a live registration needs and pyigtl 0.3.4 lacks (measured with its own classes on
127.0.0.1):

- its client keeps only the latest message of each device (of 5 TRANSFORMs sent in a row it
  kept the last), so a frame that arrives before the previous one was read is lost unnoticed:
  :class:`LiveClient` hands on every message, in order (``on_message``);
- it does not notice a server that closes the connection (it keeps reading nothing) and so
  never reconnects: :class:`LiveClient` reports it (``on_event("closed", ...)``) and connects
  again, also after a refused connection or a network error;
- a malformed message prints a traceback and an unknown type is dropped silently: here each
  gives one line (``on_event``) and the client keeps going (it reconnects only when the byte
  stream cannot be followed any more: a header that does not parse);
- its server sends with a 10 ms socket timeout (a 770 kB IMAGE to a busy client can fail) and
  installs signal handlers (possible in the main thread only): :class:`ReplayServer` sends with
  :data:`SEND_TIMEOUT_S` and installs none.

Wire conventions (PLUS Server's for a tracked probe): per frame an ``IMAGE`` (device ``Image``)
whose matrix is the identity (pixel units), a ``TRANSFORM`` ``ImageToReference`` (pixel ->
reference mm, the pixel size included) and a ``TRANSFORM`` ``ProbeToReference`` (probe mm ->
reference mm; ImageToReference = ProbeToReference @ ImageToProbe), all with the same timestamp.
"""

from __future__ import annotations

import logging
import socket
import socketserver
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pyigtl
from pyigtl.comm import OpenIGTLinkBase
from pyigtl.messages import CRC64, MessageBase

from comreg_core.errors import ComRegError

log = logging.getLogger(__name__)

#: OpenIGTLink's (and PLUS Server's) default port.
DEFAULT_PORT = 18944
#: Device names: PLUS Server's image and its pose; what ``comreg live`` sends back.
IMAGE_DEVICE = "Image"
IMAGE_POSE_DEVICE = "ImageToReference"
PROBE_POSE_DEVICE = "ProbeToReference"
SEND_DEVICE = "ReferenceToCT"
STATUS_DEVICE = "ComRegStatus"
#: A message body larger than this (bytes) is taken as a corrupt header.
MAX_BODY_BYTES = 256 * 2 ** 20
#: How long the rest of a message may take once its first byte arrived (s).
BODY_TIMEOUT_S = 5.0
#: How long sending one message may take (s).
SEND_TIMEOUT_S = 10.0
_HEADER = MessageBase.IGTL_HEADER_SIZE


class ConnectionClosed(Exception):
    """The other side closed the connection."""


class MalformedMessage(Exception):
    """A message that cannot be read. ``in_sync``: whether the next message can still be read
    (the header was sound and the whole body was read); else the connection must be dropped."""

    def __init__(self, text: str, in_sync: bool):
        super().__init__(text)
        self.in_sync = in_sync


@dataclass(frozen=True)
class UnknownMessage:
    """A message of a type pyigtl does not know (read and skipped)."""

    message_type: str
    device_name: str
    body_bytes: int


def _recv_exactly(sock: socket.socket, n: int, timeout_s: float) -> bytes:
    """``n`` bytes from ``sock``; :class:`ConnectionClosed` at the end of the stream,
    :class:`MalformedMessage` when they do not come within ``timeout_s`` of the last byte."""
    chunks, got, last = [], 0, time.monotonic()
    sock.settimeout(0.05)
    while got < n:
        try:
            chunk = sock.recv(min(n - got, 1 << 20))
        except socket.timeout:
            if time.monotonic() - last > timeout_s:
                raise MalformedMessage(f"a message stopped after {got} of {n} bytes",
                                       in_sync=False) from None
            continue
        if not chunk:
            raise ConnectionClosed()
        chunks.append(chunk)
        got += len(chunk)
        last = time.monotonic()
    return b"".join(chunks)


def read_message(sock: socket.socket, wait_s: float):
    """The next message on ``sock``: a pyigtl message, an :class:`UnknownMessage`, or None when
    nothing arrived within ``wait_s``. Raises :class:`ConnectionClosed` or
    :class:`MalformedMessage` (a header that does not parse, an absurd size, a CRC mismatch, a
    body pyigtl cannot unpack)."""
    sock.settimeout(wait_s)
    try:
        first = sock.recv(_HEADER)
    except socket.timeout:
        return None
    if not first:
        raise ConnectionClosed()
    header = first + _recv_exactly(sock, _HEADER - len(first), BODY_TIMEOUT_S)
    try:
        fields = MessageBase.parse_header(header)
    except (struct.error, UnicodeDecodeError, ValueError) as exc:
        raise MalformedMessage(f"a message header that is not OpenIGTLink ({exc})",
                               in_sync=False) from None
    kind, device, size = fields["message_type"], fields["device_name"], fields["body_size"]
    if fields["header_version"] not in (1, 2) or size > MAX_BODY_BYTES:
        raise MalformedMessage(f"a message header that is not OpenIGTLink (version "
                               f"{fields['header_version']}, a body of {size} bytes)",
                               in_sync=False)
    body = _recv_exactly(sock, size, BODY_TIMEOUT_S)
    if struct.unpack("> Q", header[50:58])[0] != CRC64(body):
        raise MalformedMessage(f"a {kind} message '{device}' whose CRC does not match its body",
                               in_sync=True)
    message = MessageBase.create_message(kind)
    if message is None:
        return UnknownMessage(kind, device, size)
    try:
        message.unpack(fields, body)
    except Exception as exc:  # pyigtl's unpacking raises whatever the bytes provoke
        raise MalformedMessage(f"a {kind} message '{device}' that cannot be unpacked "
                               f"({type(exc).__name__}: {exc})", in_sync=True) from None
    return message


#: ``on_event(kind, text)``: kind is "connected", "refused", "closed", "lost", "malformed",
#: "timeout" (no first connection within the connect timeout; the client's thread then ends).
EventCallback = Callable[[str, str], None]


class LiveClient(pyigtl.OpenIGTLinkClient):
    """An OpenIGTLink client that hands on every message (``on_message(message)``, called in
    its thread, in order; ``UnknownMessage`` for unknown types), reports what happens to the
    connection (``on_event``) and reconnects after a refusal, a close or an error. ``idle()``
    is called between reads (about every 20 ms). Messages to send are queued (pyigtl's
    outgoing queue, 100 at most; the oldest go first when it overflows) and sent while
    connected. ``reconnect=False``: the thread ends when the server closes the stream.
    ``connect_timeout_s``: when no first connection was made within this many seconds of
    :meth:`start`, the client gives up (``on_event("timeout", ...)``) and its thread ends; None:
    it tries for ever. Reconnecting after a first connection is not limited."""

    def __init__(self, host: str, port: int, on_message: Callable, on_event: EventCallback,
                 idle: Callable[[], None] | None = None, reconnect: bool = True,
                 connect_timeout_s: float | None = None):
        super().__init__(host=host, port=port, start_now=False)
        self.reconnect = reconnect
        self.connect_timeout_s = connect_timeout_s
        self._on_message, self._on_event = on_message, on_event
        self._idle = idle or (lambda: None)
        self._refused_told = False
        self._last_failure = ""

    def _event(self, kind: str, text: str) -> None:
        try:
            self._on_event(kind, text)
        except Exception:  # a callback must never kill the receiver
            log.exception("live client event callback failed")

    def _drop(self) -> None:
        if self.socket is not None:
            try:
                self.socket.close()
            except OSError:
                pass
        self.socket, self._connected = None, False

    def _connect(self, where: str, deadline: float | None) -> bool:
        """One try to connect (at most 1 s, and not past ``deadline``, a ``time.monotonic()``);
        whether it worked. The first failure of a run of them gives one "refused" event."""
        wait = 1.0 if deadline is None else min(1.0, max(deadline - time.monotonic(), 0.01))
        try:
            self.socket = socket.create_connection((self.host, self.port), timeout=wait)
        except OSError as exc:
            self._last_failure = str(exc.strerror or exc)
            if not self._refused_told:
                self._event("refused", f"cannot connect to {where} ({self._last_failure}); "
                            "retrying")
                self._refused_told = True
            return False
        self._connected, self._refused_told = True, False
        self._event("connected", f"connected to {where}")
        return True

    def _client_thread_function(self) -> None:
        where = f"{self.host}:{self.port}"
        deadline = None if self.connect_timeout_s is None else \
            time.monotonic() + self.connect_timeout_s
        while not self.communication_thread_stop_requested:
            if self.socket is None:
                if deadline is not None and time.monotonic() >= deadline:
                    self._event("timeout", f"no OpenIGTLink server answered at {where} within "
                                f"{self.connect_timeout_s:g} s ({self._last_failure})")
                    break
                if not self._connect(where, deadline):
                    self._idle()
                    time.sleep(0.2 if deadline is None else
                               min(0.2, max(deadline - time.monotonic(), 0.0)))
                    continue
                deadline = None  # the timeout is the first connection's only
            try:
                message = read_message(self.socket, 0.02)
                if message is not None:
                    self._on_message(message)
                self.socket.settimeout(SEND_TIMEOUT_S)
                while self._send_queued_message_from_socket(self.socket):
                    pass
            except ConnectionClosed:
                self._event("closed", f"{where} closed the connection"
                            + ("; reconnecting" if self.reconnect else ""))
                self._drop()
                if not self.reconnect:
                    break
            except MalformedMessage as exc:
                self._event("malformed", f"received {exc}; "
                            + ("skipped" if exc.in_sync else "reconnecting"))
                if not exc.in_sync:
                    self._drop()
            except OSError as exc:
                self._event("lost", f"the connection to {where} was lost "
                            f"({exc.strerror or exc}); reconnecting")
                self._drop()
            except Exception:
                log.exception("live client: unexpected error; reconnecting")
                self._drop()
            self._idle()
        self._drop()
        self.communication_thread_stopped = True

    def send(self, *messages) -> bool:
        """Queue ``messages`` to send; False (and nothing queued) while not connected."""
        if not self._connected:
            return False
        for message in messages:
            self._add_message_to_send_queue(message, wait=False)
        return True


class _ReplayHandler(socketserver.BaseRequestHandler):
    """One client of a :class:`ReplayServer`: sends the queued messages, reads (and keeps) what
    the client sends back, until the client leaves or the server closes."""

    def handle(self) -> None:
        server: ReplayServer = self.server
        sock = self.request
        server._attach()
        try:
            while not server.closing.is_set():
                try:
                    message = read_message(sock, 0.02)
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
            server._detach()


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
    ``without_probe`` (valid frames sent without a probe pose), ``duration_s``."""

    frames: int = 0
    sent: int = 0
    unsent: int = 0
    without_pose: int = 0
    without_probe: int = 0
    duration_s: float = 0.0


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
                 probe_poses: np.ndarray | None = None) -> ReplayStats:
    """Serve ``sweep`` (a :class:`~comreg_core.io.sweeps.TrackedSweep`) from frame
    ``first_frame`` on through ``server`` as PLUS Server would (:func:`frame_messages`; with
    ``probe_poses`` ``(N, 4, 4)``, probe mm -> reference mm, NaN where unknown, each frame's
    ProbeToReference too), at its recorded rate times ``rate`` (timestamps in s; unknown ones
    at 10 frames/s), then close the server. Waits for a client first (up to ``wait_s``; None:
    for ever); frames due while no client is connected are counted ``unsent``, as a live
    server would lose them.
    ``on_frame(index, sent)`` after each frame; ``stop`` ends it early."""
    if not 0 <= first_frame < sweep.n_frames:
        raise ComRegError(f"--first-frame {first_frame} is outside the sweep's "
                          f"{sweep.n_frames} frames.",
                          f"Give a frame number from 0 to {sweep.n_frames - 1}.")
    if not rate > 0:
        raise ComRegError(f"--rate {rate:g} is not a positive speed.", "Give e.g. --rate 1.")
    stop = stop or threading.Event()
    stats = ReplayStats()
    try:
        if not server.wait_for_client(wait_s):
            if stop.is_set() or server.closing.is_set():
                return stats
            raise ComRegError(f"No client connected to {server.host}:{server.port} within "
                              f"{wait_s:g} s.", "Start 'comreg live' (or 3D Slicer's "
                              "OpenIGTLink connector) first, or wait longer (--wait).")
        times = _schedule(sweep.timestamps[first_frame:], rate)
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
            stats.frames += 1
            stats.sent += int(sent)
            stats.unsent += int(not sent)
            stats.without_pose += int(not sweep.valid[index])
            stats.without_probe += int(bool(sweep.valid[index]) and (
                probe is None or not np.isfinite(probe).all()))
            if on_frame is not None:
                on_frame(index, sent)
        stats.duration_s = time.monotonic() - start
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
