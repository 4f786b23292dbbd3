"""The prior's record and its reasons for the verdict: ``result.json``'s ``prior``.

:func:`prior_record`: the chosen pose's rotation and shift from ``T_init``, each landmark's
error, ``at_edge`` (beyond :data:`EDGE_SHARE` of the rotation's, the shift's or a landmark's
tolerance) and ``reasons`` that make the verdict CHECK
(:func:`~comreg_core.registration.judgement.verdict.with_prior_reasons`): a result at the edge
(when the prior excludes the truth the search can only find poses inside that fit worse, and
they gather at its edge), a pose outside that fits clearly better, no pose within at all.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from comreg_core.registration.search.priors import Prior
from comreg_core.transforms import apply_transform, invert_rigid

#: The chosen pose is *at the edge* of a tolerance beyond this share of it.
EDGE_SHARE = 0.9


def prior_record(prior: Prior, T_ct_us: np.ndarray, centroid: np.ndarray, search=None, *,
                 min_confidence: float = 0.3, score_floor_mm: float = 0.05) -> dict[str, Any]:
    """``result.json``'s ``prior`` for the chosen ``T_ct_us`` and the US ``centroid`` (mm):
    ``init_file``, ``space``, ``T_init``, ``max_deg``, ``max_mm`` (null without ``T_init``),
    ``landmarks`` (each with its ``error_mm``), ``rotation_from_init_deg``,
    ``shift_from_init_mm``, ``within``, ``at_edge``, ``best_outside`` (the best-scoring
    candidate of ``search``, a :class:`~comreg_core.registration.search.scoring.SearchResult`,
    that the prior rules out, with its ``lead`` over the chosen one, or null) and ``reasons``
    (sentences for the verdict: see the module docstring; a pose outside counts when it leads
    by ``min_confidence``, as the search's confidence measures a lead)."""
    T = np.asarray(T_ct_us, dtype=np.float64)[None]
    rotation, shift, landmark = (a[0] for a in prior.errors(T, centroid))
    init = prior.T_init is not None
    landmarks = [{**lm.to_json(), "error_mm": float(e)}
                 for lm, e in zip(prior.landmarks, landmark)]
    within = bool(prior.allows(T, centroid)[0])
    reasons = []
    edges = []
    if init and rotation > EDGE_SHARE * prior.max_deg:
        edges.append(f"{rotation:.1f} of {prior.max_deg:g} deg")
    if init and shift > EDGE_SHARE * prior.max_mm:
        edges.append(f"{shift:.1f} of {prior.max_mm:g} mm")
    lm_edges = [f"landmark '{lm['label']}' {lm['error_mm']:.1f} of {lm['tolerance_mm']:g} mm"
                for lm in landmarks if lm["error_mm"] > EDGE_SHARE * lm["tolerance_mm"]]
    if not within:
        reasons.append("No pose within the prior fits the US points: the result lies outside "
                       f"its tolerances ({', '.join(edges + lm_edges)}); check the initial "
                       "pose and the landmarks.")
    elif edges or lm_edges:
        what = "the initial pose's tolerance" if edges else "the landmarks' tolerance"
        reasons.append(f"The result sits at the edge of {what} ({', '.join(edges + lm_edges)})"
                       ": the prior may exclude the true pose.")
    best_outside = None
    if search is not None:
        best_outside = _best_outside(prior, centroid, search.candidates)
        chosen = search.best.score_mm
        if best_outside is not None and math.isfinite(chosen):
            lead = max(chosen - best_outside["score_mm"], 0.0) / max(chosen, score_floor_mm)
            best_outside["lead"] = float(lead)
            if lead >= min_confidence:
                reasons.append(
                    f"A pose outside the prior fits the US points clearly better (score "
                    f"{best_outside['score_mm']:.2f} vs {chosen:.2f} mm"
                    + (f", {best_outside['rotation_from_init_deg']:.0f} deg / "
                       f"{best_outside['shift_from_init_mm']:.0f} mm from the initial pose"
                       if init else "") + "): the prior may exclude the true pose.")
    return {"init_file": prior.init_file, "space": prior.space,
            "T_init": None if not init else prior.T_init.tolist(),
            "max_deg": float(prior.max_deg) if init else None,
            "max_mm": float(prior.max_mm) if init else None, "landmarks": landmarks,
            "rotation_from_init_deg": float(rotation) if init else None,
            "shift_from_init_mm": float(shift) if init else None, "within": within,
            "at_edge": bool(edges or lm_edges), "best_outside": best_outside,
            "reasons": reasons}


def _best_outside(prior: Prior, centroid, candidates) -> dict[str, Any] | None:
    outside = [h for h in candidates if math.isfinite(h.score_mm)
               and not prior.allows(h.T_ct_us[None], centroid)[0]]
    if not outside:
        return None
    best = min(outside, key=lambda h: h.score_mm)
    rotation, shift, _ = prior.errors(best.T_ct_us[None], centroid)
    init = prior.T_init is not None
    return {"name": best.name, "score_mm": float(best.score_mm),
            "rotation_from_init_deg": float(rotation[0]) if init else None,
            "shift_from_init_mm": float(shift[0]) if init else None}


def prior_allows(prior: Prior, result):
    """``(4, 4) T -> bool``: whether ``prior`` (in the result's space) allows a pose of
    ``result`` (a :class:`~comreg_core.registration.search.result.RegistrationResult`; the US centroid:
    that of the points it registered)."""
    points = apply_transform(invert_rigid(result.T_ct_us), result.registered_points)
    centroid = points.mean(axis=0)
    return lambda T: bool(prior.allows(np.asarray(T)[None], centroid)[0])
