"""The live session's update policy (comreg_core.live.session) on frames of the real sweep fed
directly: the full search first and when the covered bone grows, warm in between; a backlog
that delays frames but drops them only beyond its bound, and says so; updates.csv written and
read back; the advice's end of the bone."""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.live.session import LiveSession
from comreg_core.registration.search.advice import scan_advice
from comreg_core.live.updates import UPDATE_COLUMNS, UpdatesLog, read_updates, row_transform
from comreg_core.live.stream import Frame
from tests.helpers import assert_close
from tests.live.conftest import cut_sweep


@pytest.fixture(scope="module")
def sweep(shared_data, tmp_path_factory):
    return read_tracked_sweep(cut_sweep(tmp_path_factory.mktemp("sweep_s"), 30, 22))


def _frames(sweep, indices, first_index=None):
    return [Frame(i if first_index is None else first_index + k, sweep.frames[i], sweep.spacing,
                  sweep.T_ref_image[i], float(sweep.timestamps[i]), 0.0)
            for k, i in enumerate(indices)]


def test_full_first_then_warm_then_full_when_the_bone_covered_grows(sweep, search_registrar,
                                                                    tmp_path):
    session = LiveSession(search_registrar, spacing=None)  # a frame sent again is used again
    first = session.update(_frames(sweep, range(6)))
    assert first.mode == "full" and first.frames_used == 6 and first.frames_received == 6
    # the same frame again: no new bone covered, so warm from the last pose
    again = session.update(_frames(sweep, [5], first_index=6))
    assert again.mode == "warm" and again.covered_mm == pytest.approx(first.covered_mm, abs=1.0)
    centroid = again.centroid
    moved = np.linalg.norm(again.T_ct_us[:3, :3] @ centroid + again.T_ct_us[:3, 3]
                           - first.T_ct_us[:3, :3] @ centroid - first.T_ct_us[:3, 3])
    assert moved < 5.0  # within the warm tolerance
    grown = session.update(_frames(sweep, range(6, 14), first_index=7))
    assert grown.covered_mm >= first.covered_mm + session.full_every_mm
    assert grown.mode == "full" and grown.frames_used == 15
    # grown again by full_every_mm right after a full search: warm first, then full
    sooner = session.update(_frames(sweep, range(14, 20), first_index=15))
    assert sooner.covered_mm >= grown.covered_mm + session.full_every_mm
    assert sooner.mode == "warm"
    later = session.update(_frames(sweep, [19], first_index=21))
    assert later.mode in ("full", "warm+full") and later.frames_used == 22

    log = UpdatesLog(tmp_path / "updates.csv")
    for update in (first, again, grown):
        update.latency_s = 0.25
        log.write(update)
    log.close()
    rows = read_updates(tmp_path / "updates.csv")
    assert tuple(rows[0]) == UPDATE_COLUMNS and len(rows) == 3
    for row, update in zip(rows, (first, again, grown)):
        assert_close(row_transform(row), update.T_ct_us, atol=1e-12)
        assert row["verdict"] == update.verdict and row["frames_used"] == update.frames_used
        assert_close([row["centroid_x"], row["centroid_y"], row["centroid_z"]], update.centroid,
                     atol=1e-4)
        assert row["latency_s"] == 0.25 and 0.0 <= row["p_correct"] <= 1.0
        assert row["bound_mm"] == pytest.approx(update.bound_mm, abs=0.005) and row["bound_mm"] > 0
        assert row["mode"] == update.mode and row["reasons"] == " | ".join(update.reasons)
    assert [row["mode"] for row in rows] == ["full", "warm", "full"]
    assert all(row["reasons"] for row in rows if row["verdict"] == "check")
    assert f"{grown.mode} " in grown.status_line() and grown.advice in grown.status_line()


def test_the_backlog_delays_frames_and_drops_only_beyond_its_bound(sweep, search_registrar):
    session = LiveSession(search_registrar, max_frames_per_update=3, max_backlog=8)
    update = session.update(_frames(sweep, range(10)))
    assert session.take_notes() == ["LAGGING: 2 frames waited too long and were dropped "
                                    "(frames 0-1; 2 so far)"]
    assert session.dropped == 2 and session.points.frames_used == 3
    assert update.waiting == 5 and "LAGGING: 5 frames waiting" in update.status_line()
    assert [r.index for r in session.points.records] == [2, 6, 9]  # spread, the newest in
    update = session.update([])  # catching up while no frame comes
    assert session.points.frames_used == 6 and update.waiting == 2
    assert session.drain() == 2 and not session.backlog
    assert sorted(r.index for r in session.points.records) == list(range(2, 10))
    assert session.take_notes() == []


