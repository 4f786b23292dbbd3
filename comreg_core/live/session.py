"""The live registration loop's state: each update takes the frames that arrived, adds their bone
points and registers the grown sweep (:class:`LiveSession`; docs/live.md for the whole story).

- **Warm or full.** An update refines the last result's poses on the grown cloud
  (:func:`warm_register`) unless the evidence changed: the first registration, the bone covered
  along the CT grew by :attr:`LiveSession.full_every_mm` since the last full search (not right
  after one), the warm pose moved beyond
  :data:`~comreg_core.live.gates.WARM_TOLERANCE`, or its verdict changed; then
  the full search runs, in the update or in a
  :class:`~comreg_core.live.background.FullSearchWorker`'s process (mode "warm+full" when its
  answer is used). The verdict only turns OK, or back to CHECK, on a full search.
- **Verdict.** The one judge (:func:`~comreg_core.register.judge.judge`) on at most
  :data:`~comreg_core.live.gates.VERDICT_POINTS` points with the result's own evidence; the scale scan and the profiles
  of the weakest directions run on full searches only, and only when the pose has settled (a
  warm update, or a verdict that is CHECK whatever they find, costs less). An OK must also have *settled*
  (:data:`~comreg_core.live.gates.SETTLED_TOLERANCE` from the full
  search on ``full_every_mm`` less bone) and, on a short sweep, its two halves must agree
  (:func:`~comreg_core.registration.search.polish.halves_disagreement_deg` within
  :data:`~comreg_core.live.gates.HALVES_TOLERANCE_DEG`).
- **Frames.** Those that can show new bone and are not too old
  (:class:`~comreg_core.live.intake.FrameGate`) are detected here or, by ``comreg live``, in
  worker processes (:mod:`comreg_core.live.pipeline`); the points are cleaned up incrementally
  (:class:`~comreg_core.live.points.SweepPoints`).
- **Prior.** An initial pose or landmarks
  (:class:`~comreg_core.registration.search.priors.Prior`) bound every registration, and their
  reasons make the update CHECK.
- **Advice.** ``"enough"`` when OK, else which end of the bone to scan towards
  (:func:`~comreg_core.registration.search.advice.scan_advice`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.registration.search.advice import scan_advice
from comreg_core.register.judge import Evidence
from comreg_core.registration.judgement.calibration import Calibration
from comreg_core.registration.search.priors import Prior
from comreg_core.registration.geometry.surface import ct_length_mm
from comreg_core.live.background import (FullSearchDone, FullSearchJob, FullSearchWorker,
                                         warm_up_registrar)
from comreg_core.live.gates import VerdictChecks, moved_beyond
from comreg_core.live.intake import Backlog, FrameGate, FrameSpacing
from comreg_core.live.points import Detection, SweepPoints, covered_length_mm, detect_frame
from comreg_core.live.stream import Frame
from comreg_core.live.updates import LiveUpdate
from comreg_core.transforms import apply_transform

log = logging.getLogger(__name__)

#: Points registered per update at most (a seeded uniform subset of the sweep's).
LIVE_POINTS = 4000
#: Frames with bone needed before the first registration.
MIN_FRAMES_WITH_BONE = 3


def warm_register(registrar, points: np.ndarray, origins: np.ndarray | None, last,
                  seed: int = 0, prior: Prior | None = None):
    """The warm start of a live update: register ``points`` ``(N, 3)`` (beam ``origins``
    ``(N, 3)`` or None) again from ``last``, the previous
    :class:`~comreg_core.registration.search.result.RegistrationResult` of the same sweep before it
    grew (:meth:`Registrar.register <comreg_core.register.Registrar.register>`'s
    ``warm_start``: its poses refined, no full search, no network pass), within ``prior`` when
    given. The one place to change how a live update registers warm."""
    return registrar.register(points, seed=seed, beam_origins=origins, warm_start=last,
                              prior=prior, residuals=False)


class LiveSession(VerdictChecks):
    """The live registration of a growing sweep against one CT (module docstring).

    Args:
        registrar: a :class:`~comreg_core.register.Registrar` (the search alone or with a
            network), its CT mesh known (the verdict needs it).
        calibration: the verdict's :class:`~comreg_core.registration.judgement.calibration.Calibration`
            or None (then it judges by the full search's confidence).
        prior: what the operating room knows (a rough initial pose, landmarks picked with a
            tracked pointer: :class:`~comreg_core.registration.search.priors.Prior`, any space) or
            None. Every registration, full or warm, keeps to the poses it allows; the verdict
            looks for the competitor among them and is CHECK when the result sits at its edge
            or a pose outside it fits clearly better (as ``comreg register --init``).
        extraction: the bone detector's and clean-up's settings (``extract-us``'s defaults).
        seed: of the registrations and the subsets.
        spacing: the :class:`~comreg_core.live.intake.FrameSpacing` of the frames used (a
            frame closer to the last one is skipped before detection: no new bone); None:
            every frame.
        max_frame_age_s: the age limit of a frame when used (s; older ones are dropped for
            lag); None: frames wait (:attr:`gate` applies both).
        max_frames_per_update: frames given to :meth:`update` (detected in the update) that
            an update detects at most (evenly spread over those waiting, the newest always
            among them); the rest wait in :attr:`backlog` for the next updates (and
            :meth:`drain`). Frames detected elsewhere (``detections``) are all taken.
        max_backlog: frames waiting at most; beyond, the oldest is dropped (and counted).
        full_every_mm: run the full search when the covered bone grew by this (mm).
        live_points: points registered per update at most.
        clock: the time source (s), ``time.monotonic`` by default.
        worker: a :class:`~comreg_core.live.background.FullSearchWorker` of the same registrar
            and prior, to run the full searches in the background (None: in the update).

    Attributes:
        first_search_beside: with a worker, the first full search runs in it too (no update
            until its answer came, with new frames; ``comreg live``), instead of in the first
            update (the default).
    """

    def __init__(self, registrar, *, calibration: Calibration | None = None,
                 prior: Prior | None = None, extraction=None, seed: int = 0,
                 spacing: FrameSpacing | None = FrameSpacing(),
                 max_frame_age_s: float | None = None,
                 max_frames_per_update: int = 16, max_backlog: int = 300,
                 full_every_mm: float = 20.0, live_points: int = LIVE_POINTS, clock=None,
                 worker: FullSearchWorker | None = None):
        if registrar.surface is None:
            raise ComRegError("Live registration needs the CT mesh (its verdict is judged on "
                              "it).", "Give the CT bone mesh (--ct CT_MESH).")
        self.registrar = registrar
        self.calibration = calibration
        self.prior = None if prior is None else prior.in_space(registrar.space)
        self.points = SweepPoints(extraction)
        self.gate = FrameGate(spacing, max_frame_age_s)
        self.seed = int(seed)
        self.max_frames_per_update = int(max_frames_per_update)
        self.backlog = Backlog(max_backlog)
        self._notes: list[str] = []
        self.full_every_mm = float(full_every_mm)
        self.live_points = int(live_points)
        self.clock = clock or time.monotonic
        self.started_s = self.clock()
        self.frames_received = 0
        self.updates: list[LiveUpdate] = []
        self.target = registrar.search_target(registrar.search_config.target_points)
        self.ct_length = (calibration.ct_length_mm if calibration is not None
                          else ct_length_mm(self.target))
        self._evidence: Evidence | None = None
        self._result = None  # the last RegistrationResult (the warm start of the next)
        self._covered_at_full = -math.inf
        self._fulls: list[tuple[float, np.ndarray]] = []  # (covered mm, T_ct_us) of each
        self._halves_deg: float | None = None  # the last full search's, when it measured it
        self.worker = worker
        self.first_search_beside = False
        self._job: tuple[int, float] | None = None  # (id, covered mm) of the worker's job
        self._jobs = 0
        self._done: FullSearchDone | None = None  # the worker's answer, not yet used
        self._answer_s = math.nan  # when the last answer was read
        self.last: LiveUpdate | None = None

    def warm_up(self) -> None:
        """Prepare the CT side once (search cloud, closest-point grid, verdict samples, the
        network's CT half) by registering a patch of the CT's own surface, so the first live
        update costs what later ones do."""
        patch, result = warm_up_registrar(self.registrar, self.seed)
        self._judge(patch, result, Evidence())

    # -- one update ----------------------------------------------------------------------------

    def update(self, frames: list[Frame] = (), received: int | None = None,
               detections: list[Detection] = ()) -> LiveUpdate | None:
        """Add the frames that arrived since the last update (in order; those that can show
        new bone are detected here, at most ``max_frames_per_update``, the rest wait in
        :attr:`backlog`) and the ``detections`` of frames detected elsewhere, and register;
        None while there is too little bone to register or nothing new. ``received``: images
        received so far by the stream (default: counted here)."""
        start = self.clock()
        counts = dict(self.gate.counts)
        self.frames_received = received if received is not None \
            else self.frames_received + len(frames)
        found = list(detections) + [detect_frame(f, self.points.config)
                                    for f in self._frames_to_detect(frames, start)]
        if not found and not self.answer_waiting():
            return None
        for detection in found:
            self.points.add_detection(detection, used_s=start)
            self.gate.used(detection, start)
        cloud = self.points.cloud()
        if cloud is None or self.points.frames_with_bone < MIN_FRAMES_WITH_BONE \
                or len(cloud.points) < 6:
            return None
        origins = self.points.beam_origins(cloud)
        pts, org = self._subset(cloud.points, origins)
        try:
            registered = self._register(pts, org, cloud.points)
        except ComRegError as exc:  # e.g. too few distinct points yet
            log.info("live update not registered: %s", exc)
            return None
        if registered is None:
            return None
        result, verdict, mode = registered
        covered = self.covered_mm(cloud.points, result.T_ct_us)
        advice = "enough" if verdict.ok else (verdict.scan_next or {}).get("words") or \
            scan_advice(apply_transform(result.T_ct_us, cloud.points), self.target,
                        self.registrar.space)
        uncertainty = verdict.uncertainty or {}
        update = LiveUpdate(
            time_s=start - self.started_s, frames_received=self.frames_received,
            frames_used=self.points.frames_used, n_points=len(cloud.points),
            covered_mm=covered, verdict=verdict.verdict, reasons=list(verdict.reasons),
            p_correct=verdict.figures.get("p_correct"), confidence=self._evidence.confidence,
            advice=advice, T_ct_us=np.array(result.T_ct_us), centroid=cloud.points.mean(axis=0),
            mode=mode, register_s=self.clock() - start, waiting=len(self.backlog),
            newest_s=(max(record.received_s for record in self.points.records) if found
                      else self._answer_s),
            searching=self.searching,
            frame_age_s=max((start - d.received_s for d in found), default=math.nan),
            skipped=counts["skipped"], dropped_lag=counts["lag"],
            bound_mm=uncertainty.get("bound_mm"),
            weakest=uncertainty.get("summary", "").partition("weakest: ")[2])
        self.gate.timed(update_s=update.register_s)
        self.last = update
        self.updates.append(update)
        return update

    def _frames_to_detect(self, frames: list[Frame], now: float) -> list[Frame]:
        """Of ``frames`` (new, in order) and the :attr:`backlog`: those the update detects
        (:meth:`update`); the gate skips or drops the others."""
        self._notes += self.backlog.add(f for f in frames if self.gate.admit(f, now))
        return self.backlog.take(self.max_frames_per_update)

    @property
    def dropped(self) -> int:
        """Frames dropped from a full :attr:`backlog`."""
        return self.backlog.dropped

    def take_notes(self) -> list[str]:
        """One-line notes since the last call (frames dropped from a full backlog)."""
        notes, self._notes = self._notes, []
        return notes

    def drain(self, frames: list[Frame] = (), detections: list[Detection] = ()) -> int:
        """Before the final registration, so that it uses every frame that came: keep the
        ``detections`` not taken yet, and detect the bone in the :attr:`backlog` and in
        ``frames`` (not decided yet; those with no new bone are skipped, none for its age).
        No registration. Returns how many frames were added."""
        max_age, self.gate.max_age_s = self.gate.max_age_s, None
        waiting = self.backlog.take() + [f for f in frames if self.gate.admit(f, self.clock())]
        self.gate.max_age_s = max_age
        found = list(detections) + [detect_frame(f, self.points.config) for f in waiting]
        for detection in found:
            self.points.add_detection(detection)
            self.gate.used(detection, math.nan)
        return len(found)

    def covered_mm(self, points: np.ndarray, T_ct_us: np.ndarray | None) -> float:
        """Bone covered by ``points`` (tracker frame) along the CT's long axis when placed by
        ``T_ct_us``; along their own longest axis without a pose."""
        if T_ct_us is None:
            centred = points - points.mean(axis=0)
            axis = np.linalg.svd(centred, full_matrices=False)[2][0]
            return covered_length_mm(centred @ axis)
        moved = apply_transform(T_ct_us, points)
        return covered_length_mm((moved - self.target.centre) @ self.target.axes[:, 0])

    def _subset(self, points: np.ndarray, origins: np.ndarray | None):
        if len(points) <= self.live_points:
            return points, origins
        keep = np.sort(np.random.default_rng(self.seed).choice(len(points), self.live_points,
                                                               replace=False))
        return points[keep], None if origins is None else origins[keep]

    def _register(self, pts: np.ndarray, origins: np.ndarray | None, everything: np.ndarray):
        """``(result, verdict, mode)`` by the policy of the module docstring: ``pts`` and
        ``origins`` are registered, ``everything`` (all points) measures the coverage. None
        while the worker runs the first full search."""
        covered = self.covered_mm(everything, None if self.last is None else self.last.T_ct_us)
        beside = self._worker_ready() and (self._result is not None or self.first_search_beside)
        if beside:
            if self._result is None and not self._first_answer(pts, origins, covered):
                return None  # the first full search runs in the worker
            return self._register_beside(pts, origins, covered)
        if self.last is None or self._result is None:
            return (*self._full(pts, origins, everything), "full")
        if covered >= self._covered_at_full + self.full_every_mm and self.last.mode == "warm":
            return (*self._full(pts, origins, everything), "full")
        result = warm_register(self.registrar, pts, origins, self._result, self.seed, self.prior)
        verdict = self._settled(self._judge(pts, result, self._evidence_of(result, pts),
                                            full=False), result.T_ct_us, pts, covered)
        verdict = self._consistent(verdict, pts)
        if self._moved(result.T_ct_us, self.last.T_ct_us, pts.mean(axis=0)) \
                or verdict.verdict != self.last.verdict:
            return (*self._full(pts, origins, everything), "warm+full")
        self._result = result
        return result, verdict, "warm"

    def _worker_ready(self) -> bool:
        """Whether the full searches go to the worker (it is ready); a worker that failed is
        let go, with a note (the full searches run in the update from then on)."""
        if self.worker is None:
            return False
        done = self.worker.poll()
        if done is not None:
            self._done, self._answer_s = done, self.clock()
        if self.worker.failed is not None:
            self._notes.append(f"{self.worker.failed}; full searches run in the update loop "
                               "from now")
            self.worker, self._job = None, None
            return False
        return self.worker.ready

    def _first_answer(self, pts: np.ndarray, origins: np.ndarray | None, covered: float) -> bool:
        """Whether the worker's answer to the first full search has come; else it is asked
        for (again, after a failure) with ``pts``."""
        done = self._done
        if done is not None and self._job is not None and done.job == self._job[0]:
            if done.error is None:
                return True
            self._notes.append(f"a background full search failed: {done.error}")
            self._done, self._job = None, None
        if self._job is None:
            self._jobs += 1
            self.worker.submit(FullSearchJob(self._jobs, pts, origins, self.seed,
                                             self._short(pts)))
            self._job, self._covered_at_full = (self._jobs, covered), covered
        return False

    @property
    def searching(self) -> bool:
        """Whether the worker runs a full search (its answer comes with a later update)."""
        return self._job is not None

    def answer_waiting(self) -> bool:
        """Whether the worker's answer to a full search waits to be used (an update without new
        frames uses it: a probe held still, the end of the stream)."""
        return self.worker is not None and self._job is not None and (
            self._done is not None or self.worker.wait(0.0))

    def _register_beside(self, pts: np.ndarray, origins: np.ndarray | None, covered: float):
        """``(result, verdict, mode)`` with the full search in the worker (module docstring);
        ``covered``: the bone covered now (mm)."""
        base, mode, done, self._done = self._result, "warm", self._done, None
        if done is not None and self._job is not None and done.job == self._job[0]:
            job_covered, self._job = self._job[1], None
            if done.error is not None:
                self._notes.append(f"a background full search failed: {done.error}")
            else:
                base, mode, self._halves_deg = done.result, "warm+full", done.halves_deg
        result = warm_register(self.registrar, pts, origins, base, self.seed, self.prior)
        verdict = self._judge(pts, result, self._evidence_of(result, pts),
                              full=mode == "warm+full" and self._can_settle(
                                  result.T_ct_us, pts, job_covered))
        if mode == "warm+full":  # judged as that full search; its own pose is recorded
            verdict = self._settled(verdict, result.T_ct_us, pts, job_covered)
            self._fulls.append((job_covered, np.array(done.result.T_ct_us)))
        else:
            verdict = self._settled(verdict, result.T_ct_us, pts, covered)
        verdict = self._consistent(verdict, pts)
        moved = self.last is not None and \
            self._moved(result.T_ct_us, self.last.T_ct_us, pts.mean(axis=0))
        asks = covered >= self._covered_at_full + self.full_every_mm or (
            mode == "warm" and (moved or verdict.verdict != self.last.verdict))
        if asks and self._job is None:
            self._jobs += 1
            self.worker.submit(FullSearchJob(self._jobs, pts, origins, self.seed,
                                             self._short(pts)))
            self._job, self._covered_at_full = (self._jobs, covered), covered
        if mode == "warm" and verdict.ok and (moved or self.last.verdict != "ok"):
            verdict = replace(verdict, verdict="check", reasons=[
                *verdict.reasons, "A full search is confirming this pose (its answer comes "
                "with a later update)."])
        self._result = result
        return result, verdict, mode

    @staticmethod
    def _moved(T: np.ndarray, T_last: np.ndarray, centroid: np.ndarray) -> bool:
        """Whether ``T`` is beyond the warm tolerance from ``T_last`` (:func:`moved_beyond`)."""
        return moved_beyond(T, T_last, centroid)

    def _full(self, pts: np.ndarray, origins: np.ndarray | None, everything: np.ndarray):
        result = self.registrar.register(pts, seed=self.seed, beam_origins=origins,
                                         prior=self.prior, residuals=False)  # verdict: own
        self._result = result
        self._covered_at_full = self.covered_mm(everything, result.T_ct_us)
        full = self._can_settle(result.T_ct_us, pts, self._covered_at_full)
        verdict = self._settled(self._judge(pts, result, self._evidence_of(result, pts),
                                            full=full),
                                result.T_ct_us, pts, self._covered_at_full)
        self._halves_deg = None
        verdict = self._consistent(verdict, pts, result, origins)
        self._fulls.append((self._covered_at_full, np.array(result.T_ct_us)))
        return result, verdict
