"""``comreg live`` at a scanner's frame rate, on 127.0.0.1: ``comreg replay --fps 40`` serves 10 s
of a sweep whose probe pauses (25 real frames of the fibula sweep, each followed by 15 copies
whose poses jitter by tracking noise, 0.1 mm and 0.01 deg: 400 frames) into ``comreg live``
(real processes, default settings: 0.5 mm / 0.5 deg frame spacing, 0.5 s age limit). The queue
stays bounded: no frame is older than the limit when an update registers it and none is dropped
for lag; the 375 copies are skipped as no new bone, counted in the status line and
``updates.csv``, and kept in the record (``frames.csv``, with their poses). ``comreg replay``
keeps the timing it is asked for: the recorded one at ``--rate``, a fixed one at ``--fps``."""

from __future__ import annotations

import csv
import json
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.live.igtl import ConnectionClosed, read_message
from comreg_core.live.replay import ReplayServer, replay_sweep
from comreg_core.live.run import FINAL_ANSWERS
from comreg_core.live.updates import read_updates
from tests.helpers import FIBULA_DIR

REPO = Path(__file__).resolve().parents[2]
#: Real frames of the sweep, and the frames each is held for (itself and its copies).
REAL, HELD = range(40, 65), 16


def _held_sweep(out: Path, held: list[int], seed: int) -> Path:
    """A frame folder in ``out`` serving the fibula sweep's frames ``held`` in order (the images
    linked, not copied), 25 ms apart; a frame repeating the one before it is a copy whose pose
    jitters by tracking noise (0.1 mm, 0.01 deg): the probe rests."""
    (out / "frames").mkdir(parents=True)
    shutil.copy(FIBULA_DIR / "calibration.json", out / "calibration.json")
    with open(FIBULA_DIR / "tracking.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    rng = np.random.default_rng(seed)
    served = []
    for n, k in enumerate(held):
        row = dict(rows[k], timestamp=str(1_000_000 + 25 * n))
        if n and held[n - 1] == k:
            for axis in "xyz":
                row[axis] = repr(float(row[axis]) + rng.uniform(-0.05, 0.05))
                row[f"euler_{axis}"] = repr(float(row[f"euler_{axis}"])
                                            + rng.uniform(-0.005, 0.005))
        (out / "frames" / f"{row['timestamp']}.png").symlink_to(
            FIBULA_DIR / "frames" / f"{rows[k]['timestamp']}.png")
        served.append(row)
    with open(out / "tracking.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(served)
    return out


@pytest.fixture(scope="module")
def paused_sweep(shared_data, tmp_path_factory) -> Path:
    """The sweep of the module docstring: each of the frames ``REAL`` held for ``HELD``."""
    return _held_sweep(tmp_path_factory.mktemp("paused"),
                       [k for k in REAL for _ in range(HELD)], seed=4)


def _live(sweep: Path, ct: Path, out: Path) -> tuple[subprocess.CompletedProcess, str]:
    """``comreg replay --fps 40`` of ``sweep`` into ``comreg live --until-end`` (default
    settings) on 127.0.0.1: live's completed process and the replay's output."""
    cli = [sys.executable, "-m", "comreg_core.cli"]
    replay = subprocess.Popen(cli + ["replay", str(sweep), "--port", "0", "--fps", "40",
                                     "--wait", "120"], cwd=REPO, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        port = int(re.search(r":(\d+); waiting", replay.stderr.readline()).group(1))
        live = subprocess.run(cli + ["live", "--igtl", f"127.0.0.1:{port}", "--ct", str(ct),
                                     "--out", str(out), "--until-end", "--no-report"],
                              cwd=REPO, capture_output=True, text=True, timeout=240)
        served, _ = replay.communicate(timeout=60)
    finally:
        replay.kill()
    assert live.returncode == 0, live.stderr
    return live, served


def test_forty_frames_a_second_for_ten_seconds_keep_the_queue_bounded(paused_sweep, ct_stl,
                                                                     tmp_path):
    out = tmp_path / "live"
    live, served = _live(paused_sweep, ct_stl, out)
    timing = re.search(r"served 400 frames in ([\d.]+) s: 400 sent; on time within (\d+) ms",
                       served)
    assert timing and 9.9 <= float(timing.group(1)) <= 10.5, served
    assert re.search(r"\d+ updates; 25 of 400 frames registered; 375 skipped \(no new bone\)$",
                     live.stdout, re.MULTILINE), live.stdout  # and nothing "not used"
    assert "dropped" not in live.stdout
    # frames queued behind one with new bone while the worker is busy: within the limit's
    # 0.5 s of frames (20), since none was dropped for its age
    queued = [int(n) for n in re.findall(r"LAGGING: (\d+) frames waiting", live.stdout)]
    assert max(queued, default=0) <= 20, queued

    rows = read_updates(out / "updates.csv")
    assert len(rows) >= 5
    assert all(r["dropped_lag"] == 0 and r["dropped_no_pose"] == 0 for r in rows)
    # a frame waits for detection within the limit, then for the update under way at most: no
    # frame older than the limit when updates take under half of it (an idle machine); this
    # one is shared, and its load stretches the updates
    longest = max(r["update_s"] for r in rows)
    limit = 0.5 if longest <= 0.25 else 0.5 + longest + 0.1
    ages = [r["frame_age_s"] for r in rows if np.isfinite(r["frame_age_s"])]  # NaN: no frame
    assert len(ages) >= 5 and all(0.0 <= a <= limit for a in ages), (ages, longest)
    skipped = [r["skipped_no_new_bone"] for r in rows]
    assert skipped == sorted(skipped) and 300 <= skipped[-1] <= 375
    for row in rows:  # at most the copies served before the frames it registered
        assert row["skipped_no_new_bone"] <= row["frames_received"] - row["frames_used"]
    status = [line for line in live.stdout.splitlines() if line.startswith("[")]
    assert f"{int(skipped[-1])} skipped (no new bone)" in status[-1]

    with open(out / "frames.csv", newline="") as f:
        frames = list(csv.DictReader(f))
    assert [int(r["index"]) for r in frames] == list(range(400))
    fates = [r["fate"] for r in frames]
    assert fates == ["used" if k % HELD == 0 else "skipped" for k in range(400)]
    ages = [float(r["age_s"]) for r in frames if r["fate"] == "used" and r["age_s"]]
    assert len(ages) >= 20 and all(0.0 <= a <= limit for a in ages)
    assert all(r["age_s"] == "" and r["raw_points"] == "" for r in frames if r["fate"] != "used")
    served_poses = read_tracked_sweep(paused_sweep).T_ref_image
    for r in frames:  # every frame's pose kept (sent as float32)
        pose = np.array([float(r[f"T_ref_image_{i}{j}"]) for i in range(3) for j in range(4)])
        assert np.abs(pose.reshape(3, 4) - served_poses[int(r["index"])][:3]).max() < 2e-3
    result = json.loads((out / "result.json").read_text())
    assert result["n_points"] == len(np.load(out / "us_points_frames.npy"))
    assert set(np.unique(np.load(out / "us_points_frames.npy"))) <= set(range(0, 400, HELD))


def test_a_full_search_s_answer_is_used_while_the_probe_rests(shared_data, ct_stl, tmp_path):
    # 12 frames with new bone (0.3 s at 40 frames/s), then the probe rests for 6 s: every
    # frame after is skipped (no new bone), and the answer of the first full search, asked
    # for at the third frame, still makes an update while the stream goes on
    sweep = _held_sweep(tmp_path / "held", [*range(40, 52), *[51] * 240], seed=5)
    out = tmp_path / "live"
    live, _ = _live(sweep, ct_stl, out)
    with open(out / "frames.csv", newline="") as f:
        frames = list(csv.DictReader(f))
    assert [r["fate"] for r in frames] == ["used"] * 12 + ["skipped"] * 240
    stream_end = float(frames[-1]["received_s"])
    rows = read_updates(out / "updates.csv")
    resting = [r for r in rows if r["time_s"] < stream_end - 0.5]
    assert resting, (stream_end, [(r["time_s"], r["mode"]) for r in rows])
    assert all(r["frames_used"] == 12 for r in resting)
    # each of them an answer alone (no frame taken) or with the last new frames
    assert resting[0]["mode"] == "warm+full"
    alone = [r for r in rows if not np.isfinite(r["frame_age_s"])]
    assert alone and all(r["mode"] == "warm+full" for r in alone)
    assert alone[0]["time_s"] < stream_end - 0.5
    # after the stream ended, at most FINAL_ANSWERS more answers
    assert sum(r["time_s"] > stream_end for r in rows) <= FINAL_ANSWERS
    assert re.search(r"12 of 252 frames registered; 240 skipped \(no new bone\)$", live.stdout,
                     re.MULTILINE), live.stdout


def _arrivals(sweep, **timing) -> tuple[list[float], object]:
    """Serve ``sweep`` on 127.0.0.1 with ``timing`` (``rate=`` or ``fps=``) to a plain reader;
    the arrival times (s) of its IMAGE messages, and the replay's stats."""
    server = ReplayServer(port=0)
    stats = {}
    serving = threading.Thread(target=lambda: stats.update(done=replay_sweep(
        sweep, server, wait_s=30, **timing)))
    serving.start()
    arrivals = []
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        try:  # until the replay closes the connection
            while (message := read_message(sock, 10.0)) is not None:
                if message.message_type == "IMAGE":
                    arrivals.append(time.monotonic())
        except ConnectionClosed:
            pass
    serving.join(30)
    assert len(arrivals) == sweep.n_frames
    return arrivals, stats["done"]


@pytest.mark.parametrize("timing", [{"rate": 20.0}, {"fps": 40.0}], ids=["rate20", "fps40"])
def test_the_replay_keeps_the_timing_asked_for(sweep12, timing):
    sweep = read_tracked_sweep(sweep12)
    arrivals, stats = _arrivals(sweep, **timing)
    if "rate" in timing:
        due = (sweep.timestamps - sweep.timestamps[0]) / timing["rate"]
    else:
        due = np.arange(sweep.n_frames) / timing["fps"]
    off = (np.array(arrivals) - arrivals[0]) - due
    # each frame close to its due time (a busy machine may delay one now and then)
    assert np.median(np.abs(off)) < 0.01 and np.abs(off).max() < 0.1, off
    assert stats.sent == sweep.n_frames and stats.late_max_s < 0.1
