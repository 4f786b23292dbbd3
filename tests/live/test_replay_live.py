"""``comreg replay`` into ``comreg live`` on 127.0.0.1: real servers and clients (processes, or
threads in this process), frames of the real fibula sweep.

- end to end through the command line: updates.csv (columns, rows, rigid finite transforms,
  the last row's centroid = the saved points'), the points = ``extract-us``'s of the same
  frames, and the folder in the form of ``comreg register``'s (its file names, its
  result.json keys, its transform for the same points);
- a connection dropped and restored (the server stops, another starts on the same port): the
  client reconnects, keeps every frame and point, and the sweep (served moved by a known rigid
  transform) registers onto the pseudo ground truth; what it sent back is its updates, in the
  form 3D Slicer applies.
"""

from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comreg_core.io import read_points
from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.live.replay import ReplayServer, frame_messages
from comreg_core.live.receiver import FrameReceiver, slicer_transform
from comreg_core.live.run import finish_live, run_live
from comreg_core.live.session import LiveSession
from comreg_core.live.updates import UPDATE_COLUMNS, read_updates, row_transform
from comreg_core.register import register_to_directory
from comreg_core.surfaces.us import extract_us_surface
from tests.helpers import assert_close
from tests.live.conftest import cut_sweep

REPO = Path(__file__).resolve().parents[2]
#: What a live folder holds besides ``comreg register``'s files.
LIVE_FILES = {"updates.csv", "us_points.ply", "us_points_frames.npy", "frames.csv"}


@pytest.fixture(scope="module")
def sweep16(shared_data, tmp_path_factory):
    """Every third of the first 48 frames of the real sweep: about 230 mm of the fibula."""
    return cut_sweep(tmp_path_factory.mktemp("sweep16"), 0, 16, step=3)


def _check_rigid(T):
    assert np.isfinite(T).all()
    assert_close(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-6, what="R^T R")
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-6)
    assert_close(T[3], [0, 0, 0, 1], atol=0.0)


def _check_updates(path: Path, frames: int, last_received: bool = True) -> list[dict]:
    header = path.read_text().splitlines()[0].split(",")
    assert tuple(header) == UPDATE_COLUMNS
    rows = read_updates(path)
    assert rows, "no update was written"
    received = [r["frames_received"] for r in rows]
    used = [r["frames_used"] for r in rows]
    assert received == sorted(received) and used == sorted(used)
    assert received[-1] == frames if last_received else received[-1] <= frames
    assert all(u <= r for u, r in zip(used, received))
    for row in rows:
        assert row["verdict"] in ("ok", "check")
        assert row["latency_s"] >= 0 and row["covered_mm"] >= 0 and row["time_s"] >= 0
        assert 0.0 <= row["p_correct"] <= 1.0  # the uncertainty's own (no calibration given)
        _check_rigid(row_transform(row))
    return rows


