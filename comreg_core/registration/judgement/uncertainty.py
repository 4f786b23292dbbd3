"""How far off a registered pose can be, in mm at the bone, from the data of this case alone.

:func:`pose_uncertainty` looks at the final fit of the US points to the CT surface:

- **local**: the point-to-plane fit's 6x6 information ``H = sum J_i J_i^T`` (pose parameters of
  :mod:`.uncertainty_kernels`) and the spread of its gradient over groups of points whose errors
  may be alike (``M = sum_b g_b g_b^T``: a frame's, or a :data:`SLAB_MM` slab's, points share
  tracking and calibration errors, so a group counts as at most :data:`GROUP_UNITS` independent
  points, not as all of its points). The
  pose covariance is the sandwich ``A^-1 (M + c P) A^-1`` with ``A = H + c P``: ``P`` the prior's
  information (the prior's tolerances when given, else the CT's length and 90 deg, which only
  bounds what the data leave free) and ``c`` the noise variance per point times the design effect
  (both robust, from this case's residuals). Where the data pin the pose this is the sandwich
  ``H^-1 M H^-1``; where they do not (along a smooth shaft) it is the prior's, i.e. unbounded.
- **target error**: the pose errors drawn from that covariance (:data:`SAMPLES` fixed normal
  draws) about the fit's own optimum (the pose refitted, :class:`.profile.ChosenBasin`: a pose
  the search left off it carries that offset) move the surface under the sweep (the registered
  points); the 95th percentile of the largest displacement is ``bound_mm``; the share within
  the clinical tolerance (4 mm, 5 deg) is ``p_local``.
- **other basins** the local matrix cannot see: a profile of the fit along the weakest slide
  and about the weakest axis (that offset held, the other five refitted,
  :mod:`.profile`), the neighbour probe (basins just beyond the tolerance) and the search's
  clinically different competitor; each pose that is another answer weighs ``exp(-dC / 2)``
  against the chosen one (``dC``: its excess cost over the chosen pose's refit, in units of
  ``c``); ``p_basin = 1 / (1 + sum of weights)``.

``p_raw = p_local * p_basin`` estimates the probability that the pose is within tolerance; a
per-CT calibration (:mod:`.calibration`) maps it to ``p_correct``.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from comreg_core.registration.geometry.icp import strided
from comreg_core.registration.judgement import uncertainty_kernels as kern
from comreg_core.registration.judgement.calibration import TOLERANCE_DEG, TOLERANCE_MM
from comreg_core.registration.judgement.directions import direction_words
from comreg_core.transforms import apply_transform, project, symmetric_eigen3

#: Thickness (mm) of the slabs (across the sweep's long axis) whose points count as one group
#: when frames are not known: a few whole frames each.
SLAB_MM = 2.5
#: Independent points a group (a frame, a slab) counts as at most: the design effect is at least
#: its points over this. 1 (every point of a frame errs alike) left right partial results CHECK
#: (on the real sweep's growing prefixes a pose slid 15 mm cost only 2-5 chi-square units) and
#: underconfident (real runs: 0.26 predicted, 0.43 observed); 4 made the real runs' p_correct
#: reliable within 0.05 without a prior, doubled the right-and-OK share of the real unions and
#: shortened the growing sweep's lag to OK from 2 of 6 starts, with no wrong result OK or at
#: p_correct >= 0.95 on any of them (bench_partial --trust, bench_growing, 2026-12-05).
GROUP_UNITS = 4.0
#: Size (mm) of the blocks a sweep's surface is counted in (its area: ``blocks * BLOCK_MM^2``).
BLOCK_MM = 5.0
#: Points used for the fit's moments (a strided subset of larger clouds).
FIT_POINTS = 3000
#: US points whose residuals give a pose's cost (a strided subset).
COST_POINTS = 600
#: Targets (registered points, a strided subset) whose displacement bounds the error.
TARGETS = 200
#: Normal draws of the pose error.
SAMPLES = 2000
#: Pairs farther apart (mm) are not on the bone; within it, residuals beyond
#: :data:`INLIER_SIGMAS` robust standard deviations are outliers.
GATE_MM = 10.0
INLIER_SIGMAS = 3.0
#: The least noise (mm) assumed per point (a noise-free simulated cloud is not exact).
NOISE_FLOOR_MM = 0.1
#: The least noise (mm) per point in the cost units ``c`` that weigh other poses: the US bone
#: surface and the CT's agree to no better than this even at the true pose (beam width,
#: segmentation), however smooth a short patch's own residuals look.
MODEL_NOISE_MM = 0.3
#: The least bound (mm) of the prior without one: the CT's length; and of its rotation (deg).
FREE_ROTATION_DEG = 90.0
#: A direction is *unbounded* when the data shrink its prior's standard deviation by less
#: than this share.
UNBOUNDED_SHARE = 0.5
#: Two-sided 95 % of a normal.
Z95 = 1.959963984540054


@dataclass(frozen=True)
class FitMoments:
    """What the final fit says about the pose (module docstring), in the kernels' parameters.

    Attributes:
        A, M, prior: ``(6, 6)`` the regularised information, the gradient's spread, the prior's
            information (times ``c``).
        c: the cost unit (mm^2): the noise variance per point (at least
            :data:`MODEL_NOISE_MM` squared) times the design effect.
        noise_mm, design_effect, groups, inliers: the robust noise, the design effect (at
            least the points per group over :data:`GROUP_UNITS`),
            the number of groups and of points used; blocks: of :data:`BLOCK_MM` the points
            touch.
        centre: ``(3,)`` CT mm; scale: mm per radian of the rotation parameters.
        targets: ``(J, 3)`` CT mm, the registered points whose displacement is bounded.
        normal_mean: ``(3,)`` the mean CT normal under the sweep (the side it was seen from).
        prior_sd: ``(6,)`` the prior's standard deviations (kernels' parameters, mm).
    """

    A: np.ndarray
    M: np.ndarray
    prior: np.ndarray
    c: float
    noise_mm: float
    design_effect: float
    groups: int
    inliers: int
    blocks: int
    centre: np.ndarray
    scale: float
    targets: np.ndarray
    normal_mean: np.ndarray
    prior_sd: np.ndarray

    @property
    def covariance(self) -> np.ndarray:
        """``(6, 6)`` the pose's covariance (mm^2 in the kernels' parameters)."""
        Ainv = kern.inverse(self.A)
        return kern.product(kern.product(Ainv, self.M + self.prior), Ainv)


@lru_cache(maxsize=1)
def standard_normals(count: int = SAMPLES) -> np.ndarray:
    """``(count, 6)`` fixed standard normal draws (seeded)."""
    return np.random.default_rng(20261205).standard_normal((count, 6))


def residuals(points_ct: np.ndarray, surface) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(closest (n, 3), normals (n, 3), signed point-to-plane residual (n,) mm)`` of CT-frame
    points on the CT surface, against the smooth surface's normals
    (:meth:`~comreg_core.registration.geometry.surface.CTSurface.smooth_normals`: a faceted
    shaft's facets would pin its roll); NaN residual where no surface point lies within
    :data:`GATE_MM`."""
    closest, faces, distance = surface.closest_faces(points_ct, GATE_MM)
    normals = surface.smooth_normals(closest, faces)
    signed = np.full(len(points_ct), np.nan)
    ok = np.isfinite(distance)
    signed[ok] = ((points_ct[ok, 0] - closest[ok, 0]) * normals[ok, 0]
                  + (points_ct[ok, 1] - closest[ok, 1]) * normals[ok, 1]) \
        + (points_ct[ok, 2] - closest[ok, 2]) * normals[ok, 2]
    return closest, normals, signed


