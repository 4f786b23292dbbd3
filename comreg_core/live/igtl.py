"""OpenIGTLink glue (pyigtl): reading a message off a socket (:func:`read_message`), the live
client (:class:`LiveClient`) and the wire conventions; ``comreg replay``'s server is in
:mod:`comreg_core.live.replay`.

pyigtl gives the messages (``ImageMessage``, ``TransformMessage``, ``StringMessage``: packing,
header parsing, unpacking; the CRC of a message read is checked by :func:`crc64`, ~4 times
faster than pyigtl's) and the client and server classes, which ComReg subclasses
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
  stream cannot be followed any more: a header that does not parse).

Wire conventions (PLUS Server's for a tracked probe): per frame an ``IMAGE`` (device ``Image``)
whose matrix is the identity (pixel units), a ``TRANSFORM`` ``ImageToReference`` (pixel ->
reference mm, the pixel size included) and a ``TRANSFORM`` ``ProbeToReference`` (probe mm ->
reference mm; ImageToReference = ProbeToReference @ ImageToProbe), all with the same timestamp.
"""

from __future__ import annotations

import logging
import socket
import struct
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pyigtl
from numba import njit
from pyigtl.messages import MessageBase

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


# OpenIGTLink's CRC-64 (ECMA-182, as pyigtl's ``CRC64``: polynomial 0x42F0E1EBA9EA3693, MSB
# first, no reflection, initial value and final XOR 0), compiled and eight bytes at a time
# ("slicing by 8"). A 950 x 811 B-mode frame's IMAGE body (770 kB) took 1.9 ms with pyigtl's
# (crcmod's C extension, a byte at a time, holding Python's lock) and takes ~0.5 ms here,
# without Python's lock: at 40 frames/s the receiver checks every frame beside the update loop.

#: The generator polynomial, its x^64 term implied.
POLYNOMIAL = 0x42F0E1EBA9EA3693
_MASK = (1 << 64) - 1


def _tables() -> np.ndarray:
    """``(8, 256)`` uint64: row ``k`` the CRC of each byte followed by ``k`` zero bytes."""
    tables = np.zeros((8, 256), np.uint64)
    for byte in range(256):
        crc = byte << 56
        for _ in range(8):
            crc = ((crc << 1) ^ POLYNOMIAL if crc >> 63 else crc << 1) & _MASK
        tables[0, byte] = crc
    for k in range(1, 8):
        for byte in range(256):
            before = int(tables[k - 1, byte])
            tables[k, byte] = ((before << 8) & _MASK) ^ int(tables[0, before >> 56])
    return tables


_TABLES = _tables()


@njit(nogil=True, cache=True)
def _crc64(data, tables):
    """CRC-64 of ``data`` ``(n,)`` uint8 with the ``(8, 256)`` ``tables``."""
    crc = np.uint64(0)
    n = len(data)
    words = n // 8
    for i in range(words):
        word = np.uint64(0)
        for j in range(8):  # big-endian: the first byte is the most significant
            word = (word << np.uint64(8)) | np.uint64(data[8 * i + j])
        x = crc ^ word
        crc = np.uint64(0)
        for k in range(8):
            crc ^= tables[k, (x >> np.uint64(8 * k)) & np.uint64(255)]
    for j in range(8 * words, n):
        crc = (crc << np.uint64(8)) ^ tables[0, (crc >> np.uint64(56)) ^ np.uint64(data[j])]
    return crc


def crc64(data: bytes) -> int:
    """OpenIGTLink's CRC-64 of ``data`` (a message body), as pyigtl's ``CRC64(data)``."""
    return int(_crc64(np.frombuffer(data, np.uint8), _TABLES))


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
    if struct.unpack("> Q", header[50:58])[0] != crc64(body):
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
    connected. ``reconnect=False``: the thread ends when the server closes the stream or the
    connection breaks.
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
        crc64(b"")  # compiled (or loaded from numba's cache) before the first message

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
            except OSError as exc:  # a reset or a broken pipe: the server went away too
                self._event("lost", f"the connection to {where} was lost "
                            f"({exc.strerror or exc})"
                            + ("; reconnecting" if self.reconnect else ""))
                self._drop()
                if not self.reconnect:
                    break
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
