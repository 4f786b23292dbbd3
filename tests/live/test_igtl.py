"""The live client against a raw TCP server on 127.0.0.1 that sends real OpenIGTLink messages
(packed by pyigtl) mixed with what a stream should not hold: a message type pyigtl does not
know, a known type live does not read, a body whose CRC does not match, and bytes that are no
OpenIGTLink header at all. Each gives one line; the client keeps going (and after the
unreadable header reconnects). And the connect timeout: a client that never connected gives up
after it; one that connected once retries for as long as it runs."""

from __future__ import annotations

import socket
import time

import numpy as np
import pyigtl
import pytest

from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.live.replay import frame_messages
from comreg_core.live.receiver import FrameReceiver
from tests.live.conftest import cut_sweep


@pytest.fixture(scope="module")
def sweep3(shared_data, tmp_path_factory):
    return read_tracked_sweep(cut_sweep(tmp_path_factory.mktemp("sweep3"), 60, 3))


def _listen(port: int) -> socket.socket:
    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", port))
    server.listen()
    server.settimeout(10.0)
    return server


def _collect(receiver: FrameReceiver, frames: int, notes: int, timeout_s: float = 10.0):
    got_frames, got_notes = [], []
    end = time.monotonic() + timeout_s
    while (len(got_frames) < frames or len(got_notes) < notes) and time.monotonic() < end:
        batch = receiver.take(0.05)
        got_frames += batch.frames
        got_notes += batch.notes
    return got_frames, got_notes


def _frame_bytes(sweep, i) -> bytes:
    return b"".join(m.pack() for m in frame_messages(sweep, i, 100.0 + i))


def test_unexpected_and_malformed_messages_give_one_line_and_the_client_goes_on(sweep3, port):
    listener = _listen(port)
    receiver = FrameReceiver("127.0.0.1", port, "Image", "ImageToReference")
    receiver.start()
    try:
        conn, _ = listener.accept()
        frames, notes = _collect(receiver, 0, 1)
        assert notes == [f"connected to 127.0.0.1:{port}"]

        unknown = bytearray(pyigtl.StringMessage("hello", device_name="Thing").pack())
        unknown[2:14] = b"FOOBAR".ljust(12, b"\0")  # a type pyigtl does not know
        bad_crc = bytearray(pyigtl.TransformMessage(np.eye(4), device_name="ImageToReference",
                                                    timestamp=5.0).pack())
        bad_crc[-1] ^= 0xFF  # the body no longer matches the header's CRC
        point = pyigtl.PointMessage(positions=[[1.0, 2.0, 3.0]], names=["p"],
                                    device_name="Stylus").pack()
        conn.sendall(_frame_bytes(sweep3, 0) + bytes(unknown) + bytes(unknown) + point
                     + bytes(bad_crc) + _frame_bytes(sweep3, 1))
        frames, notes = _collect(receiver, 2, 3)
        assert [f.index for f in frames] == [0, 1]
        assert all("\n" not in note for note in notes)
        assert len(notes) == 3, notes  # the unknown type is told once
        assert sum("unexpected FOOBAR messages of 'Thing'" in n for n in notes) == 1
        assert sum("ignoring the POINT messages of 'Stylus'" in n for n in notes) == 1
        assert sum("CRC does not match" in n and n.endswith("skipped") for n in notes) == 1

        # bytes that are no OpenIGTLink header: the stream cannot be followed; reconnect
        conn.sendall(b"\x00\x07" + b"garbage!" * 7)
        conn2, _ = listener.accept()  # the client dropped the connection and came back
        frames, notes = _collect(receiver, 0, 2)
        assert notes == ["received a message header that is not OpenIGTLink (version 7, a "
                         f"body of {int.from_bytes(b'garbage!', 'big')} bytes); reconnecting",
                         f"connected to 127.0.0.1:{port}"]
        conn2.sendall(_frame_bytes(sweep3, 2))
        frames, notes = _collect(receiver, 1, 0)
        assert [f.index for f in frames] == [2] and notes == []
        assert receiver.assembler.images == 3 and receiver.assembler.without_pose == 0
        conn.close()
        conn2.close()
    finally:
        receiver.stop()
        listener.close()


def _batches(receiver: FrameReceiver, seconds: float) -> tuple[list[str], str, float]:
    """What the receiver hands over for ``seconds`` (or until it gave up): its notes, why it
    gave up ("" if not) and when (s after the call)."""
    notes, start = [], time.monotonic()
    while time.monotonic() - start < seconds:
        batch = receiver.take(0.05)
        notes += batch.notes
        if batch.gave_up:
            return notes, batch.gave_up, time.monotonic() - start
    return notes, "", time.monotonic() - start


def test_the_connect_timeout_ends_a_client_that_never_connected(port):
    receiver = FrameReceiver("127.0.0.1", port, "Image", "ImageToReference",
                             connect_timeout_s=0.5)
    receiver.start()
    try:
        notes, gave_up, after = _batches(receiver, 5.0)
    finally:
        receiver.stop()
    assert gave_up == (f"no OpenIGTLink server answered at 127.0.0.1:{port} within 0.5 s "
                       "(Connection refused)")
    assert 0.4 < after < 1.5
    assert notes == [f"cannot connect to 127.0.0.1:{port} (Connection refused); retrying"]