def robust_noise(signed: np.ndarray) -> tuple[float, np.ndarray]:
    """``(sigma mm, inlier mask)`` of signed residuals (NaN: unmatched): the normal-consistent
    median absolute residual, then the inliers within :data:`INLIER_SIGMAS` of it."""
    matched = np.isfinite(signed)
    if matched.sum() < 12:
        return float("nan"), np.zeros(len(signed), dtype=bool)
    sigma = max(1.482602218505602 * float(np.median(np.abs(signed[matched]))), NOISE_FLOOR_MM)
    inlier = matched & (np.abs(np.where(matched, signed, 0.0)) <= INLIER_SIGMAS * sigma)
    return sigma, inlier


def block_groups(points: np.ndarray, size_mm: float = BLOCK_MM) -> tuple[np.ndarray, int]:
    """``(group id (n,), count)``: each point's ``size_mm`` grid cell."""
    cells = np.floor((points - points.min(axis=0)) / size_mm).astype(np.int64)
    _, group = np.unique(cells, axis=0, return_inverse=True)
    group = group.reshape(-1)
    return group, int(group.max()) + 1


def slab_groups(points: np.ndarray, size_mm: float = SLAB_MM) -> tuple[np.ndarray, int]:
    """``(group id (n,), count)``: each point's slab, ``size_mm`` thick, across the points'
    largest principal axis (a sweep's frames lie across the way the probe moved)."""
    from comreg_core.registration.geometry.surface import principal_frame

    along = project(points, principal_frame(points)[1][:, 0])
    _, group = np.unique(np.floor((along - along.min()) / size_mm).astype(np.int64),
                         return_inverse=True)
    group = group.reshape(-1)
    return group, int(group.max()) + 1


