"""``comreg replay`` sends the probe's pose (``ProbeToReference``) beside the image's, as PLUS
Server does for a tracked probe, so that ``live --calibration`` pairs frames too:

- the replay's command on 127.0.0.1 (a real server process) into ``run_live`` (a real client)
  once with the image's poses and once with the probe's and the calibration: every frame
  paired both times, and the same bone points;
- the probe's poses of a PLUS sequence derived from its calibration against the file's own
  ``inv(ReferenceToTracker) @ ProbeToTracker`` (read here with a regex), and those of a
  synthetic PLUS file holding them (or not) without a calibration file.
"""

from __future__ import annotations

import re
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from comreg_core.cli import app
from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.live.receiver import FrameReceiver
from comreg_core.live.run import run_live
from comreg_core.live.session import LiveSession
from comreg_core.live.stream import probe_calibration, recorded_probe_poses
from tests.helpers import SHARED_DATA, assert_close
from tests.live.conftest import cut_sweep

REPO = Path(__file__).resolve().parents[2]
SPINE = SHARED_DATA / "plus" / "TestImages" / "SpinePhantomFreehand.igs.mha"
SPINE_XML = SHARED_DATA / "plus" / "ConfigFiles" / "Testing" / \
    "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"
#: Poses cross the wire as float32: at the fibula's 1.5 m from the tracker's origin one step of
#: float32 is 1.2e-4 mm, so the two ways of giving a pose agree to a few of those.
WIRE_MM = 5e-4


@pytest.fixture(scope="module")
def sweep4(shared_data, tmp_path_factory) -> Path:
    return cut_sweep(tmp_path_factory.mktemp("sweep4"), 0, 4, step=5)