def test_replay_into_live_through_the_command_line(sweep16, ct_stl, tmp_path):
    out = tmp_path / "live"
    replay = subprocess.Popen([sys.executable, "-m", "comreg_core.cli", "replay", str(sweep16),
                               "--port", "0", "--rate", "10", "--wait", "90"], cwd=REPO,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = replay.stderr.readline()
        port = int(re.search(r"on 127\.0\.0\.1:(\d+); waiting", first).group(1))
        live = subprocess.run([sys.executable, "-m", "comreg_core.cli", "live", "--igtl",
                               f"127.0.0.1:{port}", "--ct", str(ct_stl), "--out", str(out),
                               "--until-end"], cwd=REPO, capture_output=True, text=True,
                              timeout=150)
        replay_out, replay_err = replay.communicate(timeout=30)
    finally:
        replay.kill()
    assert live.returncode == 0, live.stderr
    assert "Traceback" not in live.stderr + replay_err
    assert "served 16 frames" in replay_out and "16 sent" in replay_out
    summary = re.search(r"\d+ updates; (\d+) of 16 frames registered", live.stdout)
    assert summary, live.stdout
    status = [line for line in live.stdout.splitlines() if line.startswith("[")]
    rows = _check_updates(out / "updates.csv", 16, last_received=False)
    assert len(status) == len(rows)

    # every frame in frames.csv; those used: all, unless the machine was too busy to keep up
    # (dropped for lag, and counted); none skipped (every third frame: far apart)
    with open(out / "frames.csv", newline="") as f:
        fates = list(csv.DictReader(f))
    assert [int(r["index"]) for r in fates] == list(range(16))
    used = [int(r["index"]) for r in fates if r["fate"] == "used"]
    assert len(used) == int(summary.group(1)) and len(used) >= 12
    assert {r["fate"] for r in fates} <= {"used", "lag"}
    lag = sum(r["fate"] == "lag" for r in fates)
    assert lag == 16 - len(used) and (not lag or f"{lag} dropped while lagging" in live.stdout)
    # the points: extract-us's of the same frames (poses crossed the wire as float32)
    sweep = read_tracked_sweep(sweep16)
    expected = extract_us_surface(_frames_of(sweep, used)).points
    saved = read_points(out / "us_points.ply")
    assert saved.points.shape == expected.points.shape and saved.beam_origins is not None
    assert_close(saved.points, expected.points, atol=2e-3, what="points (mm)")
    assert np.array_equal(np.load(out / "us_points_frames.npy"),
                          np.array(used)[expected.frame_index])
    assert_close(rows[-1]["centroid_x"], saved.points[:, 0].mean(), atol=1e-3)
    assert_close([rows[-1][f"centroid_{a}"] for a in "xyz"], saved.points.mean(axis=0),
                 atol=1e-3, what="last update's centroid")

    # the folder in the form of comreg register's, and its registration for these points
    from comreg_core.register import register_to_directory

    reference = tmp_path / "register"
    register_to_directory(None, out / "us_points.ply", reference, ct_mesh=ct_stl)
    names = {p.name for p in out.iterdir()}
    assert {p.name for p in reference.iterdir()} | {"report.html", "report_images"} | \
        LIVE_FILES == names
    ours = json.loads((out / "result.json").read_text())
    theirs = json.loads((reference / "result.json").read_text())
    assert set(ours) == set(theirs)
    assert_close(ours["T_ct_us"], theirs["T_ct_us"], atol=1e-9)
    assert ours["verdict"] == theirs["verdict"]
    assert "Verdict:" in (out / "report.html").read_text()


def _frames_of(sweep, indices):
    """The sweep of its frames ``indices`` alone."""
    from dataclasses import replace

    keep = np.array(indices)
    return replace(sweep, frames=sweep.frames[keep], T_ref_image=sweep.T_ref_image[keep],
                   timestamps=sweep.timestamps[keep], valid=sweep.valid[keep],
                   frame_names=[sweep.frame_names[i] for i in keep])


def _moved(sweep, T_move):
    """The sweep tracked in another frame: every pose premultiplied by ``T_move``."""
    from dataclasses import replace

    return replace(sweep, T_ref_image=T_move @ sweep.T_ref_image)


def _serve(sweep, server: ReplayServer, frames, replies_wanted: int, timeout_s=60.0) -> None:
    """Serve ``frames`` of ``sweep`` at once; then keep the connection until the client sent
    ``replies_wanted`` messages back (or the time is up); then close."""
    try:
        assert server.wait_for_client(timeout_s)
        for i in frames:
            assert server.send_now(*frame_messages(sweep, i, float(sweep.timestamps[i])))
        end = time.monotonic() + timeout_s
        while len(server.replies) < replies_wanted and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        server.close()


def test_a_dropped_connection_is_restored_and_nothing_is_lost(sweep16, search_registrar, ct_stl,
                                                             port, tmp_path):
    from comreg_core.demo import pseudo_ground_truth
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm

    sweep = read_tracked_sweep(sweep16)
    T_move = np.eye(4)
    T_move[:3, :3] = Rotation.from_rotvec(np.radians(40.0) * np.array([0.6, 0.0, 0.8]))\
        .as_matrix()
    T_move[:3, 3] = [100.0, -50.0, 30.0]
    served = _moved(sweep, T_move)

    session = LiveSession(search_registrar)
    receiver = FrameReceiver("127.0.0.1", port, "Image", "ImageToReference")
    notes, stop = [], threading.Event()
    worker = threading.Thread(target=run_live, args=(session, receiver), kwargs=dict(
        out_dir=tmp_path, stop=stop, on_note=notes.append, on_status=lambda line: None))
    first = ReplayServer(port=port)
    worker.start()
    try:
        _serve(served, first, range(8), replies_wanted=2)  # one update: TRANSFORM + STRING
        second = ReplayServer(port=port)  # the same port, as a restarted PLUS Server
        _serve(served, second, range(8, 16), replies_wanted=2)
        end = time.monotonic() + 60
        while (session.backlog or session.points.frames_used < 16) and time.monotonic() < end:
            time.sleep(0.1)
    finally:
        stop.set()
        worker.join(timeout=60)
    assert not worker.is_alive()
    assert sum(n == f"connected to 127.0.0.1:{port}" for n in notes) == 2, notes
    assert f"127.0.0.1:{port} closed the connection; reconnecting" in notes
    assert receiver.assembler.images == 16 and session.points.frames_used == 16
    assert [r.index for r in sorted(session.points.records, key=lambda r: r.index)] == \
        list(range(16))
    rows = _check_updates(tmp_path / "updates.csv", 16)

    # what went back: each TRANSFORM is an update's pose as Slicer applies it, each STRING its
    # JSON status
    sent = [slicer_transform(row_transform(r), "LPS") for r in rows]
    for server in (first, second):
        kinds = [m.message_type for m in server.replies]
        assert kinds[:2] == ["TRANSFORM", "STRING"], kinds
        for message in server.replies:
            if message.message_type == "TRANSFORM":
                assert message.device_name == "ReferenceToCT"
                assert min(np.abs(message.matrix - T).max() for T in sent) < 1e-3
            else:
                status = json.loads(message.string)
                assert message.device_name == "ComRegStatus"
                assert status["verdict"] in ("ok", "check") and "advice" in status
                assert status["covered_mm"] >= 0
                assert status["bound_mm"] > 0 and "bone's long axis" in status["weakest"]

    # every frame's points kept: the final folder registers extract-us's cloud of all 16,
    # onto the pseudo ground truth moved by T_move
    result, _ = finish_live(session, tmp_path, ct_mesh=ct_stl, report=False)
    expected = extract_us_surface(sweep).points
    assert result.n_points == len(expected.points)
    T_truth = pseudo_ground_truth(expected.points, search_registrar.surface) @ \
        np.linalg.inv(T_move)
    centroid = read_points(tmp_path / "us_points.ply").points.mean(axis=0)
    assert translation_error_mm(result.T_ct_us, T_truth, centroid) < 4.0
    assert rotation_error_deg(result.T_ct_us, T_truth) < 5.0
    # by the session's own registrar (its CT side ready): what a fresh one gives, bit for bit
    fresh = register_to_directory(None, tmp_path / "us_points.ply", tmp_path / "fresh",
                                  ct_mesh=ct_stl, seed=session.seed)
    assert np.array_equal(fresh.T_ct_us, result.T_ct_us)
    assert json.loads((tmp_path / "fresh" / "result.json").read_text())["verdict"] == \
        json.loads((tmp_path / "result.json").read_text())["verdict"]


@pytest.mark.parametrize("stop", ["SIGINT", "SIGTERM"])
def test_ctrl_c_or_sigterm_stops_live_which_then_writes_its_folder(sweep16, ct_stl, tmp_path,
                                                                     stop):
    """Without --until-end live outlives the stream (it reconnects, once told) until Ctrl-C
    (SIGINT) or SIGTERM; then it writes the register folder (here without the report).

    live is started as from a terminal, Ctrl-C handled: a process a shell starts in the
    background (this test run's, possibly) inherits SIGINT ignored, and Python then ignores
    Ctrl-C too; SIGTERM reaches it either way."""
    import signal

    out = tmp_path / "live"
    cli = [sys.executable, "-m", "comreg_core.cli"]
    replay = subprocess.Popen(cli + ["replay", str(sweep16), "--port", "0", "--rate", "10",
                                     "--wait", "90"], cwd=REPO, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    live = None
    try:
        port = int(re.search(r":(\d+); waiting", replay.stderr.readline()).group(1))
        ours = signal.signal(signal.SIGINT, signal.default_int_handler)  # the child: SIG_DFL
        try:
            live = subprocess.Popen([sys.executable, "-X", "faulthandler", "-m",
                                     "comreg_core.cli", "live", "--igtl", f"127.0.0.1:{port}",
                                     "--ct", str(ct_stl), "--out", str(out), "--no-report"],
                                    cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    text=True)
        finally:
            signal.signal(signal.SIGINT, ours)
        replay.communicate(timeout=90)
        end = time.monotonic() + 90
        while time.monotonic() < end:  # every frame registered: the loop is idle
            rows = read_updates(out / "updates.csv") if (out / "updates.csv").exists() else []
            if rows and rows[-1]["frames_used"] == 16:
                break
            time.sleep(0.2)
        live.send_signal(getattr(signal, stop))
        try:
            stdout, stderr = live.communicate(timeout=90)
        except subprocess.TimeoutExpired:  # where it is stuck: faulthandler's stacks
            live.send_signal(signal.SIGABRT)
            stdout, stderr = live.communicate(timeout=30)
            stacks = stderr[stderr.find("Fatal Python error"):].split("\nExtension modules")[0]
            pytest.fail(f"live did not stop on {stop}; its threads:\n{stacks}")
    finally:
        replay.kill()
        if live is not None:
            live.kill()
    assert live.returncode == 0, stderr
    notes = [line for line in stderr.splitlines() if line.startswith("live: ")]
    # the server went away: seen as a close while reading or a broken pipe while sending an
    # update (which of the two is a race with the client's own sends); either way it reconnects
    gone = (f"live: 127.0.0.1:{port} closed the connection; reconnecting",
            f"live: the connection to 127.0.0.1:{port} was lost")
    assert sum(n.startswith(gone) and n.endswith("reconnecting") for n in notes) == 1, notes
    assert sum("cannot connect" in n and n.endswith("retrying") for n in notes) == 1
    assert notes[-1] == f"live: stopping ({'Ctrl-C' if stop == 'SIGINT' else stop})"
    assert "Traceback" not in stderr
    assert re.search(r"\d+ updates; 16 of 16 frames registered", stdout)
    assert (out / "result.json").is_file() and (out / "transform.tfm").is_file()
    assert not (out / "report.html").exists()
    assert json.loads((out / "result.json").read_text())["n_points"] == \
        len(read_points(out / "us_points.ply").points)