def fit_moments(points_us: np.ndarray, T_ct_us: np.ndarray, surface, *,
                free_mm: float, prior_mm: float | None = None,
                prior_deg: float | None = None, groups: np.ndarray | None = None
                ) -> FitMoments | None:
    """The :class:`FitMoments` of ``T_ct_us`` for ``(n, 3)`` US points on the CT ``surface``
    (a CTSurface). ``free_mm``: the translation bound without a prior (the CT's length);
    ``prior_mm``/``prior_deg``: the prior's tolerances (None: none); ``groups``: ``(n,)`` frame
    of each point (None: :data:`BLOCK_MM` blocks). None when under 12 points meet the CT."""
    keep = strided(np.arange(len(points_us)), FIT_POINTS)
    points = apply_transform(T_ct_us, np.asarray(points_us, dtype=np.float64)[keep])
    closest, normals, signed = residuals(points, surface)
    sigma, inlier = robust_noise(signed)
    if inlier.sum() < 12:
        return None
    pts, q, nrm = points[inlier], closest[inlier], normals[inlier]
    centre = pts.mean(axis=0)
    scale = max(float(np.sqrt(np.mean(np.sum((pts - centre) ** 2, axis=1)))), 1.0)
    if groups is None:
        group, count = slab_groups(pts)
    else:
        _, group = np.unique(np.asarray(groups)[keep][inlier], return_inverse=True)
        group, count = group.reshape(-1).astype(np.int64), int(group.max()) + 1
    H, M, _ = kern.moments(pts, q, nrm, centre, scale, group, count)
    if count > 1:
        M = M * (count / (count - 1.0))
    deff = max(1.0, float(np.trace(M)) / (sigma ** 2 * max(float(np.trace(H)), 1e-12)),
               len(pts) / count / GROUP_UNITS)  # at least: a group's points err alike
    c = max(sigma, MODEL_NOISE_MM) ** 2 * deff
    variances = _prior_variances(scale, free_mm, prior_mm, prior_deg)
    prior = np.diag(c / variances)
    return FitMoments(A=H + prior, M=M, prior=c * prior, c=c, noise_mm=sigma,
                      design_effect=deff, groups=count, inliers=int(inlier.sum()),
                      blocks=block_groups(pts)[1],
                      centre=centre, scale=scale, targets=strided(pts, TARGETS),
                      normal_mean=nrm.mean(axis=0), prior_sd=np.sqrt(variances))


def _prior_variances(scale: float, free_mm: float, prior_mm: float | None,
                     prior_deg: float | None) -> np.ndarray:
    """``(6,)`` the prior's variances in the kernels' parameters: its tolerance as 2 standard
    deviations (free: ``free_mm`` and :data:`FREE_ROTATION_DEG`)."""
    mm = free_mm if prior_mm is None else min(free_mm, prior_mm / 2.0)
    deg = FREE_ROTATION_DEG if prior_deg is None else min(FREE_ROTATION_DEG, prior_deg / 2.0)
    rotation = np.radians(deg) * scale
    return np.array([rotation ** 2] * 3 + [mm ** 2] * 3)


