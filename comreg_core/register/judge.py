"""The one judge of a registration: from its evidence to the verdict, its reasons and figures.

Every caller gets its verdict here: ``comreg register`` (:mod:`comreg_core.register.folder`),
``comreg live`` (each update), the report (from ``result.json``) and batch (through
``comreg register``); the 3D Slicer module does not judge yet (issue 50). :class:`Evidence` is what a registration says about itself: the pose search's
confidence and ambiguity, the clinically different competitor's margin, the sweep's extent
along the CT, ``p_correct`` from a per-patient calibration, and the prior's record;
:func:`judge` turns it, with the US points, the pose and the CT, into a
:class:`~comreg_core.registration.judgement.verdict.Verdict`
(:func:`~comreg_core.registration.judgement.verdict.judge_registration`: residuals, coverage, refit,
then the prior's reasons).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from comreg_core.registration.judgement.calibration import (OK_PROBABILITY, Calibration,
                                                            result_evidence)
from comreg_core.registration.judgement.verdict import (Verdict, judge_registration,
                                                        with_prior_reasons)

#: A sweep spanning less than this share of the CT's length (5th-95th percentile along its
#: long axis, :func:`~comreg_core.registration.judgement.calibration.extent_share`) is a *short sweep*:
#: its best-fitting scale says nothing, and live checks that its two halves agree.
SHORT_SWEEP_SHARE = 0.5


def is_short_sweep(extent_share: float | None) -> bool:
    """Whether a sweep of this extent share (None: unknown) is short."""
    return extent_share is not None and extent_share < SHORT_SWEEP_SHARE


@dataclass(frozen=True)
class Evidence:
    """What a registration says about its pose.

    Attributes:
        confidence, ambiguous: the pose search's (None / False without it).
        competitor: the clinically different competitor
            (:func:`~comreg_core.registration.judgement.calibration.clinical_competitor`), or None.
        extent_share: the sweep's extent over the CT's length (0-1), or None.
        p_correct: the calibrated probability that the pose is within 4 mm / 5 deg, or None
            without a calibration.
        ok_probability: the least ``p_correct`` that is OK (the calibration's).
        prior: the prior's record (:func:`~comreg_core.registration.judgement.prior_reasons.prior_record`) or
            None.
    """

    confidence: float | None = None
    ambiguous: bool = False
    competitor: dict[str, Any] | None = None
    extent_share: float | None = None
    p_correct: float | None = None
    ok_probability: float = OK_PROBABILITY
    prior: dict[str, Any] | None = None

    @classmethod
    def of(cls, result, points_us: np.ndarray, ct_length_mm: float,
           calibration: Calibration | None = None,
           allowed: Callable[[np.ndarray], Any] | None = None) -> Evidence:
        """The evidence of a :class:`~comreg_core.registration.search.result.RegistrationResult` for
        the ``(n, 3)`` US points it registered (US frame, mm) on a CT ``ct_length_mm`` long;
        ``allowed``: the poses a prior allows (the competitor is looked for among them)."""
        competitor = extent = p_correct = None
        if result.hypotheses is not None:
            competitor, extent = result_evidence(result.hypotheses, points_us, ct_length_mm,
                                                 allowed)
            if calibration is not None:
                p_correct = calibration.p_correct(competitor["margin"], extent)
        return cls(confidence=result.confidence, ambiguous=bool(result.ambiguous),
                   competitor=competitor, extent_share=extent, p_correct=p_correct,
                   ok_probability=OK_PROBABILITY if calibration is None
                   else calibration.ok_probability,
                   prior=result.info.get("prior"))

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> Evidence:
        """The evidence a ``result.json`` holds (what ``comreg register`` judged with)."""
        hypotheses = record.get("hypotheses") or {}
        # "calibration": the key's name before 2026-12-05 (still read)
        calibration = record.get("verdict_calibration") or record.get("calibration") or {}
        return cls(confidence=hypotheses.get("confidence"),
                   ambiguous=bool(hypotheses.get("ambiguous")),
                   competitor=record.get("competitor"), extent_share=record.get("extent_share"),
                   p_correct=record.get("p_correct"),
                   ok_probability=calibration.get("ok_probability", OK_PROBABILITY),
                   prior=record.get("prior"))

    def to_json(self) -> dict[str, Any]:
        """``result.json``'s evidence keys: ``competitor``, ``extent_share``, ``p_correct``."""
        return {"competitor": self.competitor, "extent_share": self.extent_share,
                "p_correct": self.p_correct}


def judge(points_us: np.ndarray, T_ct_us: np.ndarray, ct_surface, evidence: Evidence, *,
          scale_scan: bool = True) -> Verdict:
    """The verdict of ``T_ct_us`` (``(4, 4)`` mm) for the ``(n, 3)`` US points (US frame, mm)
    on the CT (anything :func:`~comreg_core.registration.geometry.surface.as_surface` takes), with the
    registration's ``evidence``. ``scale_scan=False`` leaves out the scale check (a live warm
    update)."""
    verdict = judge_registration(points_us, T_ct_us, ct_surface,
                                 confidence=evidence.confidence, ambiguous=evidence.ambiguous,
                                 p_correct=evidence.p_correct,
                                 ok_probability=evidence.ok_probability,
                                 short_sweep=is_short_sweep(evidence.extent_share),
                                 scale_scan=scale_scan)
    return with_prior_reasons(verdict, evidence.prior)