def test_the_advice_points_to_the_nearer_end_until_it_is_reached(search_registrar):
    session = LiveSession(search_registrar)
    target = session.target
    axis, centre = target.axes[:, 0], target.centre
    along = (target.points - centre) @ axis
    lo, hi = along.min(), along.max()
    plus = "proximal end (superior)" if axis[2] > 0 else "distal end (inferior)"
    minus = "distal end (inferior)" if axis[2] > 0 else "proximal end (superior)"

    def at(a, b):
        return centre + np.linspace(a, b, 200)[:, None] * axis

    assert scan_advice(at(hi - 120, hi - 60), target) == f"scan towards the {plus}"
    assert scan_advice(at(lo + 60, lo + 120), target) == f"scan towards the {minus}"
    assert scan_advice(at(hi - 100, hi - 5), target) == f"scan towards the {minus}"
    assert scan_advice(at(lo + 5, lo + 100), target) == f"scan towards the {plus}"


def test_an_ok_verdict_waits_until_the_pose_has_settled(search_registrar):
    """OK stands only when the pose agrees (2 mm / 2 deg at the points' centroid) with the full
    search made on at least ``full_every_mm`` less bone; otherwise CHECK, with the reason."""
    from comreg_core.registration.judgement.verdict import Verdict

    session = LiveSession(search_registrar)
    pts = np.random.default_rng(0).normal(scale=10.0, size=(200, 3)) + [0.0, 0.0, 50.0]
    earlier = _pose(np.eye(3), [1.0, 2.0, 3.0])
    session._fulls = [(100.0, earlier)]
    ok = Verdict("ok", [], {"median_mm": 0.5})

    def shifted(mm, deg=0.0):
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        return _pose([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], [1.0 + mm, 2.0, 3.0])

    assert session._settled(ok, shifted(1.5), pts, covered=120.0).ok
    moved = session._settled(ok, shifted(2.5), pts, covered=120.0)
    assert moved.verdict == "check" and "moved 2.5 mm / 0.0 deg" in moved.reasons[-1]
    assert moved.figures == ok.figures and ok.reasons == []  # the original is left alone
    # a 3 deg turn about x (through the origin) moves the centroid (~50 mm away) by ~2.6 mm as well
    assert session._settled(ok, shifted(0.0, 3.0), pts, covered=120.0).verdict == "check"
    # the only full search was on less than full_every_mm less bone: nothing to confirm it yet
    early = session._settled(ok, earlier, pts, covered=110.0)
    assert early.verdict == "check" and "No registration of less bone" in early.reasons[-1]
    check = Verdict("check", ["residuals"], {})
    assert session._settled(check, earlier, pts, covered=120.0) is check


def _pose(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_warm_updates_leave_the_profiles_and_the_scale_scan_to_the_settled_full_searches(
        sweep, search_registrar, monkeypatch):
    """The one judge runs with its profiles and scale scan on a full search's pose that has
    settled (it agrees with the full search on ``full_every_mm`` less bone, so it may be OK),
    and without them on a warm update's (a warm OK only keeps an OK that a full judgement gave)
    and on a first full search's (nothing to settle against: CHECK whatever they find)."""
    import comreg_core.live.gates as gates
    from comreg_core.registration.geometry.metrics import (rotation_error_deg,
                                                           translation_error_mm)

    calls = []
    judge = gates.judge

    def spy(*args, **kwargs):
        calls.append((kwargs["profiles"], kwargs["scale_scan"]))
        return judge(*args, **kwargs)

    def three_updates(session, before_the_third=lambda: None):
        updates = [session.update(_frames(sweep, range(6))),
                   session.update(_frames(sweep, [5], first_index=6))]
        before_the_third()
        return updates + [session.update(_frames(sweep, range(6, 14), first_index=7))]

    monkeypatch.setattr(gates, "judge", spy)
    # the first full search (6 frames) and the second (15 frames) disagree: not settled
    first, again, grown = three_updates(LiveSession(search_registrar, spacing=None))
    assert [u.mode for u in (first, again, grown)] == ["full", "warm", "full"]
    assert rotation_error_deg(grown.T_ct_us, first.T_ct_us) > 2.0
    assert calls == [(False, False)] * 3
    calls.clear()
    session = LiveSession(search_registrar, spacing=None)

    def settle():  # as if the first full search had found the second's pose
        session._fulls = [(mm, grown.T_ct_us) for mm, _ in session._fulls]

    first, again, later = three_updates(session, settle)
    assert first.mode == "full" and first.verdict == "check" and calls[0] == (False, False)
    assert again.mode == "warm" and calls[1] == (False, False)
    assert later.mode == "full" and later.covered_mm >= first.covered_mm + session.full_every_mm
    assert rotation_error_deg(later.T_ct_us, grown.T_ct_us) < 1e-6  # the same search
    assert translation_error_mm(later.T_ct_us, grown.T_ct_us, later.centroid) < 1e-6
    assert calls[2:] == [(True, True)]
