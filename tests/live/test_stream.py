"""A live sweep's frames and points (comreg_core.live.stream), without sockets: pairing images
with poses (the frame folder reader as the reference), the probe calibration, the points
against ``extract-us``'s, the covered length against a naive union of intervals."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.live.intake import coalesce
from comreg_core.live.points import SweepPoints, covered_length_mm
from comreg_core.live.stream import Frame, FrameAssembler, probe_calibration
from tests.helpers import assert_close
from tests.live.conftest import cut_sweep


@pytest.fixture(scope="module")
def sweep6(shared_data, tmp_path_factory):
    return cut_sweep(tmp_path_factory.mktemp("sweep6"), 40, 6, step=3)


def _naive_covered(along, gap, min_points):
    """The union of stretches, one point at a time."""
    s = sorted(along)
    total, first, count = 0.0, s[0], 1
    for a, b in zip(s, s[1:]):
        if b - a > gap:
            total += (a - first) if count >= min_points else 0.0
            first, count = b, 1
        else:
            count += 1
    return total + ((s[-1] - first) if count >= min_points else 0.0)


def test_covered_length_is_the_union_of_the_stretches():
    rng = np.random.default_rng(3)
    for _ in range(20):
        centres = rng.uniform(-200, 200, rng.integers(1, 6))
        along = np.concatenate([c + rng.uniform(0, rng.uniform(1, 80), rng.integers(1, 200))
                                for c in centres])
        assert_close(covered_length_mm(along, 15.0, 20), _naive_covered(along, 15.0, 20),
                     atol=1e-9)
    assert covered_length_mm(np.array([])) == 0.0
    assert covered_length_mm(np.linspace(0, 100, 101), 40.0, 20) == pytest.approx(100.0)
    # two stretches 50 mm apart, and a stray echo: 30 + 20 mm
    along = np.concatenate([np.linspace(0, 30, 50), np.linspace(80, 100, 50), [300.0]])
    assert covered_length_mm(along, 40.0, 20) == pytest.approx(50.0)


def test_coalesce_spreads_the_frames_and_keeps_the_newest():
    frames = list(range(20))
    picked = coalesce(frames, 8)
    assert len(picked) == 8 and picked == sorted(picked) and picked[-1] == 19 and picked[0] == 0
    assert np.diff(picked).max() - np.diff(picked).min() <= 1
    assert coalesce(frames[:5], 8) == frames[:5]


def _messages(sweep, i):
    """(image (H, W), identity matrix, timestamp, T_ref_pixel) as PLUS Server sends frame i."""
    return sweep.frames[i], np.eye(4), float(sweep.timestamps[i]), sweep.T_ref_pixel[i]


def test_images_pair_with_the_pose_of_the_same_timestamp_in_either_order(sweep6):
    sweep = read_tracked_sweep(sweep6)
    assembler = FrameAssembler("ImageToReference")
    frames = []
    for i in range(sweep.n_frames):
        image, ijk, t, pose = _messages(sweep, i)
        if i % 2:  # pose first, then the image
            frames += assembler.add_pose("StylusToReference", np.eye(4), t, 0.0)[0]
            frames += assembler.add_pose("ImageToReference", pose, t, 0.0)[0]
            frames += assembler.add_image(image, ijk, t, 0.0)[0]
        else:
            frames += assembler.add_image(image, ijk, t, 0.0)[0]
            frames += assembler.add_pose("ImageToReference", pose, t, 0.0)[0]
    assert [f.index for f in frames] == list(range(sweep.n_frames))
    for f in frames:
        assert_close(f.T_ref_image, sweep.T_ref_image[f.index], atol=1e-9)
        assert_close(f.spacing, sweep.spacing, atol=1e-12)
        assert np.array_equal(f.image, sweep.frames[f.index])


def test_an_image_without_a_pose_is_one_note_and_no_frame(sweep6):
    sweep = read_tracked_sweep(sweep6)
    assembler = FrameAssembler("ImageToReference", wait_s=0.5)
    image, ijk, t, pose = _messages(sweep, 0)
    assert assembler.add_image(image, ijk, t, 10.0) == ([], [])  # its pose may still come
    assert assembler.expire(10.2) == ([], [])
    frames, notes = assembler.expire(10.6)
    assert frames == [] and len(notes) == 1 and "\n" not in notes[0]
    assert "without a ImageToReference pose" in notes[0] and assembler.without_pose == 1
    # a later pose tells at once that an earlier image has none
    image1, _, t1, pose1 = _messages(sweep, 1)
    assembler.add_image(image, ijk, t1 - 0.5, 11.0)
    frames, notes = assembler.add_pose("ImageToReference", pose1, t1, 11.0)
    assert frames == [] and len(notes) == 1
    frames, notes = assembler.add_image(image1, ijk, t1, 11.0)
    assert [f.index for f in frames] == [2] and notes == []


def _through_pyigtl(image: np.ndarray) -> np.ndarray:
    """``image`` as a live client gets it: packed into an IMAGE message and unpacked again."""
    import pyigtl

    packed = pyigtl.ImageMessage(image, device_name="Image", timestamp=1.0).pack()
    received = pyigtl.ImageMessage()
    received.unpack(pyigtl.MessageBase.parse_header(packed[:58]), packed[58:])
    return received.image


def test_a_frame_of_one_slice_is_used_and_a_volume_of_several_is_a_note(sweep6):
    """PLUS sends a B-mode frame as one slice (grey, or colour channels last); an IMAGE of
    several slices is no frame, not a colour image."""
    sweep = read_tracked_sweep(sweep6)
    grey, ijk, t, pose = _messages(sweep, 0)
    colour = np.repeat(grey[None, :, :, None], 3, axis=-1)  # (1, H, W, 3), equal channels
    for image, used in ((grey[None], True), (colour, True), (np.stack([grey] * 4), False),
                        (np.repeat(colour, 2, axis=0), False)):
        assembler = FrameAssembler("ImageToReference")
        received = _through_pyigtl(image)
        assert received.shape == image.shape
        frames, notes = assembler.add_image(received, ijk, t, 0.0)
        if used:
            frames += assembler.add_pose("ImageToReference", pose, t, 0.0)[0]
            assert len(frames) == 1 and np.array_equal(frames[0].image, grey)
        else:
            assert frames == [] and len(notes) == 1, notes
            assert f"an image of shape {received.shape} is no 2D B-mode frame" in notes[0]
            told = [assembler.add_image(received, ijk, t, 0.0)[1] for _ in range(199)]
            assert [k + 2 for k, n in enumerate(told) if n] == [2, 3, 100, 200]  # not all


def test_an_unusable_pose_is_a_note(sweep6):
    sweep = read_tracked_sweep(sweep6)
    image, ijk, t, pose = _messages(sweep, 0)
    assembler = FrameAssembler("ImageToReference")
    sheared = pose.copy()
    sheared[:3, 1] += 0.5 * sheared[:3, 0]
    assembler.add_image(image, ijk, t, 0.0)
    frames, notes = assembler.add_pose("ImageToReference", sheared, t, 0.0)
    assert frames == [] and len(notes) == 1 and "right angles" in notes[0]
    frames, notes = assembler.add_pose("ImageToReference", np.full((4, 4), np.nan), t, 0.0)
    assert frames == [] and "not a finite" in notes[0]


def test_a_probe_pose_with_the_calibration_gives_the_image_pose(sweep6):
    """ProbeToReference from tracking.csv (scipy's 'xyz' Euler angles, read here) with
    calibration.json: the frames' poses are the frame folder reader's."""
    sweep = read_tracked_sweep(sweep6)
    T_probe_pixel = probe_calibration(sweep6 / "calibration.json")
    with open(sweep6 / "tracking.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assembler = FrameAssembler("ProbeToReference", T_probe_pixel)
    for i, row in enumerate(rows):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", [float(row[k]) for k in
                                                ("euler_x", "euler_y", "euler_z")],
                                        degrees=True).as_matrix()
        T[:3, 3] = [float(row[k]) for k in "xyz"]
        assembler.add_image(sweep.frames[i], np.diag([9.0, 9.0, 9.0, 1.0]), i, 0.0)
        (frame,), _ = assembler.add_pose("ProbeToReference", T, i, 0.0)
        assert_close(frame.T_ref_image, sweep.T_ref_image[i], atol=1e-9)
        assert_close(frame.spacing, sweep.spacing, atol=1e-12)


def test_the_points_are_extract_us_points_whatever_the_order(sweep6):
    """Frames added out of order give exactly ``extract-us``'s cloud of the sweep."""
    from comreg_core.surfaces.us import extract_us_surface

    sweep = read_tracked_sweep(sweep6)
    expected = extract_us_surface(sweep).points
    points = SweepPoints()
    for i in (3, 0, 5, 1, 4, 2):
        points.add(Frame(i, sweep.frames[i], sweep.spacing, sweep.T_ref_image[i],
                         float(sweep.timestamps[i]), 0.0))
    cloud = points.cloud()
    assert points.frames_used == 6 and cloud.points.shape == expected.points.shape
    assert_close(cloud.points, expected.points, atol=1e-9)
    assert np.array_equal(cloud.frame_index, expected.frame_index)
    from comreg_core.surfaces.us_points import beam_origins

    assert_close(points.beam_origins(cloud),
                 beam_origins(expected.points, sweep.T_ref_image[expected.frame_index]),
                 atol=1e-9)
