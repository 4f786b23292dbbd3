"""Warm re-registration: a sweep that grew since its last registration, registered again from
that registration's poses instead of a full search (live registration while scanning,
``comreg live``).

The last result's refined candidates (:class:`~comreg_core.registration.search.scoring.
SearchResult`) hold the chosen pose and the poses that competed with it. The warm search
takes the chosen pose and the best-scoring distinct others (at most ``top``), refines each on
the grown cloud by a short ICP against the dense CT cloud (:data:`WARM_ITERATIONS` on
:data:`WARM_POINTS` of the ``icp_points`` subset), scores them on the subset, polishes and chooses as the full search does
(:func:`~comreg_core.registration.search.polish.choose_and_polish`), so the result carries the same
confidence, runner-up and evidence for the verdict. No screening and no new starts: a pose that
was not among the last result's candidates cannot be found here; the caller runs a full search
when the evidence changed (a new region covered, the verdict flipped).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.registration.search.advice import choice_evidence
from comreg_core.registration.search.config import SearchConfig
from comreg_core.registration.geometry.icp import apply_poses, point_to_plane_icp, strided
from comreg_core.registration.search.polish import choose_and_polish
from comreg_core.registration.search.priors import Prior
from comreg_core.registration.search.scoring import (Candidate, SearchResult,
                                                     same_pose, score_poses)
from comreg_core.registration.geometry.tracked_nearest import NearestTracker
from comreg_core.registration.geometry.surface import SurfaceCloud
from comreg_core.transforms import as_points, orthonormalize

#: Poses a warm search refines: the last chosen one and the best distinct others.
WARM_TOP = 4
#: Their refinement before the score and the polish: point-to-plane ICP on this many evenly
#: strided US points of the ICP subset, at most this many iterations (they start where the
#: last registration left them, near their optimum for the grown sweep; the polish on the
#: mesh finishes the chosen one).
WARM_POINTS = 512
WARM_ITERATIONS = 10


def warm_poses(previous: SearchResult, centroid: np.ndarray, config: SearchConfig,
               top: int = WARM_TOP) -> tuple[list[str], np.ndarray]:
    """The names and ``(K, 4, 4)`` poses (mm) a warm search starts from: ``previous``'s chosen
    pose, then its other candidates by increasing score, each distinct from those already
    taken (``distinct_deg``/``distinct_mm`` at the US ``centroid`` ``(3,)``), ``top`` at most."""
    if not previous.candidates:
        raise ComRegError("The previous registration has no pose candidates to start from.",
                          "Register it with the pose search on first.")
    chosen = previous.best
    others = sorted((h for h in previous.candidates if h.name != chosen.name),
                    key=lambda h: (not math.isfinite(h.score_mm), h.score_mm))
    candidates = [chosen] + others
    poses = np.stack([h.T_ct_us for h in candidates])
    placed = apply_poses(poses, centroid[None])[:, 0]
    kept: list[int] = [0]
    for i in range(1, len(candidates)):
        if len(kept) == top:
            break
        if not same_pose(poses, placed, i, np.array(kept), config).any():
            kept.append(i)
    return [candidates[i].name for i in kept], poses[kept]


def warm_search(us_points: np.ndarray, previous: SearchResult, target: SurfaceCloud,
                config: SearchConfig | None = None, *,
                beam_origins: np.ndarray | None = None, prior: Prior | None = None,
                space: str = "LPS", top: int = WARM_TOP) -> SearchResult:
    """Register ``us_points`` ``(N, 3)`` mm (US frame) again from ``previous``'s poses (module
    docstring): the same :class:`SearchResult` as
    :func:`~comreg_core.registration.search.search.search_poses`, ``starts_tried`` = the poses
    refined. ``beam_origins`` ``(N, 3)`` mm or None; ``prior`` (in the CT's space) or None:
    only poses within it are chosen."""
    from comreg_core.registration.search.search import is_patch, us_subset_indices

    cfg = config or SearchConfig()
    pts = as_points(us_points, "US points")
    keep = us_subset_indices(len(pts), cfg.icp_points)
    subset_mm = pts[keep]
    origins = None if beam_origins is None else as_points(beam_origins, "beam origins")[keep]
    centroid = pts.mean(axis=0)
    patch = is_patch(pts, target, cfg)
    if patch:
        cfg = replace(cfg, min_confidence=max(cfg.min_confidence, cfg.patch_min_confidence))
    names, starts = warm_poses(previous, centroid, cfg, top)
    fit = point_to_plane_icp(strided(subset_mm, WARM_POINTS), starts, NearestTracker(target),
                             iterations=WARM_ITERATIONS, trim_fraction=cfg.icp_trim)
    poses = np.stack([orthonormalize(T) for T in fit.T])
    within = None if prior is None else (lambda T: prior.allows(T, centroid))
    scores = score_poses(poses, subset_mm, target, cfg, origins=origins)
    polishes: list[dict[str, Any] | None] = [None] * len(names)
    best, runner = choose_and_polish(subset_mm, centroid, poses, scores, polishes, target, cfg,
                                     origins=origins, within=within,
                                     slide_probe=False)  # the full searches probed
    confidence, ambiguous, advice = choice_evidence(poses, scores, best, runner, cfg, centroid,
                                                    target, space)
    candidates = tuple(Candidate(n, starts[i], poses[i], float(scores[i]),
                                 float(fit.rmse_mm[i]), polishes[i])
                       for i, n in enumerate(names))
    return SearchResult(
        T_ct_us=poses[best], chosen=names[best],
        runner_up=None if runner is None else names[runner],
        score_gap_mm=None if runner is None else float(scores[runner] - scores[best]),
        confidence=confidence, ambiguous=ambiguous, candidates=candidates,
        starts_tried=len(names), advice=advice, patch=patch)
