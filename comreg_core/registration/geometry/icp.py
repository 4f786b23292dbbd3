"""One rigid point-to-plane ICP, batched over start poses, with pluggable correspondences.

:func:`point_to_plane_icp` refines ``B`` start poses of one source cloud at once. Where the
correspondences come from is the caller's choice (a :data:`~comreg_core.registration.geometry.surface.
Matcher`): the nearest of dense CT samples (:meth:`SurfaceCloud.match`; as a
:class:`~comreg_core.registration.geometry.tracked_nearest.NearestTracker`, the same answers
with each start's points remembered between iterations: the pose search's refinement, the warm
search, the verdict's refit), a closest-point grid (:meth:`SurfaceCloud.match_approx`, its
screening), or the exact closest points of the CT mesh with a distance gate
(:meth:`CTSurface.matcher`, the polish and the ``icp-gt`` baseline: a batch of one or a few).
:func:`coarse_to_fine_icp` runs it on growing strided subsets, dropping starts that fall behind.

No gradient and no torch: the network's own differentiable ICP is
:func:`comreg_core.model.diff_icp.differentiable_icp`. Point-to-plane converges along a shaft,
where the surface slides under the points, in a few iterations; point-to-point ICP crawls there
(``tests/benchmarks/bench_search.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from comreg_core.errors import InvalidGeometryError
from comreg_core.registration.geometry.kernels import pose_steps, transform_points
from comreg_core.registration.geometry.surface import Matcher
from comreg_core.registration.geometry.tracked_nearest import NearestTracker
from comreg_core.transforms import as_points

#: A polish (and the mesh refinement) stops once its RMS has not fallen by :data:`STALL_MM`
#: for this many iterations (its gated pairs can make it jitter above the tolerance for good).
POLISH_PATIENCE = 5
#: The mesh refinement of the network's ICP result (``model.icp.mesh_refine``,
#: :func:`~comreg_core.registration.geometry.icp.refine_on_mesh`): US points used (evenly strided),
#: most iterations, and the share of the farthest pairs left out (the sweep's false
#: intersections; untrimmed, it leaves half the simulated validation sweeps over 2 mm / 2 deg
#: from the truth even when it starts there).
MESH_REFINE_POINTS = 1024
MESH_REFINE_ITERATIONS = 50
MESH_REFINE_TRIM = 0.1

#: Fewest matched pairs an update needs (six unknowns).
MIN_PAIRS = 6
#: With ``patience``: an RMS that falls by less than this (mm) has not improved.
STALL_MM = 1e-4


class ICPResult(NamedTuple):
    """What :func:`point_to_plane_icp` returns (``B`` start poses).

    Attributes:
        T: ``(B, 4, 4)`` refined poses (mm).
        rmse_mm: ``(B,)`` RMS point-to-plane residual of the pairs kept at each start's last
            matching (NaN when it never had :data:`MIN_PAIRS`).
        iterations: ``(B,)`` matchings done per start.
        converged: ``(B,)`` the last update moved no source point by ``tolerance_mm`` or more.
        inlier_fraction: ``(B,)`` share of the source points matched (within the matcher's
            gate) at the last matching.
    """

    T: np.ndarray
    rmse_mm: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    inlier_fraction: np.ndarray


def apply_poses(poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(n, 3)`` points (or ``(B, n, 3)``, one cloud per pose) moved by each of ``(B, 4, 4)``
    poses: ``(B, n, 3)``, in a fixed order of operations (the same bits on every CPU;
    :func:`~comreg_core.registration.geometry.kernels.transform_points`)."""
    points = np.asarray(points, dtype=np.float64)
    cloud = points[None] if points.ndim == 2 else points
    poses = np.asarray(poses, dtype=np.float64)
    return transform_points(np.ascontiguousarray(poses[:, :3, :3]),
                            np.ascontiguousarray(poses[:, :3, 3]), np.ascontiguousarray(cloud))


