"""The live registration loop's state: each update takes the frames that arrived, adds their bone
points and registers the grown sweep (:class:`LiveSession`); ``updates.csv`` records it
(:class:`UpdatesLog`).

**Warm or full.** An update registers *warm* (:func:`warm_register`: the registrar's warm
start, which refines the last result's chosen pose and its best distinct competitors on the
grown cloud), unless the evidence changed, when it runs the *full* search (as ``comreg
register`` does): the first registration; the bone covered along the CT's long axis grew by
:attr:`LiveSession.full_every_mm` since the last full search (unless the last update was a full
search: the frames that came while it ran are registered warm first, so a slow full search,
during which more than ``full_every_mm`` of bone arrives, is not followed by another at once);
the warm pose moved beyond
:data:`WARM_TOLERANCE` from the last update's (it switched to another of its poses); or its
verdict differs from the last update's (then the full search decides it, in the same update).
So the verdict only ever turns OK, or back to CHECK, on a full search.

**Verdict.** Every update is judged as ``comreg register`` judges a result
(:func:`~comreg_core.registration.verdict.judge_registration`: residuals, refit, coverage, on
at most :data:`VERDICT_POINTS` of the points) with the result's own evidence: the margin of its
best clinically different pose (and, with a calibration, ``p_correct`` at the sweep's extent)
or its confidence. A warm result's evidence covers the competitors it carried over from the
last full search; new ones are found by the next full search. The US calibration's scale is
checked (the refit's scale scan, ~0.07 s) on full searches only. An OK verdict must also have
*settled* (:data:`SETTLED_TOLERANCE`): the pose agrees with the last full search made on at
least ``full_every_mm`` less bone, else the update says CHECK; a partial sweep's pose can slide
along the shaft by a few millimetres while every other test passes, and the first OK needs two
full searches. On a sweep spanning under half the CT, an OK verdict also needs its two halves
to agree (:func:`~comreg_core.registration.polish.halves_disagreement_deg` within
:data:`HALVES_TOLERANCE_DEG`, measured by the full search, kept by the warm updates after it):
a shaft pins its rotation about its own axis only weakly.

**Prior.** What the operating room knows (a rough initial pose, landmarks touched with a tracked
pointer: :class:`~comreg_core.registration.priors.Prior`) bounds every registration, full or
warm, as it bounds ``comreg register``'s, and its reasons (a result at its edge, a clearly
better pose outside it) make the update CHECK. On a long bone's shaft it is what rules out the
bone reversed end to end before the sweep reaches an end.

**Advice.** ``"enough"`` when the verdict is OK, else which end of the bone to scan towards
(:func:`scan_advice`).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.registration.advice import end_names
from comreg_core.registration.calibration import (OK_PROBABILITY, TOLERANCE_DEG, Calibration,
                                                  clinical_competitor, extent_share)
from comreg_core.registration.metrics import rotation_error_deg, translation_error_mm
from comreg_core.registration.polish import halves_disagreement_deg
from comreg_core.registration.priors import Prior, prior_allows
from comreg_core.registration.surface import ct_length_mm
from comreg_core.registration.verdict import judge_registration, with_prior_reasons
from comreg_core.live.stream import Frame, SweepPoints, coalesce, covered_length_mm
from comreg_core.transforms import apply_transform, space_change

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
#: An end of the bone counts as reached when the points come this close to it (mm).
END_REACHED_MM = 15.0
#: ``updates.csv``'s columns.
UPDATE_COLUMNS = ("time_s", "frames_received", "frames_used", "covered_mm", "verdict",
                  "p_correct", "latency_s", "centroid_x", "centroid_y", "centroid_z",
                  *(f"T_ct_us_{r}{c}" for r in range(3) for c in range(4)))


def warm_register(registrar, points: np.ndarray, origins: np.ndarray | None, last,
                  seed: int = 0, prior: Prior | None = None):
    """The warm start of a live update: register ``points`` ``(N, 3)`` (beam ``origins``
    ``(N, 3)`` or None) again from ``last``, the previous
    :class:`~comreg_core.registration.result.RegistrationResult` of the same sweep before it
    grew (:meth:`Registrar.register <comreg_core.inference.Registrar.register>`'s
    ``warm_start``: its poses refined, no full search, no network pass), within ``prior`` when
    given. The one place to change how a live update registers warm."""
    return registrar.register(points, seed=seed, beam_origins=origins, warm_start=last,
                              prior=prior, residuals=False)


@dataclass
class LiveUpdate:
    """One update: what was registered and judged, and what to tell the user.

    Attributes:
        time_s: since the session started (s). frames_received, frames_used: so far.
        n_points: bone points registered. covered_mm: bone covered along the CT's long axis.
        verdict: "ok"/"check"; reasons: why CHECK. p_correct: None without a calibration.
        confidence: the registration's (the pose search's). advice: "enough" or where to scan.
        T_ct_us: ``(4, 4)`` tracker reference -> CT (the CT's space, mm).
        centroid: ``(3,)`` of the points (tracker frame, mm).
        mode: "full", "warm" or "warm+full" (a warm result the full search replaced).
        register_s: the update's time (s): detection, registration, verdict.
        waiting: frames left in the backlog for later updates (the loop is lagging).
        newest_s: arrival (``time.monotonic()``) of the newest frame registered; latency_s:
            from it to the update being sent (set by whoever sends it).
    """

    time_s: float
    frames_received: int
    frames_used: int
    n_points: int
    covered_mm: float
    verdict: str
    reasons: list[str]
    p_correct: float | None
    confidence: float | None
    advice: str
    T_ct_us: np.ndarray
    centroid: np.ndarray
    mode: str
    register_s: float
    waiting: int
    newest_s: float
    latency_s: float = float("nan")

    def csv_row(self) -> list:
        """The ``updates.csv`` row (:data:`UPDATE_COLUMNS`)."""
        p = "" if self.p_correct is None else f"{self.p_correct:.4f}"
        return [f"{self.time_s:.3f}", self.frames_received, self.frames_used,
                f"{self.covered_mm:.1f}", self.verdict, p, f"{self.latency_s:.3f}",
                *(f"{v:.4f}" for v in self.centroid),
                *(repr(float(v)) for v in self.T_ct_us[:3].reshape(-1))]

    def status_line(self) -> str:
        """One line for the terminal."""
        p = "n/a" if self.p_correct is None else f"{self.p_correct:.2f}"
        lag = f"; LAGGING: {self.waiting} frames waiting" if self.waiting else ""
        late = f"; LATE by {self.latency_s:.1f} s" if self.latency_s > 1.0 else ""
        return (f"[{self.time_s:7.1f} s] frames {self.frames_used}/{self.frames_received}, "
                f"{self.n_points} points, {self.covered_mm:.0f} mm covered | {self.mode} "
                f"{self.register_s:.2f} s, latency {self.latency_s:.2f} s | "
                f"{self.verdict.upper()} p_correct {p} | {self.advice}{lag}{late}")

    def message_text(self) -> str:
        """The STRING sent back: JSON with ``verdict``, ``p_correct``, ``covered_mm``,
        ``advice``, ``frames_used``, ``frames_received``, ``reasons``."""
        return json.dumps({"verdict": self.verdict, "p_correct": self.p_correct,
                           "covered_mm": round(self.covered_mm, 1), "advice": self.advice,
                           "frames_used": self.frames_used,
                           "frames_received": self.frames_received, "reasons": self.reasons})


@dataclass
class _Evidence:
    """What a registration said about the clinically different poses."""

    margin: float
    confidence: float | None
    ambiguous: bool


class LiveSession:
    """The live registration of a growing sweep against one CT (module docstring).

    Args:
        registrar: a :class:`~comreg_core.inference.Registrar` (the search alone or with a
            network), its CT mesh known (the verdict needs it).
        calibration: the verdict's :class:`~comreg_core.registration.calibration.Calibration`
            or None (then it judges by the full search's confidence).
        prior: what the operating room knows (a rough initial pose, landmarks picked with a
            tracked pointer: :class:`~comreg_core.registration.priors.Prior`, any space) or
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
    """

    def __init__(self, registrar, *, calibration: Calibration | None = None,
                 prior: Prior | None = None, extraction=None, seed: int = 0,
                 max_frames_per_update: int = 16, max_backlog: int = 300,
                 full_every_mm: float = 20.0, live_points: int = LIVE_POINTS, clock=None):
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
        self.target = registrar.hypothesis_target(registrar.hypothesis_config.target_points)
        self.ct_length = (calibration.ct_length_mm if calibration is not None
                          else ct_length_mm(self.target))
        self._evidence: _Evidence | None = None
        self._result = None  # the last RegistrationResult (the warm start of the next)
        self._covered_at_full = -math.inf
        self._fulls: list[tuple[float, np.ndarray]] = []  # (covered mm, T_ct_us) of each
        self._halves_deg: float | None = None  # the last full search's, when it measured it
        self.last: LiveUpdate | None = None

    def warm_up(self) -> None:
        """Prepare the CT side once (search cloud, closest-point grid, verdict samples, the
        network's CT half) by registering a patch of the CT's own surface, so the first live
        update costs what later ones do."""
        samples, _ = self.registrar.surface.samples(2000)
        along = (samples - self.target.centre) @ self.target.axes[:, 0]
        patch = samples[np.abs(along - np.median(along)) < 0.25 * self.ct_length]
        result = self.registrar.register(patch, seed=self.seed)
        self._judge(patch, result, _Evidence(1.0, None, False))

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
            newest_s=max(record.received_s for record in self.points.records))
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
        if self.last is None or self._result is None or (
                covered >= self._covered_at_full + self.full_every_mm
                and self.last.mode == "warm"):
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

    @staticmethod
    def _moved(T: np.ndarray, T_last: np.ndarray, centroid: np.ndarray) -> bool:
        """Whether ``T`` is beyond :data:`WARM_TOLERANCE` from ``T_last``."""
        deg, mm = WARM_TOLERANCE
        return rotation_error_deg(T, T_last) > deg or \
            translation_error_mm(T, T_last, centroid) > mm

    def _evidence_of(self, result, pts: np.ndarray) -> _Evidence:
        margin = 1.0
        if result.hypotheses is not None:
            allowed = None if self.prior is None else prior_allows(self.prior, result)
            margin = clinical_competitor(result.hypotheses, pts, allowed)["margin"]
        self._evidence = _Evidence(float(margin), result.confidence, bool(result.ambiguous))
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

    def _consistent(self, verdict, pts: np.ndarray, result=None, origins=None):
        """``verdict``, turned CHECK when it is OK for a sweep spanning under half the CT whose
        halves fit best more than :data:`HALVES_TOLERANCE_DEG` apart. A full search's
        ``result`` (with its beam ``origins``) has them measured; a warm update keeps the
        last full search's measure (none: not checked)."""
        if not verdict.ok or extent_share(pts, self.ct_length) >= 0.5:
            return verdict
        if result is not None:
            self._halves_deg = halves_disagreement_deg(
                pts, result.T_ct_us, self.target, self.registrar.hypothesis_config,
                origins=origins)
        halves_deg = self._halves_deg
        if halves_deg is None or halves_deg <= HALVES_TOLERANCE_DEG:
            return verdict
        why = (f"The two halves of the sweep fit best turned {halves_deg:.1f} deg apart: the "
               f"bone seen so far does not pin the pose's rotation to {HALVES_TOLERANCE_DEG:g} "
               "deg yet.")
        return replace(verdict, verdict="check", reasons=[*verdict.reasons, why])

    def _judge(self, pts: np.ndarray, result, evidence: _Evidence, scale_scan: bool = True):
        """The verdict of ``result`` (its ``T_ct_us``, and where it lies in the prior) for
        ``pts`` with the registration's ``evidence``; without
        ``scale_scan`` (a warm update) no scale check: the US calibration's scale is checked
        by the full searches (a scale problem found there makes the warm verdicts differ, so
        each update runs the full search again and stays CHECK)."""
        extent = extent_share(pts, self.ct_length)
        p_correct = None
        if self.calibration is not None:
            p_correct = self.calibration.p_correct(evidence.margin, extent)
        if len(pts) > VERDICT_POINTS:
            pts = pts[np.sort(np.random.default_rng(self.seed).choice(
                len(pts), VERDICT_POINTS, replace=False))]
        ok_probability = OK_PROBABILITY if self.calibration is None \
            else self.calibration.ok_probability
        verdict = judge_registration(pts, result.T_ct_us, self.registrar.surface,
                                     confidence=evidence.confidence,
                                     ambiguous=evidence.ambiguous, p_correct=p_correct,
                                     short_sweep=extent < 0.5, ok_probability=ok_probability,
                                     scale_scan=scale_scan)
        return with_prior_reasons(verdict, result.info.get("prior"))


def scan_advice(points_ct: np.ndarray, target, space: str = "LPS") -> str:
    """Where to scan next: towards the end of the bone the registered points ``(N, 3)`` (CT
    frame, mm) lie nearer to, along the CT's long axis (``target``: its
    :class:`~comreg_core.registration.surface.SurfaceCloud`, centre and axes), or towards the
    other end when they already reach that one (within :data:`END_REACHED_MM`). The ends are
    named as anatomy names a limb's: the superior end proximal, the inferior end distal (other
    axes by their direction, e.g. "the left end")."""
    axis = target.axes[:, 0]
    along_ct = (target.points - target.centre) @ axis
    lo, hi = float(along_ct.min()), float(along_ct.max())
    along = (points_ct - target.centre) @ axis
    a, b = float(np.percentile(along, 5)), float(np.percentile(along, 95))
    plus, minus = end_names(space_change(space, "LPS")[:3, :3] @ axis)
    towards_plus = 0.5 * (a + b) > 0.5 * (lo + hi)
    if towards_plus and hi - b < END_REACHED_MM:
        towards_plus = False
    elif not towards_plus and a - lo < END_REACHED_MM:
        towards_plus = True
    name = plus if towards_plus else minus
    limb = {"superior": "proximal", "inferior": "distal"}
    return f"scan towards the {limb.get(name, name)} end" + (
        f" ({name})" if name in limb else "")


class UpdatesLog:
    """``updates.csv``: the header, then one row per update (:data:`UPDATE_COLUMNS`), each
    flushed as it is written, so the file is complete up to the last update at any moment."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        self._writer.writerow(UPDATE_COLUMNS)
        self._file.flush()

    def write(self, update: LiveUpdate) -> None:
        self._writer.writerow(update.csv_row())
        self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()


def read_updates(path: str | Path) -> list[dict]:
    """The rows of an ``updates.csv`` as dicts of floats (``verdict`` a string, an empty
    ``p_correct`` None)."""
    rows = []
    with open(path, newline="", encoding="utf-8") as f:
        for row in csv.DictReader(f):
            rows.append({k: (v if k == "verdict" else (None if v == "" else float(v)))
                         for k, v in row.items()})
    return rows


def row_transform(row: dict) -> np.ndarray:
    """``T_ct_us`` ``(4, 4)`` of an ``updates.csv`` row (:func:`read_updates`)."""
    T = np.eye(4)
    T[:3] = np.array([row[f"T_ct_us_{r}{c}"] for r in range(3) for c in range(4)]).reshape(3, 4)
    return T