def _start_replay(folder: Path) -> tuple[subprocess.Popen, int, str]:
    """``comreg replay folder`` (a process) waiting for a client: (it, its port, its line)."""
    replay = subprocess.Popen([sys.executable, "-m", "comreg_core.cli", "replay", str(folder),
                               "--port", "0", "--rate", "20", "--wait", "60"], cwd=REPO,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = replay.stderr.readline()
    found = re.search(r"on 127\.0\.0\.1:(\d+); waiting", first)
    if found is None:
        replay.kill()
        pytest.fail(f"comreg replay did not start: {first}{replay.stderr.read()}")
    return replay, int(found.group(1)), first


def _live(replay: tuple, registrar, pose_device: str, T_probe_pixel):
    """``run_live --until-end`` here on the replay's stream; returns (the session, the
    receiver, the replay's stdout, its stderr)."""
    process, port, first = replay
    session = LiveSession(registrar)
    receiver = FrameReceiver("127.0.0.1", port, "Image", pose_device, T_probe_pixel,
                             reconnect=False, connect_timeout_s=10.0)
    notes = []
    run_live(session, receiver, until_end=True, on_note=notes.append,
             on_status=lambda line: None)
    out, err = process.communicate(timeout=30)
    assert not any("without" in n or "unusable" in n for n in notes), notes
    session.drain()
    return session, receiver, out, first + err


def test_live_pairs_the_replay_with_and_without_the_calibration(sweep4, search_registrar):
    replays = [_start_replay(sweep4), _start_replay(sweep4)]  # both start up at once
    try:
        image = _live(replays[0], search_registrar, "ImageToReference", None)
        probe = _live(replays[1], search_registrar, "ProbeToReference",
                      probe_calibration(sweep4 / "calibration.json"))
    finally:
        for process, _, _ in replays:
            process.kill()
    for session, receiver, out, err in (image, probe):
        assert "served 4 frames" in out and "4 sent" in out and "without" not in out, out
        assert "replay:" not in err and "Traceback" not in err, err
        assert receiver.assembler.images == 4 and receiver.assembler.without_pose == 0
        assert receiver.assembler.bad_poses == 0 and session.points.frames_used == 4
    by_image, by_probe = image[0].points.cloud(), probe[0].points.cloud()
    assert len(by_image.points) > 100
    assert np.array_equal(by_image.frame_index, by_probe.frame_index)
    assert_close(by_probe.points, by_image.points, atol=WIRE_MM, what="points (mm)")
    poses = [np.stack([r.T_ref_image for r in sorted(s.points.records, key=lambda r: r.index)])
             for s in (image[0], probe[0])]
    assert_close(poses[1], poses[0], atol=WIRE_MM, what="T_ref_image")


def _naive_tracker_poses(path: Path, name: str) -> np.ndarray:
    """``(N, 4, 4)`` the ``Seq_FrameXXXX_<name>Transform`` fields of a PLUS metafile header."""
    header = path.read_bytes().split(b"ElementDataFile", 1)[0].decode("latin-1")
    found = re.findall(rf"^Seq_Frame(\d+)_{name}Transform = (.*)$", header, re.M)
    return np.stack([np.array(text.split(), float).reshape(4, 4)
                     for _, text in sorted(found, key=lambda f: int(f[0]))])


def test_a_plus_sequence_gives_the_probe_poses_through_its_calibration(shared_data):
    sweep = read_tracked_sweep(SPINE, calibration=SPINE_XML)
    poses, source = recorded_probe_poses(sweep, SPINE_XML)
    expected = np.linalg.inv(_naive_tracker_poses(SPINE, "ReferenceToTracker")) @ \
        _naive_tracker_poses(SPINE, "ProbeToTracker")
    valid = sweep.valid
    assert valid.sum() >= 15 and "calibration" in source
    assert_close(poses[valid], expected[valid], atol=1e-6, what="ProbeToReference")
    assert np.isnan(poses[~valid]).all()
    # and live's composition gives the image's pixels back (its third column is rebuilt)
    C = probe_calibration(SPINE_XML)
    assert_close((poses[valid] @ C)[:, :, [0, 1, 3]], sweep.T_ref_pixel[valid][:, :, [0, 1, 3]],
                 atol=1e-9, what="ProbeToReference @ ImageToProbe")


def _write_plus(path: Path, transforms: dict[str, np.ndarray]) -> Path:
    """A PLUS sequence metafile of two 8 x 8 frames with per-frame ``transforms`` (name ->
    ``(2, 4, 4)``)."""
    data = zlib.compress(np.full((2, 8, 8), 100, np.uint8).tobytes())
    lines = ["ObjectType = Image", "NDims = 3", "BinaryData = True", "CompressedData = True",
             f"CompressedDataSize = {len(data)}", "DimSize = 8 8 2", "ElementSpacing = 1 1 1",
             "ElementType = MET_UCHAR", "UltrasoundImageOrientation = MF"]
    for i in range(2):
        lines.append(f"Seq_Frame{i:04d}_Timestamp = {i * 0.1:.3f}")
        for name, T in transforms.items():
            lines += [f"Seq_Frame{i:04d}_{name}Transform = "
                      + " ".join(repr(float(v)) for v in T[i].ravel()),
                      f"Seq_Frame{i:04d}_{name}TransformStatus = OK"]
    lines.append("ElementDataFile = LOCAL")
    path.write_bytes(("\n".join(lines) + "\n").encode("latin-1") + data)
    return path


def _rigid(rng, n=2) -> np.ndarray:
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.uniform(-100, 100, (n, 3))
    return T


def test_a_plus_sequence_without_a_calibration_file(tmp_path):
    """Its own ImageToProbe per frame: the probe's poses are its chain's. Only the image's
    poses: none, and the replay says so in one line."""
    rng = np.random.default_rng(3)
    probe, reference = _rigid(rng), _rigid(rng)
    image_to_probe = _rigid(rng) @ np.diag([0.1, 0.1, 0.1, 1.0])
    chain = _write_plus(tmp_path / "chain.igs.mha", {
        "ImageToProbe": image_to_probe, "ProbeToTracker": probe,
        "ReferenceToTracker": reference})
    poses, source = recorded_probe_poses(read_tracked_sweep(chain))
    assert "ProbeToReference" in source
    assert_close(poses, np.linalg.inv(reference) @ probe, atol=1e-9, what="ProbeToReference")

    image_only = _write_plus(tmp_path / "image.igs.mha",
                             {"ImageToReference": np.linalg.inv(reference) @ probe
                              @ image_to_probe})
    poses, source = recorded_probe_poses(read_tracked_sweep(image_only))
    assert poses is None and "no probe pose" in source
    result = CliRunner().invoke(app, ["replay", str(image_only), "--port", "0", "--wait", "0.2"])
    assert result.exit_code == 2  # no client came
    said = [line for line in result.stderr.splitlines() if line.startswith("replay:")]
    assert said == ["replay: sending ImageToReference only, no ProbeToReference: the recording "
                    "gives no probe pose and there is no probe calibration to derive it from "
                    "(--probe-calibration)"]
