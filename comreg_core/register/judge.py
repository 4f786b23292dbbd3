"""The one judge of a registration: from its evidence to the verdict, its reasons, figures,
uncertainty and advice.

Every caller gets its verdict here: ``comreg register`` (:mod:`comreg_core.register.folder`),
``comreg live`` (each update), the report (from ``result.json``), batch (through
``comreg register``), ``comreg calibrate`` and the 3D Slicer module (through
:func:`~comreg_core.register.folder.register_to_directory`). :class:`Evidence` is what a registration says about itself besides its fit: the pose search's
confidence, the clinically different competitor, the sweep's extent along the CT, the
per-patient calibration's map to ``p_correct``, and the prior's record; :func:`judge` turns it,
with the US points, the pose and the CT, into a
:class:`~comreg_core.registration.judgement.verdict.Verdict`: the pose's uncertainty in mm and
where to scan next (:mod:`~comreg_core.registration.judgement.assessment`), ``p_correct``, the
fit checks relative to this case's noise
(:func:`~comreg_core.registration.judgement.verdict.judge_registration`), then the prior's
reasons.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from comreg_core.registration.geometry.extent import SHORT_SWEEP_SHARE
from comreg_core.registration.geometry.surface import as_surface
from comreg_core.registration.judgement.assessment import pose_uncertainty
from comreg_core.registration.judgement.calibration import (OK_PROBABILITY, Calibration,
                                                            calibrated, result_evidence)
from comreg_core.registration.judgement.verdict import (Verdict, judge_registration,
                                                        with_prior_reasons)


def is_short_sweep(extent_share: float | None) -> bool:
    """Whether a sweep of this extent share (None: unknown) is short (under
    :data:`~comreg_core.registration.geometry.extent.SHORT_SWEEP_SHARE`)."""
    return extent_share is not None and extent_share < SHORT_SWEEP_SHARE


@dataclass(frozen=True)
class Evidence:
    """What a registration says about its pose, besides its fit.

    Attributes:
        confidence, ambiguous: the pose search's (None / False without it).
        competitor: the clinically different competitor
            (:func:`~comreg_core.registration.judgement.calibration.clinical_competitor`, with its
            ``T_ct_us``), or None.
        extent_share: the sweep's extent over the CT's length (0-1), or None.
        knots: the verdict calibration's map from ``p_raw`` to ``p_correct``
            (:attr:`~comreg_core.registration.judgement.calibration.Calibration.knots`), or None
            (``p_correct`` is then the uncertainty's own ``p_raw``).
        ok_probability: the least ``p_correct`` that is OK (the calibration's).
        prior: the prior's record (:func:`~comreg_core.registration.judgement.prior_reasons.prior_record`) or
            None.
    """

    confidence: float | None = None
    ambiguous: bool = False
    competitor: dict[str, Any] | None = None
    extent_share: float | None = None
    knots: dict[str, list[float]] | None = None
    ok_probability: float = OK_PROBABILITY
    prior: dict[str, Any] | None = None

    @classmethod
    def of(cls, result, points_us: np.ndarray, ct_length_mm: float,
           calibration: Calibration | None = None,
           allowed: Callable[[np.ndarray], Any] | None = None) -> Evidence:
        """The evidence of a :class:`~comreg_core.registration.search.result.RegistrationResult` for
        the ``(n, 3)`` US points it registered (US frame, mm) on a CT ``ct_length_mm`` long;
        ``allowed``: the poses a prior allows (the competitor is looked for among them)."""
        competitor = extent = None
        if result.search is not None:
            competitor, extent = result_evidence(result.search, points_us, ct_length_mm,
                                                 allowed)
        return cls(confidence=result.confidence, ambiguous=bool(result.ambiguous),
                   competitor=competitor, extent_share=extent,
                   knots=None if calibration is None else calibration.knots,
                   ok_probability=OK_PROBABILITY if calibration is None
                   else calibration.ok_probability,
                   prior=result.info.get("prior"))

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> Evidence:
        """The evidence a ``result.json`` holds (what ``comreg register`` judged with)."""
        # earlier names, still read: "hypotheses" (the search), "calibration" (to 2026-12-05)
        search = record.get("search") or record.get("hypotheses") or {}
        calibration = record.get("verdict_calibration") or record.get("calibration") or {}
        return cls(confidence=search.get("confidence"),
                   ambiguous=bool(search.get("ambiguous")),
                   competitor=record.get("competitor"), extent_share=record.get("extent_share"),
                   knots=calibration.get("knots"),
                   ok_probability=calibration.get("ok_probability", OK_PROBABILITY),
                   prior=record.get("prior"))

    def to_json(self) -> dict[str, Any]:
        """``result.json``'s evidence keys: ``competitor``, ``extent_share``."""
        return {"competitor": self.competitor, "extent_share": self.extent_share}

    def prior_tolerances(self) -> tuple[float | None, float | None]:
        """``(mm, deg)`` the prior allows (the tighter of its initial pose's and landmarks'
        tolerances; None where it says nothing)."""
        if not self.prior:
            return None, None
        mm = [self.prior.get("max_mm")] + [lm.get("tolerance_mm")
                                           for lm in self.prior.get("landmarks") or []]
        mm = [float(x) for x in mm if x is not None]
        deg = self.prior.get("max_deg") if self.prior.get("T_init") is not None else None
        return (min(mm) if mm else None), (None if deg is None else float(deg))

    def p_correct(self, p_raw: float) -> float:
        """``p_correct`` of an uncertainty's ``p_raw``: the calibration's map, or ``p_raw``."""
        return float(p_raw) if self.knots is None else calibrated(p_raw, self.knots)


def judge(points_us: np.ndarray, T_ct_us: np.ndarray, ct_surface, evidence: Evidence, *,
          scale_scan: bool = True, profiles: bool = True) -> Verdict:
    """The verdict of ``T_ct_us`` (``(4, 4)`` mm) for the ``(n, 3)`` US points (US frame, mm)
    on the CT (anything :func:`~comreg_core.registration.geometry.surface.as_surface` takes), with the
    registration's ``evidence``: the pose's uncertainty
    (:func:`~comreg_core.registration.judgement.assessment.pose_uncertainty`), ``p_correct``
    from it, then the fit checks (:func:`~comreg_core.registration.judgement.verdict.judge_registration`)
    and the prior's reasons. ``scale_scan=False`` leaves out the scale check (a live warm
    update); ``profiles=False`` the profiles of the weakest directions (a calibration's many
    judgements)."""
    surface = as_surface(ct_surface)
    prior_mm, prior_deg = evidence.prior_tolerances()
    competitor = (evidence.competitor or {}).get("T_ct_us")
    uncertainty = pose_uncertainty(
        np.asarray(points_us, dtype=np.float64), np.asarray(T_ct_us, dtype=np.float64),
        surface, ct_length_mm=None, prior_mm=prior_mm, prior_deg=prior_deg,
        competitors=[] if competitor is None else [np.asarray(competitor, dtype=np.float64)],
        profiles=profiles)
    p_correct = None if uncertainty is None else evidence.p_correct(uncertainty.p_raw)
    verdict = judge_registration(points_us, T_ct_us, surface, uncertainty=uncertainty,
                                 p_correct=p_correct, confidence=evidence.confidence,
                                 ambiguous=evidence.ambiguous,
                                 ok_probability=evidence.ok_probability,
                                 short_sweep=is_short_sweep(evidence.extent_share),
                                 scale_scan=scale_scan)
    return with_prior_reasons(verdict, evidence.prior)

