"""Scores, sameness, confidence and the choice among refined poses; the result types.

Definitions (steps 4 and 6 of :mod:`comreg_core.registration.search.search`): the **score** of a pose
is the trimmed mean distance (mm) of its registered US points to the CT; two poses are the
**same** when rotated apart by at most ``distinct_deg`` and placing the US centroid within
``distinct_mm``; the **confidence** of a pose scoring ``a`` over one scoring ``b`` is
``max(b - a, 0) / max(b, score_floor_mm)``, in [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from comreg_core.registration.search.config import SearchConfig
from comreg_core.registration.geometry.icp import apply_poses


def trimmed_mean(distances: np.ndarray, trim: float) -> np.ndarray:
    """``(B,)`` mean of the smallest ``1 - trim`` share (at least one) of each row of ``(B, n)``
    distances: the candidates' score."""
    n = distances.shape[1]
    return np.sort(distances, axis=1)[:, :max(1, n - int(trim * n))].mean(axis=1)


def score_poses(poses: np.ndarray, points: np.ndarray, target, config: SearchConfig, *,
                origins: np.ndarray | None = None, approximate: bool = False) -> np.ndarray:
    """``(B,)`` scores (mm) of ``(B, 4, 4)`` poses for ``(n, 3)`` US points: the trimmed mean of
    their distances to the CT cloud ``target`` (:meth:`SurfaceCloud.surface_distances`), each
    point facing away from its beam origin (``origins`` ``(n, 3)``, US frame, or None)
    penalised by ``facing_penalty_mm``."""
    moved = apply_poses(poses, points)  # B n 3
    beams = None if origins is None else apply_poses(poses, origins)
    return trimmed_mean(target.surface_distances(moved, approximate, origins=beams,
                                                 facing_penalty_mm=config.facing_penalty_mm),
                        config.score_trim)


def same_pose(poses: np.ndarray, centroids: np.ndarray, i: int, others: np.ndarray,
               config: SearchConfig, *, rotation_only: bool = False) -> np.ndarray:
    """Which of the poses ``others`` (indices) are the same pose as pose ``i``: rotated apart by
    at most ``distinct_deg`` and, unless ``rotation_only``, placing the US centroid within
    ``distinct_mm``. ``poses`` ``(B, 4, 4)``, ``centroids`` ``(B, 3)`` mm (the US centroid
    placed by each pose); returns ``(len(others),)`` bool."""
    cos = (np.einsum("kij,ij->k", poses[others, :3, :3], poses[i, :3, :3]) - 1.0) / 2.0
    same = cos >= math.cos(math.radians(config.distinct_deg))
    if not rotation_only:
        same &= np.linalg.norm(centroids[others] - centroids[i], axis=1) <= config.distinct_mm
    return same


def confidence_over(score: float, others: np.ndarray | float, config: SearchConfig):
    """How clearly a pose scoring ``score`` beats poses scoring ``others`` (mm): ``max(other -
    score, 0) / max(other, score_floor_mm)``, in [0, 1] (module docstring, step 6)."""
    others = np.asarray(others, dtype=np.float64)
    return np.maximum(others - score, 0.0) / np.maximum(others, config.score_floor_mm)


#: Two scores are *tied* when the worse leads the better by less than this share of itself
#: (confidence below it): far above floating-point noise (1e-15) and far below the smallest
#: lead that counts as evidence (``min_confidence``, 0.3). A decision between tied scores is
#: made by the order of the candidates (fixed by the input's shape), never by their last bits.
SCORE_TIE_SHARE = 1e-3


def tied(score: float, other: float, config: SearchConfig) -> bool:
    """Whether two scores (mm) are a tie (:data:`SCORE_TIE_SHARE`)."""
    low, high = min(score, other), max(score, other)
    return bool(confidence_over(low, high, config) < SCORE_TIE_SHARE)


def choose(scores: np.ndarray, eligible: np.ndarray, score_floor_mm: float = 0.05) -> int:
    """Index of the chosen pose among the ``eligible`` ones ``(B,)`` bool: the best score
    ``(B,)`` mm; of the scores tied with it (:func:`tied`), the first in generation order."""
    masked = np.where(eligible, scores, np.inf)
    best = float(masked.min())
    if not math.isfinite(best):
        return int(np.argmin(masked))
    candidates = np.flatnonzero(eligible)
    lead = np.maximum(scores[candidates] - best, 0.0) / np.maximum(scores[candidates],
                                                                   score_floor_mm)
    return int(candidates[np.flatnonzero(lead < SCORE_TIE_SHARE)[0]])