def strided(points: np.ndarray, count: int) -> np.ndarray:
    """``min(count, N)`` evenly strided rows of ``(N, 3)`` points (first and last included)."""
    return points[np.linspace(0, len(points) - 1, min(count, len(points))).astype(np.int64)]


def point_to_plane_icp(source: np.ndarray, T_init: np.ndarray, match: Matcher, *,
                       iterations: int = 20, trim_fraction: float = 0.0,
                       tolerance_mm: float = 0.01, patience: int = 0) -> ICPResult:
    """Rigid point-to-plane ICP (Gauss-Newton) of a source cloud from ``B`` start poses.

    Each iteration matches every moved source point ``p_i`` to ``q_i`` with normal ``n_i``
    (``match``; pairs it leaves unmatched, ``inf`` distance, are out), leaves out the
    ``trim_fraction`` of the matched points farthest from their match, and solves
    ``min sum ((R p_i + t - q_i) . n_i)^2`` linearised about the kept points' centroid (6x6
    normal equations per start with a tiny damping, so that directions the surface does not
    constrain, e.g. sliding along a cylinder, get no update), then applies the exact rotation
    of the solved rotation vector. A start stops once an update moves no source point by more
    than ``tolerance_mm``, or when fewer than :data:`MIN_PAIRS` pairs are left; with
    ``patience``, also once its RMS has not fallen by :data:`STALL_MM` for that many
    iterations (a matcher that drops far pairs can make the pose jitter forever above the
    tolerance: on the real fibula sweep the exact polish ran 100 iterations in 4 of 6 cases).

    Args:
        source: ``(n, 3)`` mm, the points to move (or ``(B, n, 3)``, one cloud per start).
        T_init: ``(B, 4, 4)`` (or ``(4, 4)``) mm start poses.
        match: the correspondences (:data:`~comreg_core.registration.geometry.surface.Matcher`).
        iterations: most matchings per start.
        trim_fraction: share of the matched pairs left out, in [0, 1); at least
            :data:`MIN_PAIRS` are always kept.
        tolerance_mm: convergence threshold (bound on the largest point displacement).
        patience: stop a start whose RMS has not improved for this many iterations (0: off).
            Such a start counts as converged.

    Returns:
        :class:`ICPResult`.
    """
    src = np.asarray(source, dtype=np.float64)
    if src.ndim == 2:
        src = as_points(src, "source points")
    if src.shape[-2] < MIN_PAIRS or not np.isfinite(src).all():
        raise InvalidGeometryError(f"ICP needs at least {MIN_PAIRS} finite source points; it "
                                   f"got {src.shape[-2]}.", "Pass a larger cloud.")
    T = np.array(T_init, dtype=np.float64, copy=True)
    single = T.ndim == 2
    T = T[None] if single else T
    B = len(T)
    extent = np.linalg.norm(np.ptp(src, axis=-2), axis=-1)
    extent = np.broadcast_to(np.where(extent > 0, extent, 1.0), (B,))
    rmse = np.full(B, np.nan)
    done_iterations = np.zeros(B, dtype=np.int64)
    converged = np.zeros(B, dtype=bool)
    inliers = np.zeros(B)
    active = np.arange(B)  # starts still moving; converged ones are left alone
    best_rmse, stalled_for = np.full(B, np.inf), np.zeros(B, dtype=np.int64)
    for _ in range(iterations):
        moved = apply_poses(T[active], src if src.ndim == 2 else src[active])  # m n 3
        # m n 3, m n 3, m n (a tracker remembers each start's points by its row)
        q, nrm, d = match(moved, active) if isinstance(match, NearestTracker) else match(moved)
        done_iterations[active] += 1
        Ta = np.ascontiguousarray(T[active])
        step = pose_steps(np.ascontiguousarray(moved), np.ascontiguousarray(q, dtype=np.float64),
                          np.ascontiguousarray(nrm, dtype=np.float64),
                          np.ascontiguousarray(d, dtype=np.float64), float(trim_fraction), Ta)
        inliers[active] = step[:, 3]
        enough = np.isfinite(step[:, 0])  # the others stop where they are
        T[active] = Ta
        active, step = active[enough], step[enough]
        if len(active) == 0:
            break
        rmse[active] = step[:, 0]
        improved = rmse[active] < best_rmse[active] - STALL_MM
        best_rmse[active] = np.minimum(best_rmse[active], rmse[active])
        stalled_for[active] = np.where(improved, 0, stalled_for[active] + 1)
        # bound on the largest displacement of a source point by this update
        still = step[:, 1] * extent[active] + step[:, 2] >= tolerance_mm
        if patience:
            still &= stalled_for[active] < patience
        converged[active[~still]] = True
        active = active[still]
        if len(active) == 0:
            break
    if single:
        return ICPResult(T[0], rmse[0], done_iterations[0], converged[0], inliers[0])
    return ICPResult(T, rmse, done_iterations, converged, inliers)


