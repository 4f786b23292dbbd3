"""The network's poses as further starts of a finished pose search.

With a pretrained network, :meth:`Registrar.register <comreg_core.register.Registrar.register>`
runs the search alone first (the same starts, screening and choice as without a network) and
then gives the network's poses their chance here: each is refined like a search start, the
best-scoring one polished on the CT mesh, and it replaces the search's choice only when its
score is lower by more than a tie (:func:`~comreg_core.registration.search.scoring.tied`). So the
chosen score is never worse than the search alone's on the same input, and the network can only
add a pose the search did not find.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from comreg_core.registration.search.advice import choice_evidence
from comreg_core.registration.search.config import SearchConfig
from comreg_core.registration.geometry.icp import apply_poses, coarse_to_fine_icp
from comreg_core.registration.search.polish import polish_pose
from comreg_core.registration.search.priors import Prior
from comreg_core.registration.search.scoring import (Candidate, SearchResult, choose,
                                                     runner_up, score_poses, tied)
from comreg_core.registration.geometry.tracked_nearest import NearestTracker
from comreg_core.registration.geometry.surface import SurfaceCloud
from comreg_core.transforms import as_points, orthonormalize


def add_network_starts(result: SearchResult, starts: dict[str, np.ndarray],
                       us_points: np.ndarray, target: SurfaceCloud, config: SearchConfig,
                       *, subset_indices: np.ndarray, beam_origins: np.ndarray | None = None,
                       prior: Prior | None = None, space: str = "LPS") -> SearchResult:
    """``result`` (the search alone's) with the network's ``starts`` ``{name: T_ct_us (4, 4)
    mm}`` tried too (module docstring).

    Args:
        us_points: ``(N, 3)`` mm, the US points the search registered (US frame).
        subset_indices: the indices of the search's US subset (its ICP and score points).
        beam_origins: ``(N, 3)`` mm, each point's beam origin, or None.
        prior: only poses it allows count (None: all).
        config: the search's settings (a patch's ``min_confidence`` raised as the search
            raised it).
    """
    pts = as_points(us_points, "US points")
    subset = pts[subset_indices]
    origins = None if beam_origins is None else np.asarray(beam_origins)[subset_indices]
    centroid = pts.mean(axis=0)
    if result.patch:
        config = replace(config, min_confidence=max(config.min_confidence,
                                                    config.patch_min_confidence))
    names = list(starts)
    refined, rmse = coarse_to_fine_icp(subset, np.stack([starts[n] for n in names]),
                                       NearestTracker(target), iterations=config.icp_iterations,
                                       schedule=config.icp_schedule,
                                       margin_mm=config.icp_margin_mm,
                                       trim_fraction=config.icp_trim)
    poses = np.stack([orthonormalize(T) for T in refined])
    scores = score_poses(poses, subset, target, config, origins=origins)
    allowed = np.ones(len(poses), bool) if prior is None else prior.allows(poses, centroid)
    polishes: list[dict | None] = [None] * len(names)
    best = choose(scores, allowed, config.score_floor_mm) if allowed.any() else None
    if best is not None and target.surface is not None:
        poses[best], scores[best], polishes[best] = polish_pose(subset, centroid, poses[best],
                                                                target, config,
                                                                origins=origins)
        if prior is not None and not prior.allows(poses[best][None], centroid)[0]:
            best = None  # the polish took it out of the prior
    extra = tuple(Candidate(n, starts[n], poses[i], float(scores[i]), float(rmse[i]),
                            polishes[i]) for i, n in enumerate(names))
    merged = replace(result, candidates=result.candidates + extra,
                     starts_tried=result.starts_tried + len(names))
    chosen_score = result.best.score_mm
    if best is None or scores[best] >= chosen_score or tied(scores[best], chosen_score, config):
        return merged
    return _rechosen(merged, len(result.candidates) + best, pts, centroid, target, config,
                     prior, space)


def _rechosen(result: SearchResult, chosen: int, pts: np.ndarray, centroid: np.ndarray,
              target: SurfaceCloud, config: SearchConfig, prior: Prior | None,
              space: str) -> SearchResult:
    """``result`` with its candidate ``chosen`` (index) as the choice: the runner-up,
    confidence, ambiguity and advice found again among all its candidates."""
    cands = result.candidates
    poses = np.stack([h.T_ct_us for h in cands])
    scores = np.array([h.score_mm for h in cands])
    placed = apply_poses(poses, centroid[None])[:, 0]
    others = np.array([i for i in range(len(cands)) if i != chosen], dtype=np.int64)
    if prior is not None and len(others):
        others = others[prior.allows(poses[others], centroid)]
    runner = runner_up(poses, placed, scores, chosen, others, config)
    confidence, ambiguous, advice = choice_evidence(poses, scores, chosen, runner, config,
                                                    centroid, target, space)
    return replace(result, T_ct_us=poses[chosen], chosen=cands[chosen].name,
                   runner_up=None if runner is None else cands[runner].name,
                   score_gap_mm=None if runner is None else float(scores[runner]
                                                                  - scores[chosen]),
                   confidence=confidence, ambiguous=ambiguous, advice=advice)
