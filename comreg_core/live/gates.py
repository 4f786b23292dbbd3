"""The live session's verdict: the one judge's (:func:`~comreg_core.register.judge.judge`) on at
most :data:`VERDICT_POINTS` points, with the session's own checks on top: an OK pose must have
*settled* (:func:`settled`), a short sweep's two halves must agree (:func:`halves_agree`); and a
warm pose that moved far calls for the full search (:func:`moved_beyond`). The functions are
pure; :class:`VerdictChecks` applies them with the state of a
:class:`~comreg_core.live.session.LiveSession`."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from comreg_core.register.judge import Evidence, is_short_sweep, judge
from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
from comreg_core.registration.geometry.extent import extent_share
from comreg_core.registration.judgement.calibration import TOLERANCE_DEG
from comreg_core.registration.judgement.prior_reasons import prior_allows
from comreg_core.registration.search.polish import halves_disagreement_deg

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
#: Points the verdict of an update is computed on at most.
VERDICT_POINTS = 1000


def moved_beyond(T: np.ndarray, T_last: np.ndarray, centroid: np.ndarray,
                 tolerance: tuple[float, float] = WARM_TOLERANCE) -> bool:
    """Whether the pose ``T`` is beyond ``tolerance`` (deg, mm at ``centroid`` ``(3,)``) from
    ``T_last`` (both ``(4, 4)``)."""
    deg, mm = tolerance
    return rotation_error_deg(T, T_last) > deg or translation_error_mm(T, T_last, centroid) > mm


def unsettled_reason(T_ct_us: np.ndarray, centroid: np.ndarray, earlier: np.ndarray | None,
                     full_every_mm: float) -> str | None:
    """Why the pose ``T_ct_us`` has not settled (None: it has): it is beyond
    :data:`SETTLED_TOLERANCE` (at ``centroid``) from ``earlier``, the pose of the last full search
    made on at least ``full_every_mm`` less bone, or there is none yet (None)."""
    if earlier is None:
        return "No registration of less bone to confirm this pose yet."
    deg, mm = SETTLED_TOLERANCE
    turned = rotation_error_deg(T_ct_us, earlier)
    moved = translation_error_mm(T_ct_us, earlier, centroid)
    if turned <= deg and moved <= mm:
        return None
    return (f"The pose moved {moved:.1f} mm / {turned:.1f} deg since the registration "
            f"of {full_every_mm:g} mm less bone: it has not settled yet.")


def settled(verdict, T_ct_us: np.ndarray, centroid: np.ndarray, earlier: np.ndarray | None,
            full_every_mm: float):
    """``verdict``, turned CHECK when it is OK but the pose ``T_ct_us`` has not settled
    (:func:`unsettled_reason`)."""
    if not verdict.ok:
        return verdict
    why = unsettled_reason(T_ct_us, centroid, earlier, full_every_mm)
    if why is None:
        return verdict
    return replace(verdict, verdict="check", reasons=[*verdict.reasons, why])


def halves_agree(verdict, halves_deg: float | None):
    """``verdict``, turned CHECK when it is OK and the sweep's two halves fit best
    ``halves_deg`` apart, more than :data:`HALVES_TOLERANCE_DEG` (None: not measured)."""
    if not verdict.ok or halves_deg is None or halves_deg <= HALVES_TOLERANCE_DEG:
        return verdict
    why = (f"The two halves of the sweep fit best turned {halves_deg:.1f} deg apart: the "
           f"bone seen so far does not pin the pose's rotation to {HALVES_TOLERANCE_DEG:g} "
           "deg yet.")
    return replace(verdict, verdict="check", reasons=[*verdict.reasons, why])


class VerdictChecks:
    """The verdict of a live update, for :class:`~comreg_core.live.session.LiveSession` (whose
    state it reads: ``prior``, ``ct_length``, ``calibration``, ``seed``, ``registrar``,
    ``target``, ``full_every_mm``, the full searches' poses ``_fulls`` and the last halves'
    measure ``_halves_deg``)."""

    def _evidence_of(self, result, pts: np.ndarray) -> Evidence:
        """The evidence of ``result`` for ``pts`` (:meth:`Evidence.of`; the competitor among the
        poses the prior allows), kept for the update's record."""
        allowed = None if self.prior is None else prior_allows(self.prior, result)
        self._evidence = Evidence.of(result, pts, self.ct_length, self.calibration, allowed)
        return self._evidence

    def _earlier_full(self, covered: float) -> np.ndarray | None:
        """The pose of the last full search made on at least ``full_every_mm`` less than
        ``covered`` mm of bone (None: none yet)."""
        earlier = [T for mm, T in self._fulls if mm <= covered - self.full_every_mm]
        return earlier[-1] if earlier else None

    def _settled(self, verdict, T_ct_us: np.ndarray, pts: np.ndarray, covered: float):
        """``verdict``, turned CHECK when it is OK but the pose has not settled
        (:func:`~comreg_core.live.gates.settled`: against the last full search made on at
        least ``full_every_mm`` less than ``covered`` mm of bone)."""
        return settled(verdict, T_ct_us, pts.mean(axis=0), self._earlier_full(covered),
                       self.full_every_mm)

    def _can_settle(self, T_ct_us: np.ndarray, pts: np.ndarray, covered: float) -> bool:
        """Whether the pose has settled (:meth:`_settled` would keep an OK): a full search's
        verdict that cannot be OK needs neither the scale check nor the profiles."""
        return unsettled_reason(T_ct_us, pts.mean(axis=0), self._earlier_full(covered),
                                self.full_every_mm) is None

    def _short(self, pts: np.ndarray) -> bool:
        """Whether the sweep ``pts`` is short (:func:`is_short_sweep`: for the verdict and the
        halves check)."""
        return is_short_sweep(extent_share(pts, self.ct_length))

    def _consistent(self, verdict, pts: np.ndarray, result=None, origins=None):
        """``verdict``, turned CHECK when it is OK for a sweep spanning under half the CT whose
        halves fit best too far apart (:func:`halves_agree`). A full search's
        ``result`` (with its beam ``origins``) has them measured; a warm update keeps the
        last full search's measure (none: not checked)."""
        if not verdict.ok or not self._short(pts):
            return verdict
        if result is not None:
            self._halves_deg = halves_disagreement_deg(
                pts, result.T_ct_us, self.target, self.registrar.search_config,
                origins=origins)
        return halves_agree(verdict, self._halves_deg)

    def _judge(self, pts: np.ndarray, result, evidence: Evidence, full: bool = True):
        """The verdict of ``result`` for ``pts`` by the one judge (:func:`judge`) on at most
        :data:`VERDICT_POINTS` of them. A warm update (``full=False``) has no scale check and
        no profiles of the weakest directions: both are the full searches' (a scale problem
        or another basin found there makes the warm verdicts differ, so each update runs the
        full search again and stays CHECK; a warm OK only keeps an OK a full judgement gave,
        see :mod:`.session`); so is a full search's whose pose has not settled
        (:meth:`_can_settle`): it is CHECK whatever they find."""
        if len(pts) > VERDICT_POINTS:
            pts = pts[np.sort(np.random.default_rng(self.seed).choice(
                len(pts), VERDICT_POINTS, replace=False))]
        return judge(pts, result.T_ct_us, self.registrar.surface, evidence,
                     scale_scan=full, profiles=full)