def test_the_connect_timeout_is_the_first_connections_only(port):
    """Connected once, then the server goes away: the client retries past the timeout (and
    finds the server again when it comes back)."""
    listener = _listen(port)
    receiver = FrameReceiver("127.0.0.1", port, "Image", "ImageToReference",
                             connect_timeout_s=0.3)
    receiver.start()
    try:
        conn, _ = listener.accept()
        listener.close()  # first, so that the client cannot come back before it
        conn.close()
        notes, gave_up, _ = _batches(receiver, 1.2)
        assert gave_up == ""
        assert notes == [f"connected to 127.0.0.1:{port}",
                         f"127.0.0.1:{port} closed the connection; reconnecting",
                         f"cannot connect to 127.0.0.1:{port} (Connection refused); retrying"]
        listener = _listen(port)
        listener.accept()[0].close()
        notes, gave_up, _ = _batches(receiver, 0.5)
        assert gave_up == "" and notes[0] == f"connected to 127.0.0.1:{port}"
    finally:
        receiver.stop()
        listener.close()


def test_without_reconnecting_a_broken_connection_ends_the_stream(port):
    """``--until-end``'s client (no reconnect): a server that resets the connection (an RST,
    as a crashed PLUS Server's host sends) ends the stream as a clean close does, with one line
    and no attempt to reconnect."""
    import struct

    listener = _listen(port)
    receiver = FrameReceiver("127.0.0.1", port, "Image", "ImageToReference", reconnect=False)
    receiver.start()
    try:
        conn, _ = listener.accept()
        listener.close()
        notes, _, _ = _batches_until(receiver, f"connected to 127.0.0.1:{port}")
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        conn.close()  # linger 0: a reset, not a close (once the client says it is connected)
        ended = False
        end = time.monotonic() + 5.0
        while not ended and time.monotonic() < end:
            batch = receiver.take(0.05)
            notes += batch.notes
            ended = batch.ended
    finally:
        receiver.stop()
    assert ended, notes
    assert notes[0] == f"connected to 127.0.0.1:{port}"
    assert len(notes) == 2 and "reconnecting" not in notes[1], notes
    assert notes[1] in (f"127.0.0.1:{port} closed the connection",
                        f"the connection to 127.0.0.1:{port} was lost (Connection reset by peer)")


def _batches_until(receiver: FrameReceiver, note: str, timeout_s: float = 5.0):
    """The receiver's notes until ``note`` came (or ``timeout_s``): ``(notes, gave_up, s)``."""
    notes, start = [], time.monotonic()
    while note not in notes and time.monotonic() - start < timeout_s:
        notes += receiver.take(0.05).notes
    return notes, "", time.monotonic() - start


def test_a_closing_replay_server_lets_the_client_read_its_last_frames(sweep3):
    """The replay server ends the stream after the client has its last frames, even when the
    client's own messages wait unread: a server closing on unread messages resets the
    connection, and the client's system throws away the frames it had not read yet."""
    import threading

    from comreg_core.live.igtl import ConnectionClosed, read_message
    from comreg_core.live.replay import ReplayServer

    server = ReplayServer("127.0.0.1", 0)
    client = socket.create_connection(("127.0.0.1", server.port), timeout=10.0)
    try:
        assert server.wait_for_client(10.0)
        chatter = pyigtl.StringMessage("x" * 200, device_name="ReferenceToCT").pack()
        client.sendall(chatter * 2000)  # ~0.5 MB the server reads one message at a time
        for i in range(3):
            assert server.send_now(*frame_messages(sweep3, i, 100.0 + i))
        closing = threading.Thread(target=server.close)
        closing.start()
        time.sleep(0.5)  # the frames wait unread in the client's buffer while the server closes
        images = []
        end = time.monotonic() + 10.0
        while time.monotonic() < end:
            try:
                message = read_message(client, 1.0)
            except ConnectionClosed:
                break
            if isinstance(message, pyigtl.ImageMessage):
                images.append(message.timestamp)
        assert images == [100.0, 101.0, 102.0]
    finally:
        client.close()
        closing.join(10.0)
    assert not closing.is_alive()


def test_crc64_is_pyigtl_s(sweep3):
    """The compiled CRC-64 equals pyigtl's (crcmod's) on bodies of every length up to 40 bytes
    (the tail the 8-byte words leave), on random bodies and on a real frame's IMAGE body, and
    a flipped bit changes it."""
    from pyigtl.messages import CRC64

    from comreg_core.live.igtl import crc64

    rng = np.random.default_rng(0)
    bodies = [rng.integers(0, 256, n, dtype=np.uint8).tobytes() for n in range(41)]
    bodies += [rng.integers(0, 256, n, dtype=np.uint8).tobytes() for n in (1000, 65_539)]
    image = frame_messages(sweep3, 0, 1.5)[0].pack()[pyigtl.messages.MessageBase
                                                      .IGTL_HEADER_SIZE:]
    assert len(image) > 700_000
    for body in bodies + [image]:
        assert crc64(body) == CRC64(body)
    flipped = bytearray(image)
    flipped[12_345] ^= 0x10
    assert crc64(bytes(flipped)) != crc64(image)