def runner_up(poses: np.ndarray, placed: np.ndarray, scores: np.ndarray, best: int,
              candidates: np.ndarray, config: SearchConfig) -> int | None:
    """The best-scoring of ``candidates`` (indices, ``best`` excluded by the caller) that is a
    different pose from ``best`` (:func:`same_pose`), or None. ``poses`` ``(B, 4, 4)``,
    ``placed`` ``(B, 3)`` US centroids, ``scores`` ``(B,)`` mm."""
    candidates = np.asarray(candidates, dtype=np.int64)
    distinct = candidates[~same_pose(poses, placed, best, candidates, config)]
    return int(distinct[np.argmin(scores[distinct])]) if len(distinct) else None


def polish_candidates(scores: np.ndarray, poses: np.ndarray, placed: np.ndarray,
                       config: SearchConfig) -> list[int]:
    """The poses worth polishing: the best-scoring one and the distinct poses tied with it
    (confidence below ``min_confidence``), the network's own pose (index 0) next if it is tied,
    then by increasing score, at most ``polish_top``."""
    order = np.argsort(scores, kind="stable")
    tied = order[confidence_over(scores[order[0]], scores[order], config) < config.min_confidence]
    if 0 in tied[1:]:  # the prior: a tie the geometry cannot break may be the network's to break
        tied = np.concatenate([tied[:1], [0], tied[1:][tied[1:] != 0]])
    kept: list[int] = []
    for i in tied:
        if len(kept) == config.polish_top:
            break
        if not kept or not same_pose(poses, placed, int(i), np.array(kept), config).any():
            kept.append(int(i))
    return kept


@dataclass(frozen=True)
class Candidate:
    """One refined candidate: ``name``, its start ``T_start`` and refined ``T_ct_us``
    (``(4, 4)`` mm, after the polish when polished), ``score_mm`` (trimmed mean distance to the
    CT, mm; exact distances to the mesh when polished), the refinement ICP's final
    ``icp_rmse_mm``, and ``polish``: ``{"iterations", "inlier_fraction", "rmse_mm"
    (matched points' RMS distance to the mesh), "converged", "moved_mm" (how far the polish
    moved the US centroid), "quick" (only the quick polish of a tied pose), "runtime_s"}``,
    None when not polished."""

    name: str
    T_start: np.ndarray
    T_ct_us: np.ndarray
    score_mm: float
    icp_rmse_mm: float
    polish: dict[str, Any] | None = None


@dataclass(frozen=True)
class SearchResult:
    """The outcome of :func:`search_poses` (module docstring for the definitions).

    Attributes:
        T_ct_us: ``(4, 4)`` mm, the chosen candidate's refined (and polished) pose.
        chosen: its name.
        runner_up: the best-scoring genuinely different pose's name, None if there is none.
        score_gap_mm: ``score(runner_up) - score(chosen)`` (mm), None without a runner-up.
        confidence: ``max(score_gap_mm, 0) / max(score(runner_up), score_floor_mm)`` in
            [0, 1]; 1.0 without a runner-up.
        ambiguous: ``confidence < min_confidence`` (``patch_min_confidence`` for a patch).
        candidates: every refined :class:`Candidate`, in generation order.
        starts_tried: start poses built and screened before the best ``refine_top`` were refined.
        advice: when ambiguous, where the runner-up puts the sweep and what to scan to tell the
            poses apart (:func:`comreg_core.registration.search.advice.ambiguity_advice`), else None.
        patch: the US cloud was a patch (a short sweep,
            :func:`~comreg_core.registration.search.search.is_patch`), searched over all rotations.
    """

    T_ct_us: np.ndarray
    chosen: str
    runner_up: str | None
    score_gap_mm: float | None
    confidence: float
    ambiguous: bool
    candidates: tuple[Candidate, ...] = field(default=())
    starts_tried: int = 0
    advice: dict[str, Any] | None = None
    patch: bool = False

    @property
    def polish(self) -> dict[str, Any] | None:
        """The chosen pose's polish (:attr:`Candidate.polish`), None when it was not run."""
        return self.best.polish

    @property
    def polished(self) -> list[str]:
        """Names of the polished candidates (the best and those tied with it)."""
        return [h.name for h in self.candidates if h.polish is not None]

    @property
    def scores(self) -> dict[str, float]:
        """``{name: score_mm}`` of every candidate."""
        return {h.name: h.score_mm for h in self.candidates}

    @property
    def best(self) -> Candidate:
        return next(h for h in self.candidates if h.name == self.chosen)

    def to_json(self) -> dict[str, Any]:
        """JSON-able summary (``result.json``'s ``search`` block)."""
        return {"chosen": self.chosen, "runner_up": self.runner_up,
                "score_mm": self.best.score_mm, "score_gap_mm": self.score_gap_mm,
                "confidence": self.confidence, "ambiguous": self.ambiguous,
                "starts_tried": self.starts_tried, "scores_mm": self.scores,
                "polish": self.polish, "polished": self.polished, "advice": self.advice,
                "patch": self.patch}
