"""The live registration loop's state: each update takes the frames that arrived, adds their bone
points and registers the grown sweep (:class:`LiveSession`; docs/live.md for the whole story).

- **Warm or full.** An update refines the last result's poses on the grown cloud
  (:func:`warm_register`) unless the evidence changed: the first registration, the bone covered
  along the CT grew by :attr:`LiveSession.full_every_mm` since the last full search (not right
  after one), the warm pose moved beyond :data:`WARM_TOLERANCE`, or its verdict changed; then
  the full search runs, in the update or in a
  :class:`~comreg_core.live.background.FullSearchWorker`'s process (mode "warm+full" when its
  answer is used). The verdict only turns OK, or back to CHECK, on a full search.
- **Verdict.** The one judge (:func:`~comreg_core.register.judge.judge`) on at most
  :data:`VERDICT_POINTS` points with the result's own evidence; the scale is checked on full
  searches only. An OK must also have *settled* (:data:`SETTLED_TOLERANCE` from the full
  search on ``full_every_mm`` less bone) and, on a short sweep, its two halves must agree
  (:func:`~comreg_core.registration.search.polish.halves_disagreement_deg` within
  :data:`HALVES_TOLERANCE_DEG`).
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
from comreg_core.register.judge import Evidence, is_short_sweep, judge
from comreg_core.registration.geometry.extent import extent_share
from comreg_core.registration.judgement.calibration import TOLERANCE_DEG, Calibration
from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
from comreg_core.registration.search.polish import halves_disagreement_deg
from comreg_core.registration.judgement.prior_reasons import prior_allows
from comreg_core.registration.search.priors import Prior
from comreg_core.registration.geometry.surface import ct_length_mm
from comreg_core.live.background import (FullSearchDone, FullSearchJob, FullSearchWorker,
                                         warm_up_registrar)
from comreg_core.live.stream import Frame, SweepPoints, coalesce, covered_length_mm
from comreg_core.live.updates import LiveUpdate
from comreg_core.transforms import apply_transform

log = logging.getLogger(__name__)

#: A warm pose that moved more than this from the last update's, (deg, mm at the points'
#: centroid), calls for the full search.
WARM_TOLERANCE = (5.0, 5.0)
#: An OK verdict needs the pose to agree, within this (deg, mm at the points' centroid), with
#: the last full search made on at least ``full_every_mm`` less bone: a pose still moving as
#: bone is added has not settled.
SETTLED_TOLERANCE = (2.0, 2.0)
#: An OK verdict on a sweep spanning under half the CT needs its two halves (along the bone) to
#: fit best at rotations at most this far apart (deg): the tolerance of a correct pose.
HALVES_TOLERANCE_DEG = TOLERANCE_DEG
#: Points registered per update at most (a seeded uniform subset of the sweep's).
LIVE_POINTS = 4000
#: Points the verdict of an update is computed on at most.
VERDICT_POINTS = 1000
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


class LiveSession:
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
        max_frames_per_update: frames an update detects at most (evenly spread over those
            waiting, the newest always among them); the rest wait in :attr:`backlog` for the
            next updates (and :meth:`drain`), so lagging delays frames but loses none.
        max_backlog: frames waiting at most; beyond, the oldest is dropped (and counted).
        full_every_mm: run the full search when the covered bone grew by this (mm).
        live_points: points registered per update at most.
        clock: the time source (s), ``time.monotonic`` by default.
        worker: a :class:`~comreg_core.live.background.FullSearchWorker` of the same registrar
            and prior, to run the full searches in the background (None: in the update).
    """

    def __init__(self, registrar, *, calibration: Calibration | None = None,
                 prior: Prior | None = None, extraction=None, seed: int = 0,
                 max_frames_per_update: int = 16, max_backlog: int = 300,
                 full_every_mm: float = 20.0, live_points: int = LIVE_POINTS, clock=None,
                 worker: FullSearchWorker | None = None):
        if registrar.surface is None:
            raise ComRegError("Live registration needs the CT mesh (its verdict is judged on "
                              "it).", "Give the CT bone mesh (--ct CT_MESH).")
        self.registrar = registrar
        self.calibration = calibration
        self.prior = None if prior is None else prior.in_space(registrar.space)
        self.points = SweepPoints(extraction) if extraction is not None else SweepPoints()
        self.seed = int(seed)
        self.max_frames_per_update = int(max_frames_per_update)
        self.max_backlog = int(max_backlog)
        self.backlog: list[Frame] = []
        self.dropped = 0
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
        self._job: tuple[int, float] | None = None  # (id, covered mm) of the worker's job
        self._jobs = 0
        self._done: FullSearchDone | None = None  # the worker's answer, not yet used
        self.last: LiveUpdate | None = None

    def warm_up(self) -> None:
        """Prepare the CT side once (search cloud, closest-point grid, verdict samples, the
        network's CT half) by registering a patch of the CT's own surface, so the first live
        update costs what later ones do."""
        patch, result = warm_up_registrar(self.registrar, self.seed)
        self._judge(patch, result, Evidence())

    # -- one update ----------------------------------------------------------------------------

    def update(self, frames: list[Frame], received: int | None = None) -> LiveUpdate | None:
        """Add ``frames`` (those that arrived since the last update, in order; none to catch
        up on the :attr:`backlog`) and register; None while there is too little bone to
        register or nothing new. ``received``: images received so far by the stream (default:
        counted here)."""
        start = self.clock()
        self.frames_received = received if received is not None \
            else self.frames_received + len(frames)
        self.backlog.extend(frames)
        if len(self.backlog) > self.max_backlog:
            excess = len(self.backlog) - self.max_backlog
            self.dropped += excess
            self._notes.append(f"LAGGING: {excess} frames waited too long and were dropped "
                               f"(frames {self.backlog[0].index}-{self.backlog[excess - 1].index}"
                               f"; {self.dropped} so far)")
            del self.backlog[:excess]
        use = coalesce(self.backlog, self.max_frames_per_update)
        if not use:
            return None
        chosen = {id(frame) for frame in use}
        self.backlog = [frame for frame in self.backlog if id(frame) not in chosen]
        for frame in use:
            self.points.add(frame)
        cloud = self.points.cloud()
        if cloud is None or self.points.frames_with_bone < MIN_FRAMES_WITH_BONE \
                or len(cloud.points) < 6:
            return None
        origins = self.points.beam_origins(cloud)
        pts, org = self._subset(cloud.points, origins)
        try:
            result, verdict, mode = self._register(pts, org, cloud.points)
        except ComRegError as exc:  # e.g. too few distinct points yet
            log.info("live update not registered: %s", exc)
            return None
        covered = self.covered_mm(cloud.points, result.T_ct_us)
        advice = "enough" if verdict.ok else scan_advice(
            apply_transform(result.T_ct_us, cloud.points), self.target, self.registrar.space)
        update = LiveUpdate(
            time_s=start - self.started_s, frames_received=self.frames_received,
            frames_used=self.points.frames_used, n_points=len(cloud.points),
            covered_mm=covered, verdict=verdict.verdict, reasons=list(verdict.reasons),
            p_correct=verdict.figures.get("p_correct"), confidence=self._evidence.confidence,
            advice=advice, T_ct_us=np.array(result.T_ct_us), centroid=cloud.points.mean(axis=0),
            mode=mode, register_s=self.clock() - start, waiting=len(self.backlog),
            newest_s=max(record.received_s for record in self.points.records),
            searching=self._job is not None)
        self.last = update
        self.updates.append(update)
        return update

    def take_notes(self) -> list[str]:
        """One-line notes since the last call (frames dropped from a full backlog)."""
        notes, self._notes = self._notes, []
        return notes

    def drain(self) -> int:
        """Detect the bone in every frame still in the backlog (no registration): before the
        final registration, so that it uses every frame received. Returns how many."""
        frames, self.backlog = self.backlog, []
        for frame in frames:
            self.points.add(frame)
        return len(frames)

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
        ``origins`` are registered, ``everything`` (all points) measures the coverage."""
        covered = self.covered_mm(everything, None if self.last is None else self.last.T_ct_us)
        if self.last is None or self._result is None:
            return (*self._full(pts, origins, everything), "full")
        if self._worker_ready():
            return self._register_beside(pts, origins, covered)
        if covered >= self._covered_at_full + self.full_every_mm and self.last.mode == "warm":
            return (*self._full(pts, origins, everything), "full")
        result = warm_register(self.registrar, pts, origins, self._result, self.seed, self.prior)
        verdict = self._settled(self._judge(pts, result, self._evidence_of(result, pts),
                                            scale_scan=False), result.T_ct_us, pts, covered)
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
            self._done = done
        if self.worker.failed is not None:
            self._notes.append(f"{self.worker.failed}; full searches run in the update loop "
                               "from now")
            self.worker, self._job = None, None
            return False
        return self.worker.ready

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
                              scale_scan=mode == "warm+full")
        if mode == "warm+full":  # judged as that full search; its own pose is recorded
            verdict = self._settled(verdict, result.T_ct_us, pts, job_covered)
            self._fulls.append((job_covered, np.array(done.result.T_ct_us)))
        else:
            verdict = self._settled(verdict, result.T_ct_us, pts, covered)
        verdict = self._consistent(verdict, pts)
        moved = self._moved(result.T_ct_us, self.last.T_ct_us, pts.mean(axis=0))
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
        """Whether ``T`` is beyond :data:`WARM_TOLERANCE` from ``T_last``."""
        deg, mm = WARM_TOLERANCE
        return rotation_error_deg(T, T_last) > deg or \
            translation_error_mm(T, T_last, centroid) > mm

    def _evidence_of(self, result, pts: np.ndarray) -> Evidence:
        """The evidence of ``result`` for ``pts`` (:meth:`Evidence.of`; the competitor among the
        poses the prior allows), kept for the update's record."""
        allowed = None if self.prior is None else prior_allows(self.prior, result)
        self._evidence = Evidence.of(result, pts, self.ct_length, self.calibration, allowed)
        return self._evidence

    def _full(self, pts: np.ndarray, origins: np.ndarray | None, everything: np.ndarray):
        result = self.registrar.register(pts, seed=self.seed, beam_origins=origins,
                                         prior=self.prior, residuals=False)  # verdict: own
        self._result = result
        self._covered_at_full = self.covered_mm(everything, result.T_ct_us)
        verdict = self._settled(self._judge(pts, result, self._evidence_of(result, pts)),
                                result.T_ct_us, pts, self._covered_at_full)
        self._halves_deg = None
        verdict = self._consistent(verdict, pts, result, origins)
        self._fulls.append((self._covered_at_full, np.array(result.T_ct_us)))
        return result, verdict

    def _settled(self, verdict, T_ct_us: np.ndarray, pts: np.ndarray, covered: float):
        """``verdict``, turned CHECK when it is OK but the pose has not settled: it is beyond
        :data:`SETTLED_TOLERANCE` from the last full search made on at least
        ``full_every_mm`` less bone (or there is none yet)."""
        if not verdict.ok:
            return verdict
        earlier = [T for mm, T in self._fulls if mm <= covered - self.full_every_mm]
        if earlier:
            deg, mm = SETTLED_TOLERANCE
            turned = rotation_error_deg(T_ct_us, earlier[-1])
            moved = translation_error_mm(T_ct_us, earlier[-1], pts.mean(axis=0))
            if turned <= deg and moved <= mm:
                return verdict
            why = (f"The pose moved {moved:.1f} mm / {turned:.1f} deg since the registration "
                   f"of {self.full_every_mm:g} mm less bone: it has not settled yet.")
        else:
            why = "No registration of less bone to confirm this pose yet."
        return replace(verdict, verdict="check", reasons=[*verdict.reasons, why])

    def _short(self, pts: np.ndarray) -> bool:
        """Whether the sweep ``pts`` is short (:func:`is_short_sweep`: for the verdict and the
        halves check)."""
        return is_short_sweep(extent_share(pts, self.ct_length))

    def _consistent(self, verdict, pts: np.ndarray, result=None, origins=None):
        """``verdict``, turned CHECK when it is OK for a sweep spanning under half the CT whose
        halves fit best more than :data:`HALVES_TOLERANCE_DEG` apart. A full search's
        ``result`` (with its beam ``origins``) has them measured; a warm update keeps the
        last full search's measure (none: not checked)."""
        if not verdict.ok or not self._short(pts):
            return verdict
        if result is not None:
            self._halves_deg = halves_disagreement_deg(
                pts, result.T_ct_us, self.target, self.registrar.search_config,
                origins=origins)
        halves_deg = self._halves_deg
        if halves_deg is None or halves_deg <= HALVES_TOLERANCE_DEG:
            return verdict
        why = (f"The two halves of the sweep fit best turned {halves_deg:.1f} deg apart: the "
               f"bone seen so far does not pin the pose's rotation to {HALVES_TOLERANCE_DEG:g} "
               "deg yet.")
        return replace(verdict, verdict="check", reasons=[*verdict.reasons, why])

    def _judge(self, pts: np.ndarray, result, evidence: Evidence, scale_scan: bool = True):
        """The verdict of ``result`` for ``pts`` by the one judge (:func:`judge`) on at most
        :data:`VERDICT_POINTS` of them; without ``scale_scan`` (a warm update) no scale check:
        the US calibration's scale is checked by the full searches (a scale problem found
        there makes the warm verdicts differ, so each update runs the full search again and
        stays CHECK)."""
        if len(pts) > VERDICT_POINTS:
            pts = pts[np.sort(np.random.default_rng(self.seed).choice(
                len(pts), VERDICT_POINTS, replace=False))]
        return judge(pts, result.T_ct_us, self.registrar.surface, evidence,
                     scale_scan=scale_scan)
