"""Screening (step 2 of :mod:`comreg_core.registration.search.search`): thousands of start poses
get a quick ICP and a quick score at once, and only the best distinct ones go on to the full
refinement."""

from __future__ import annotations

import numpy as np

from comreg_core.registration.geometry import kernels
from comreg_core.registration.search.config import SearchConfig
from comreg_core.registration.geometry.icp import apply_poses, strided
from comreg_core.registration.search.scoring import same_pose
from comreg_core.registration.geometry.surface import SurfaceCloud


def screen_starts(us_points: np.ndarray, starts: np.ndarray, target: SurfaceCloud,
                  config: SearchConfig, *, keep_first: bool = True,
                  origins: np.ndarray | None = None, within=None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Pick the starts worth a full ICP: ``screen_iterations`` of point-to-plane ICP on
    ``screen_points`` US points for every start at once (correspondences from the CT's
    closest-point grid, :meth:`SurfaceCloud.nearest_approx`), then a quick score (trimmed
    mean distance of ``screen_score_points`` US points to the CT); keep the first start (the
    network's own pose, unmoved; unless ``keep_first`` is False) and then the best-scoring
    ones, skipping those within
    ``distinct_deg`` and ``distinct_mm`` (US centroid) of one already kept, up to
    ``refine_top`` in all (all of them, unmoved, when ``refine_top`` is 0 or not below ``B``).

    Args:
        us_points: ``(n, 3)`` mm, US points (US frame).
        starts: ``(B, 4, 4)`` mm start poses ``T_ct_us``.
        origins: ``(n, 3)`` mm, each US point's beam origin (US frame), or None.
        within: ``(B, 4, 4) -> (B,) bool``, the poses a prior allows, or None: the screened
            poses it allows are kept first (a prior's starts may slide out of it).

    Returns:
        ``(K,)`` indices of the kept starts and their ``(K, 4, 4)`` screened poses.
    """
    if config.refine_top == 0 or len(starts) <= config.refine_top:
        return np.arange(len(starts)), starts

    sub = strided(us_points, config.screen_score_points)
    sub_origins = None if origins is None else strided(origins, config.screen_score_points)
    poses, scores = _screen_compiled(us_points, starts, target, config, sub, sub_origins)
    centroids = apply_poses(poses, us_points.mean(axis=0)[None])[:, 0]  # B 3
    chosen = [0] if keep_first else []
    order = np.argsort(scores, kind="stable")
    if within is not None:
        order = order[np.argsort(~within(poses)[order], kind="stable")]
    for i in order:
        if len(chosen) == config.refine_top:
            break
        if not chosen or not same_pose(poses, centroids, i, np.array(chosen), config).any():
            chosen.append(int(i))
    kept = np.array(chosen)
    screened = poses[kept]
    if keep_first:
        screened[0] = starts[0]
    return kept, screened


def _screen_compiled(us_points, starts, target: SurfaceCloud, config: SearchConfig,
                     sub: np.ndarray, sub_origins: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The screening's ICP and quick score by the compiled kernels: ``(B, 4, 4)`` screened
    poses and their ``(B,)`` scores (mm)."""
    origin, spacing, grid = target.closest_point_grid
    cloud, normals = target.points, target.normals
    origins = np.zeros((0, 3)) if sub_origins is None else np.ascontiguousarray(sub_origins)
    with kernels.PARALLEL:  # one parallel launch at a time (kernels.py)
        poses, _, _ = kernels.grid_icp(
            np.ascontiguousarray(strided(us_points, config.screen_points)),
            np.ascontiguousarray(starts, dtype=np.float64), origin, float(spacing), grid, cloud,
            normals, int(config.screen_iterations), float(config.icp_trim), 0.1)
        scores = kernels.grid_scores(
            poses, np.ascontiguousarray(sub), origins, origin, float(spacing), grid, cloud,
            normals, float(config.score_trim), float(config.facing_penalty_mm))
    return poses, scores
