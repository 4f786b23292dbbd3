"""Which frames a live session uses (comreg_core.live.intake): the no-new-bone rule against
known poses (a naive corner-by-corner reference), the skip and lag decisions of the gate in
stream order with their counts and record, and the frames a session detects itself."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comreg_core.errors import ComRegError
from comreg_core.live.intake import (LAG, SKIPPED, USED, Backlog, FrameGate, FrameSpacing,
                                     image_corners)
from comreg_core.live.stream import Frame

#: An image of 100 x 80 pixels of 0.5 mm: 49.5 mm wide, 39.5 mm deep.
SPACING = np.array([0.5, 0.5])


def _pose(rotvec_deg=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = t
    return T


def _frame(index, T, received_s=0.0) -> Frame:
    return Frame(index, np.zeros((80, 100), np.uint8), SPACING, T, float(index), received_s)


def _naive_motion(T_a, T_b, W=49.5, H=39.5):
    """The largest distance a corner moves, corner by corner, and the angle turned (deg)."""
    worst = 0.0
    for x, y in ((0, 0), (W, 0), (0, H), (W, H)):
        p = np.array([x, y, 0.0, 1.0])
        worst = max(worst, float(np.linalg.norm((T_b @ p - T_a @ p)[:3])))
    R = T_a[:3, :3].T @ T_b[:3, :3]
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2))))
    return worst, angle


def test_the_motion_of_a_frame_is_the_farthest_corners_and_its_turn():
    corners = image_corners(_frame(0, np.eye(4)))
    assert np.array_equal(corners[3], [49.5, 39.5, 0.0])
    spacing = FrameSpacing()
    # a pure shift: every corner moves by it, no turn
    mm, deg = spacing.moved(_pose(), _pose(t=(0.3, -0.4, 0.0)), corners)
    assert mm == pytest.approx(0.5, abs=1e-12) and deg == pytest.approx(0.0, abs=1e-9)
    # a turn in the image plane about its first corner: the far corner moves 2 r sin(a / 2)
    mm, deg = spacing.moved(_pose(), _pose((0.0, 0.0, 1.0)), corners)
    r = math.hypot(49.5, 39.5)
    assert mm == pytest.approx(2 * r * math.sin(math.radians(0.5)), rel=1e-9)
    assert deg == pytest.approx(1.0, abs=1e-9)
    rng = np.random.default_rng(5)
    for _ in range(50):  # anywhere, against the naive reference
        T_a = _pose(rng.uniform(-180, 180, 3), rng.uniform(-500, 500, 3))
        T_b = T_a @ _pose(rng.normal(scale=0.5, size=3), rng.normal(scale=0.5, size=3))
        mm, deg = spacing.moved(T_a, T_b, corners)
        naive_mm, naive_deg = _naive_motion(T_a, T_b)
        assert mm == pytest.approx(naive_mm, rel=1e-9, abs=1e-9)
        assert deg == pytest.approx(naive_deg, abs=1e-5)


def test_new_bone_needs_the_distance_or_the_angle():
    corners = image_corners(_frame(0, np.eye(4)))
    spacing = FrameSpacing(0.5, 0.5)
    assert not spacing.new_bone(_pose(), _pose(t=(0.0, 0.0, 0.49)), corners)
    assert spacing.new_bone(_pose(), _pose(t=(0.0, 0.0, 0.5)), corners)
    # a turn about the image's centre line (its y axis through x = 24.75 mm), 0.6 deg: the
    # corners move 0.26 mm only, but the frame turned past the angle
    centre = _pose(t=(24.75, 0.0, 0.0))
    turned = centre @ _pose((0.0, 0.6, 0.0)) @ np.linalg.inv(centre)
    mm, deg = spacing.moved(_pose(), turned, corners)
    assert mm < 0.5 and deg == pytest.approx(0.6)
    assert spacing.new_bone(_pose(), turned, corners)
    assert not FrameSpacing(0.5, 1.0).new_bone(_pose(), turned, corners)
    assert FrameSpacing(0.0, 0.0).new_bone(_pose(), _pose(), corners)  # every frame
    with pytest.raises(ComRegError, match="not two non-negative numbers"):
        FrameSpacing(-1.0, 0.5)


def test_the_gate_skips_frames_without_new_bone_in_stream_order():
    gate = FrameGate(FrameSpacing(0.5, 0.5))
    shifts = [0.0, 0.2, 0.4, 0.6, 0.7, 1.3, 1.3]
    admitted = [gate.admit(_frame(k, _pose(t=(0.0, 0.0, z))), 0.0) for k, z in enumerate(shifts)]
    # each against the last frame admitted: 0 -> 0.6 (0.6 mm) -> 1.3 (0.7 mm)
    assert admitted == [True, False, False, True, False, True, False]
    assert gate.counts == {SKIPPED: 4, LAG: 0}
    assert [(f.index, f.fate) for f in gate.fates] == [(1, SKIPPED), (2, SKIPPED), (4, SKIPPED),
                                                       (6, SKIPPED)]
    assert np.array_equal(gate.fates[0].T_ref_image, _pose(t=(0.0, 0.0, 0.2)))  # kept
    gate.used(_frame(0, _pose()), 3.0)
    assert gate.fates[-1].fate == USED and gate.fates[-1].at_s == 3.0
    assert all(FrameGate(None).admit(_frame(k, _pose()), 0.0) for k in range(3))


def test_the_gate_drops_frames_that_waited_too_long():
    gate = FrameGate(FrameSpacing(), max_age_s=0.5)
    assert not gate.admit(_frame(0, _pose(), received_s=10.0), 10.6)  # waited 0.6 s
    assert gate.counts[LAG] == 1 and gate.fates[-1].fate == LAG
    # a frame dropped is no reference for the next: this one, 0.1 mm from it, is new bone
    assert gate.admit(_frame(1, _pose(t=(0.1, 0, 0)), received_s=10.2), 10.6)
    # what detection and an update still take counts: 0.05 + 0.15 s
    gate.timed(detect_s=0.05)
    gate.timed(update_s=0.15)
    assert not gate.admit(_frame(2, _pose(t=(5.0, 0, 0)), received_s=10.0), 10.35)
    assert gate.admit(_frame(3, _pose(t=(10.0, 0, 0)), received_s=10.0), 10.25)
    # ... but at most half the limit: slow updates must not drop every frame
    gate.timed(update_s=3.0)
    assert gate.admit(_frame(4, _pose(t=(15.0, 0, 0)), received_s=10.0), 10.25)
    assert not gate.admit(_frame(5, _pose(t=(20.0, 0, 0)), received_s=10.0), 10.26)
    assert gate.counts == {SKIPPED: 0, LAG: 3}
    with pytest.raises(ComRegError, match="not a positive number"):
        FrameGate(max_age_s=0.0)


def test_the_backlog_spreads_what_it_gives_and_drops_beyond_its_bound():
    backlog = Backlog(max_frames=8)
    frames = [_frame(k, _pose()) for k in range(10)]
    notes = backlog.add(frames)
    assert notes == ["LAGGING: 2 frames waited too long and were dropped (frames 0-1; 2 so far)"]
    assert backlog.dropped == 2 and len(backlog) == 8
    assert [f.index for f in backlog.take(3)] == [2, 6, 9]  # spread, the newest in
    assert [f.index for f in backlog.take()] == [3, 4, 5, 7, 8] and not backlog


def test_a_session_skips_a_frame_sent_again(shared_data, search_registrar):
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.live.session import LiveSession
    from tests.helpers import FIBULA_DIR

    sweep = read_tracked_sweep(FIBULA_DIR)
    frames = [Frame(k, sweep.frames[i], sweep.spacing, sweep.T_ref_image[i], float(k), 0.0)
              for k, i in enumerate([40, 41, 42, 43, 43])]
    session = LiveSession(search_registrar)
    session.update(frames[:4])
    assert session.update(frames[4:]) is None  # the same pose again: nothing new to register
    assert session.gate.counts[SKIPPED] == 1 and session.points.frames_used == 4
