"""The polish (step 5 of :mod:`comreg_core.registration.search.search`): the best pose and the poses
tied with it refined against the exact closest points of the CT mesh and re-scored exactly; then
the choice (step 6)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from comreg_core.registration.search.config import (POLISH_TOLERANCE_MM, QUICK_POLISH_ITERATIONS,
                                                    QUICK_POLISH_POINTS, SLIDE_PROBE_GAIN,
                                                    SearchConfig)
from comreg_core.registration.geometry.extent import SLIDE_PROBE_MAX_SHARE, extent_mm
from comreg_core.registration.geometry.icp import (POLISH_PATIENCE, apply_poses,
                                                   point_to_plane_icp, strided)
from comreg_core.registration.geometry.metrics import rotation_error_deg
from comreg_core.registration.search.scoring import (choose, polish_candidates, runner_up,
                                                     trimmed_mean)
from comreg_core.registration.geometry.surface import SurfaceCloud, ct_length_mm, facing_away
from comreg_core.transforms import apply_transform, matmul, project


def choose_and_polish(subset_mm: np.ndarray, centroid: np.ndarray, poses: np.ndarray,
                      scores: np.ndarray, polishes: list[dict[str, Any] | None],
                      target: SurfaceCloud,
                      config: SearchConfig, *, origins: np.ndarray | None = None,
                      within: Callable[[np.ndarray], np.ndarray] | None = None,
                      slide_probe: bool = True) -> tuple[int, int | None]:
    """Steps 5-6 of the search: polish the poses tied with the best (``poses``
    ``(B, 4, 4)``, ``scores`` ``(B,)`` and ``polishes`` are updated in place; poses polished
    before are not polished again), choose, and find the runner-up. Returns ``(chosen,
    runner-up or None)`` indices.

    ``within``: ``(B, 4, 4) poses -> (B,) bool``, the poses a prior allows
    (:meth:`~comreg_core.registration.search.priors.Prior.allows`), or None (all). With it only the
    allowed poses are polished, chosen (the polished ones among them, else any) and count as
    the runner-up; when it allows none, all are considered. ``slide_probe``: the chosen pose
    of a partial sweep gets :func:`probe_slides` (the full search; a warm start does not;
    nor with a prior, which bounds the pose itself)."""
    eligible = np.ones(len(poses), dtype=bool)
    allowed = eligible if within is None else within(poses)
    pool = np.flatnonzero(allowed) if allowed.any() else np.arange(len(poses))
    placed = apply_poses(poses, centroid[None])[:, 0]  # B 3
    if target.surface is not None:
        # the best pose and those tied with it, polished and re-scored exactly; only polished
        # poses can be chosen (the scores of the others are not exact, and they were not tied)
        candidates = [int(pool[k]) for k in polish_candidates(scores[pool], poses[pool],
                                                               placed[pool], config)]
        quick = len(candidates) > 1  # several: a quick polish of each, then the chosen in full
        for i in candidates:
            if polishes[i] is None:
                poses[i], scores[i], polishes[i] = polish_pose(subset_mm, centroid, poses[i],
                                                               target, config, quick=quick,
                                                               origins=origins)
        placed = apply_poses(poses, centroid[None])[:, 0]
        eligible = np.array([p is not None for p in polishes])
    if within is not None:  # a polish may have moved a pose out of the prior
        allowed = within(poses)
        eligible = next((m for m in (eligible & allowed, allowed) if m.any()), eligible)
    best = choose(scores, eligible, config.score_floor_mm)
    if polishes[best] is not None and polishes[best]["quick"]:
        before = poses[best].copy(), scores[best], polishes[best]
        poses[best], scores[best], polishes[best] = polish_pose(
            subset_mm, centroid, poses[best], target, config, after=polishes[best],
            origins=origins)
        if within is not None and allowed[best] and not within(poses[best][None])[0]:
            poses[best], scores[best], polishes[best] = before  # it left the prior: undone
        placed[best] = apply_transform(poses[best], centroid[None])[0]
    if slide_probe and within is None and polishes[best] is not None:
        probed = probe_slides(subset_mm, centroid, poses[best], scores[best], polishes[best],
                              target, config, origins=origins)
        if probed is not None:
            poses[best], scores[best], polishes[best] = probed
            placed[best] = apply_transform(poses[best], centroid[None])[0]
    others = np.array([i for i in range(len(poses)) if i != best
                       and (allowed[i] or not allowed.any())], dtype=np.int64)
    runner = runner_up(poses, placed, scores, best, others, config)
    return best, runner


def probe_slides(subset_mm: np.ndarray, centroid: np.ndarray, T: np.ndarray, score: float,
                 previous: dict[str, Any], target: SurfaceCloud, config: SearchConfig, *,
                 origins: np.ndarray | None = None
                 ) -> tuple[np.ndarray, float, dict[str, Any]] | None:
    """The slide probe (``config.slide_probe_mm``) of ``T`` ``(4, 4)``, the polished chosen
    pose of ``subset_mm`` ``(n, 3)`` (its exact ``score``, its polish record ``previous``):
    ``T`` slid by the probe distance along the CT's long axis, both ways, is quick-polished
    from there and scored exactly on all of ``subset_mm``; the better of the two, if it scores
    lower than ``score``, is polished in full. Returns it when it then scores at least
    :data:`SLIDE_PROBE_GAIN` lower: ``(pose, exact score, polish record)``, the record with
    ``slid_mm``, ``probe_shift_mm`` (of the US centroid from ``T``) and ``moved_mm`` (from
    before the first polish, as the norms combine). None otherwise, when the sweep spans at
    least :data:`~comreg_core.registration.geometry.extent.SLIDE_PROBE_MAX_SHARE` of the CT's
    length along its long axis (a whole cloud; the sweep's
    :func:`~comreg_core.registration.geometry.extent.extent_mm` along that axis, so that a few
    stray points do not make a partial sweep whole), or when ``slide_probe_mm`` is 0."""
    if config.slide_probe_mm <= 0:
        return None
    axis = target.axes[:, 0]
    span = extent_mm(apply_transform(T, subset_mm), axis)
    if span >= SLIDE_PROBE_MAX_SHARE * ct_length_mm(target):
        return None
    best = None
    for slide in (-config.slide_probe_mm, config.slide_probe_mm):
        shift = np.eye(4)
        shift[:3, 3] = slide * axis
        pose, quick_score, info = polish_pose(subset_mm, centroid, matmul(shift, T), target, config,
                                              quick=True, origins=origins)
        if quick_score < score and (best is None or quick_score < best[1]):
            best = pose, quick_score, info, slide
    if best is None:
        return None
    pose, probed_score, info = polish_pose(subset_mm, centroid, best[0], target, config,
                                           after=best[2], origins=origins)
    if not probed_score < (1.0 - SLIDE_PROBE_GAIN) * score:
        return None
    moved = np.linalg.norm(apply_transform(pose, centroid[None])
                           - apply_transform(T, centroid[None]))
    info.update(slid_mm=float(best[3]), probe_shift_mm=float(moved),
                moved_mm=float(np.hypot(previous["moved_mm"], moved)))
    return pose, probed_score, info


def polish_pose(subset_mm: np.ndarray, centroid: np.ndarray, T: np.ndarray,
                target: SurfaceCloud, config: SearchConfig, *, quick: bool = False,
                after: dict[str, Any] | None = None, origins: np.ndarray | None = None
                ) -> tuple[np.ndarray, float, dict[str, Any]]:
    """Step 5 of the search for one pose ``T`` ``(4, 4)``: the polished pose, its
    exact score (trimmed mean distance of ``subset_mm`` ``(n, 3)`` to the mesh, mm) and the
    polish's record (:attr:`~comreg_core.registration.search.scoring.Candidate.polish`;
    ``moved_mm`` of the US ``centroid`` ``(3,)``).
    ``quick``: on :data:`QUICK_POLISH_POINTS`
    strided points and at most :data:`QUICK_POLISH_ITERATIONS` (to compare tied poses);
    ``after``: the record of a quick polish this one continues (its counts are added)."""
    mark = time.perf_counter()
    source = strided(subset_mm, QUICK_POLISH_POINTS) if quick else subset_mm
    iterations = (min(QUICK_POLISH_ITERATIONS, config.polish_iterations) if quick
                  else config.polish_iterations)
    surface = target.surface
    fit = point_to_plane_icp(source, T, surface.matcher(config.polish_max_distance_mm),
                             iterations=iterations, tolerance_mm=POLISH_TOLERANCE_MM,
                             patience=POLISH_PATIENCE)
    polished = fit.T
    info = {"iterations": int(fit.iterations), "inlier_fraction": float(fit.inlier_fraction),
            "rmse_mm": float(fit.rmse_mm), "converged": bool(fit.converged)}
    info["moved_mm"] = float(np.linalg.norm(apply_transform(polished, centroid[None])
                                            - apply_transform(T, centroid[None])))
    registered = apply_transform(polished, subset_mm)
    _, normals, distances = surface.closest(registered)
    if origins is not None:  # share of points whose surface faces away from their probe
        away = facing_away(normals, registered, apply_transform(polished, origins))
        info["facing_away"] = float(away.mean())
        distances = distances + config.facing_penalty_mm * away
    score = float(trimmed_mean(distances[None], config.score_trim)[0])
    info["quick"] = quick
    info["runtime_s"] = time.perf_counter() - mark
    if after is not None:  # moved_mm: from before the quick polish (near enough: both small)
        info["iterations"] += after["iterations"]
        info["runtime_s"] += after["runtime_s"]
        info["moved_mm"] = float(np.hypot(info["moved_mm"], after["moved_mm"]))
    return polished, score, info


def halves_disagreement_deg(subset_mm: np.ndarray, T: np.ndarray, target: SurfaceCloud,
                            config: SearchConfig, *, origins: np.ndarray | None = None
                            ) -> float:
    """How far apart (deg) the rotations lie that the two halves of a sweep fit best: the US
    points ``subset_mm`` ``(n, 3)`` (beam ``origins`` ``(n, 3)`` or None) are split at their
    median along the CT's long axis as ``T`` ``(4, 4)`` places them, and each half is polished
    alone from ``T``. A shaft pins its rotation about its own axis only weakly, and a real
    sweep's tracking and echoes are not consistent along its length: when the halves each fit
    best turned several degrees apart, the data cannot pin the whole sweep's rotation closer
    than that (on the real fibula sweep's first 125 mm: halves 11 deg apart, the pose 7 deg
    from the whole sweep's, turned about the shaft). 0 when a half has under 6 points."""
    along = project(apply_transform(T, subset_mm), target.axes[:, 0])
    lower = along < np.median(along)
    poses = []
    for half in (lower, ~lower):
        if half.sum() < 6:
            return 0.0
        pose, _, _ = polish_pose(subset_mm[half], subset_mm[half].mean(axis=0), T, target,
                                 config, origins=None if origins is None else origins[half])
        poses.append(pose)
    return float(rotation_error_deg(poses[0], poses[1]))