def target_error(fit: FitMoments, covariance: np.ndarray, samples: int = SAMPLES,
                 offset: np.ndarray | None = None) -> tuple[float, float]:
    """``(95 % bound mm of the largest target displacement, share of draws within 4 mm and
    5 deg)`` of pose errors with this ``(6, 6)`` covariance about ``offset`` ``(6,)`` (the
    kernels' parameters of the fit's optimum from the pose judged; None: zero)."""
    centre = np.zeros(6) if offset is None else np.asarray(offset, dtype=np.float64)
    largest, angle = kern.target_errors(kern.cholesky(covariance), standard_normals()[:samples],
                                        fit.targets, fit.centre, fit.scale, centre)
    within = (largest <= TOLERANCE_MM) & (angle <= TOLERANCE_DEG)
    return float(np.percentile(largest, 95)), float(np.mean(within))


def weakest_directions(fit: FitMoments, covariance: np.ndarray, long_axis: np.ndarray
                       ) -> list[dict[str, Any]]:
    """The weakest slide and the weakest rotation axis of the pose: ``[{"kind": "slide" |
    "rotation", "words", "axis_ct" (3,), "bound_mm" | "bound_deg", "unbounded"}]``, each bound
    the 95 % two-sided one of that direction's marginal."""
    out = []
    for kind, block, unit in (("slide", slice(3, 6), 1.0),
                              ("rotation", slice(0, 3), 180.0 / np.pi / fit.scale)):
        values, vectors = symmetric_eigen3(covariance[block, block])
        sd = float(np.sqrt(max(values[0], 0.0)))
        axis = vectors[:, 0]
        item = {"kind": kind, "words": direction_words(kind, axis, long_axis),
                "axis_ct": [float(x) for x in axis],
                "unbounded": bool(sd > UNBOUNDED_SHARE * fit.prior_sd[block][0])}
        item["bound_mm" if kind == "slide" else "bound_deg"] = Z95 * sd * unit
        out.append(item)
    return out


def basin_weight(delta_cost: float) -> float:
    """The weight ``exp(-dC / 2)`` of a pose whose cost exceeds the chosen one's by ``dC``
    (units of ``c``; a negative excess counts as a tie)."""
    return float(np.exp(-0.5 * max(float(delta_cost), 0.0)))


def truncated_cost(points_us: np.ndarray, T_ct_us: np.ndarray, surface, fit: FitMoments):
    """The fit's cost of a pose ``(4, 4)`` (a float), or of each of ``(K, 4, 4)`` poses (``(K,)``,
    their closest points found in one query): the mean over (a strided subset of
    :data:`COST_POINTS`) US points of the squared residual, each capped at
    ``(INLIER_SIGMAS * noise)^2`` (unmatched: the cap), times the :data:`FIT_POINTS` subset's
    size, over ``c``: the units in which a cost difference is a chi-square."""
    points = np.asarray(points_us, dtype=np.float64)
    counted = min(len(points), FIT_POINTS)
    sub = strided(points, COST_POINTS)
    poses = np.asarray(T_ct_us, dtype=np.float64)
    stack = poses.reshape(-1, 4, 4)
    _, _, signed = residuals(np.concatenate([apply_transform(T, sub) for T in stack]), surface)
    cap = (INLIER_SIGMAS * fit.noise_mm) ** 2
    squared = np.where(np.isfinite(signed), np.minimum(np.nan_to_num(signed) ** 2, cap), cap)
    costs = np.array([float(np.mean(row)) * counted / fit.c
                      for row in squared.reshape(len(stack), len(sub))])
    return float(costs[0]) if poses.ndim == 2 else costs


#: Each CT surface's long axis (:func:`long_axis_of`), found once.
_LONG_AXES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def long_axis_of(surface) -> np.ndarray:
    """``(3,)`` the CT's long axis (the principal axis of its vertices; found once per
    surface, read-only)."""
    from comreg_core.registration.geometry.surface import principal_frame

    if surface not in _LONG_AXES:
        axis = np.array(principal_frame(surface.vertices)[1][:, 0])
        axis.flags.writeable = False
        _LONG_AXES[surface] = axis
    return _LONG_AXES[surface]


def extent_along(points: np.ndarray, axis: np.ndarray) -> tuple[float, float]:
    """``(min, max)`` mm of ``(n, 3)`` points along a unit axis."""
    along = project(points, axis)
    return float(along.min()), float(along.max())