def coarse_to_fine_icp(source: np.ndarray, T_init: np.ndarray, match: Matcher, *,
                       iterations: int = 20,
                       schedule: tuple[tuple[int, int], ...] = ((128, 30), (512, 30)),
                       margin_mm: float | None = None, trim_fraction: float = 0.0,
                       tolerance_mm: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """:func:`point_to_plane_icp` of one source cloud from ``B`` starts, coarse to fine: first
    the ``schedule`` stages ``(points, iterations)`` on evenly strided subsets of the source
    (the long way from a poor start is cheap there; stages with ``points >= n`` are skipped),
    then ``iterations`` on all ``n`` points. After each stage only the starts whose residual is
    within ``margin_mm`` of the best one go on (all when None); the others keep their pose and
    residual so far (they are far behind: this only saves time).

    Args:
        source: ``(n, 3)`` mm; ``T_init``: ``(B, 4, 4)`` mm; ``match``: the correspondences.

    Returns:
        ``(B, 4, 4)`` refined poses and ``(B,)`` RMS point-to-plane residual (mm) of the kept
        points at the last matching of each start.
    """
    src = as_points(source, "source points")
    T = np.array(T_init, dtype=np.float64, copy=True)  # B 4 4
    rmse = np.full(len(T), np.nan)
    stages = [(int(p), int(it)) for p, it in schedule if 0 < p < len(src)]
    stages.append((len(src), int(iterations)))
    going = np.ones(len(T), dtype=bool)
    for i, (points, its) in enumerate(stages):
        result = point_to_plane_icp(strided(src, points), T[going], match, iterations=its,
                                    trim_fraction=trim_fraction, tolerance_mm=tolerance_mm)
        T[going], rmse[going] = result.T, result.rmse_mm
        if margin_mm is not None and i < len(stages) - 1 and np.isfinite(rmse[going]).any():
            going &= ~(rmse > np.nanmin(rmse[going]) + margin_mm)
    return T, rmse


def refine_on_mesh(points_mm: np.ndarray, T_start: np.ndarray, match: Matcher
                   ) -> tuple[np.ndarray, float]:
    """Trimmed point-to-plane ICP of US points ``(N, 3)`` mm from the pose ``T_start``
    ``(4, 4)`` (US -> CT, mm) onto the CT mesh (``match``: e.g. ``CTSurface.matcher()``).
    It stops, as the search's polish does, once its RMS has stalled for
    :data:`~comreg_core.registration.search.config.POLISH_PATIENCE` iterations. Returns the refined
    pose ``(4, 4)`` and its RMS point-to-plane residual (mm)."""
    result = point_to_plane_icp(strided(as_points(points_mm, "US points"), MESH_REFINE_POINTS),
                                np.asarray(T_start, dtype=np.float64)[None], match,
                                iterations=MESH_REFINE_ITERATIONS,
                                trim_fraction=MESH_REFINE_TRIM, patience=POLISH_PATIENCE)
    return result.T[0], float(result.rmse_mm[0])
