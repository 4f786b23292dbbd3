"""Test-time pose hypotheses: no flips, no spins about the shaft, and a confidence flag.

A partial US sweep of a long, near-symmetric bone (fibula, tibia or femur shaft) fits several
poses: flipped end to end, turned about the shaft, or the one the network found. The learned
coarse pose only has to land in ICP's basin; when it lands in the basin of a symmetric
alternative, plain ICP converges there and the result is a flip. This module tries the
alternatives at test time, with no extra training data:

1. **Start poses** (all ``T_ct_us``, mm). Bases: ``network`` (the network's pose after its
   ICP), ``coarse`` (its coarse pose before the ICP, with ``include_coarse``) and ``pca`` (with
   ``principal_axes_solve`` and a completion: the full-to-full solve of the completed shape
   against the CT by principal axes; the completion is a whole bone, so this is well posed up
   to the axes' signs, which the flips below cover). Around each base ``T_b``: ``G @ T_b`` with
   ``G`` a rigid motion of the *CT frame* about the principal axes of the completed bone placed
   by ``T_b`` (centroid ``c``, axes ``a0`` = long, ``a1``, ``a2``; the CT's own frame without a
   completion): rotations about ``a0`` by ``360 k / shaft_rotations`` deg (``+rot45``, ...),
   with ``axis_flips`` each also flipped end to end (180 deg about ``a1``, ``+flip``), and
   each of these slid along ``a0`` by multiples of ``slide_step_mm`` over +-``slide_range_mm``
   (default half the CT's length; ``+slide-16``, ...), for the slides along the shaft ICP
   cannot undo. Names read like ``network+flip+rot90+slide24``. With the defaults that is
   3 bases x 16 rotations x ~50 slides, about 2,400 starts on a fibula.

2. **Screening** (:func:`screen_starts`): all starts at once get a quick point-to-plane ICP
   (``screen_iterations`` on ``screen_points`` US points, correspondences read from a
   closest-point grid of the CT, :meth:`HypothesisTarget.nearest_approx`) and a quick score;
   the ``refine_top`` best distinct ones go on, the network's own pose always among them.
   Scoring *after* a few ICP steps matters: before them the right basin's starts rank in the
   hundreds, after them first.

3. **Refinement**: the kept starts are refined together, in one batch, of a subset of the
   US cloud (``icp_points``, uniform random, ``icp_subset``) against a dense cloud of the CT
   surface (``target_points`` area-uniform samples with their triangles' normals). Not an FPS
   subset: farthest-point sampling picks isolated false echoes first (on simulated fibula
   sweeps ~3 % of the points, 10-15 % of an FPS subset, more than ``icp_trim`` leaves out,
   enough to pull the ICP 20 mm off the truth). By default (``icp_mode="plane"``) with the
   batched point-to-plane ICP :func:`point_to_plane_icp_batch`, coarse to fine: the
   ``icp_schedule`` stages on evenly strided subsets (128, then 512 US points, 30 iterations
   each), then ``icp_iterations`` on all ``icp_points``; after each stage only the hypotheses
   whose residual is within ``icp_margin_mm`` of the best go on. Point-to-point
   :func:`~comreg_core.model.diff_icp.differentiable_icp` (``"hard"`` / ``"soft"``, kept as
   options) crawls along a shaft, where the surface slides under the points
   (``tests/benchmarks/bench_hypotheses.py``).

4. **Score** (mm, lower is better): the trimmed mean distance of the hypothesis' registered US
   subset to the CT surface: the mean of the smallest ``1 - score_trim`` share of the
   point-to-surface distances, each taken to the tangent plane of the nearest dense CT point
   (KD-tree, pykdtree; :meth:`HypothesisTarget.surface_distances`: unlike the plain
   nearest-point distance it has almost no bias from the sample spacing, so a perfect fit
   scores near 0 and the gaps between poses are not blurred). Trimming keeps false bone echoes
   and parts of the sweep the CT does not explain from dominating.

5. **Polish** (``polish``, needs the mesh): the best-scoring pose and the distinct poses *tied*
   with it (confidence below ``min_confidence``, step 6; at most ``polish_top``) get a last
   point-to-plane ICP of the same US subset against the *exact* closest points of the CT mesh
   and their triangles' normals (:func:`comreg_core.surface_icp.point_to_plane_icp`, the
   ``icp-gt`` baseline's ICP), pairs farther apart than ``polish_max_distance_mm`` (2 mm) left
   out, and are re-scored with exact distances to the mesh. With several such poses each first
   gets a quick polish (:data:`QUICK_POLISH_POINTS` points, :data:`QUICK_POLISH_ITERATIONS`),
   and the chosen one is then polished in full (at most ``polish_iterations``). Why: the
   refinement matches to the nearest of the dense CT samples and trims a share of the points,
   so false echoes a few mm off the bone still pull on it; on simulated fibula sweeps it stopped
   2-3 deg or 2-11 mm off in 5 of 100 trials that the gated exact polish brought to within
   0.1 deg / 0.1 mm, and poses that the refinement scored alike (a flip at 0.19 mm, the truth's
   basin at 0.17 mm) separate once polished (0.2 mm vs 0.006 mm). Median cost ~0.05 s, ~0.4 s
   with ties. Built from a bare cloud, the target has no :attr:`~HypothesisTarget.matcher` and
   the polish is skipped.

6. **Choice and confidence**: the best score wins (exact ties go to the network's own pose).
   Two poses are *distinct* when rotated apart by more than ``distinct_deg`` or placing the US
   centroid more than ``distinct_mm`` apart. ``confidence(a over b) = max(score_b - score_a,
   0) / max(score_b, score_floor_mm)`` in [0, 1] (``score_floor_mm``, 0.05 mm: differences
   between near-perfect fits are noise, not evidence). Poses over which the best has a
   confidence below ``min_confidence`` are *tied* with it; with ``tie_break="network"`` the
   tied pose rotated least from the network's pose sets the rotation (among the tied poses
   rotated like it, the best score wins, so slides are still decided by the score): a flip or
   a spin the geometry cannot tell apart is decided by the learned prior. The *runner-up* is
   the best-scoring pose distinct from the chosen one (converged duplicates never count);
   ``score_gap_mm = score(runner-up) - score(chosen)``; ``confidence`` = that of the chosen
   pose over the runner-up (1 without a runner-up); ``ambiguous = confidence <
   min_confidence``: another, clearly different pose explains the US points (nearly) as well,
   e.g. a sweep of a featureless stretch of shaft. With the polish, only the polished poses
   can be chosen (the others' scores are not exact, and they were not tied anyway); with
   several, the choice is made on their quick-polish scores and the chosen one is then polished
   in full (its final score is the one reported).

7. **Second round** (``retry_ambiguous``): an ambiguous result may mean only that no start
   landed in the right basin (from poses the network was not trained for, its bases can be
   20-30 deg off and the grid's 45 deg spacing too coarse). Then steps 1-3 run again on the
   grid interleaved with the first (rotations and slides shifted by half a step: ``+rot22.5``,
   ``+slide4``, ...; the bases themselves are not repeated), and steps 5-6 choose among the
   hypotheses of both rounds (poses polished in the first round are not polished again).
   ``starts_tried`` counts both rounds. Costs about one more search, only for ambiguous
   results.

Use it standalone (no network needed)::

    target = HypothesisTarget.from_mesh("fibula.stl")
    result = search_hypotheses(us_points, T_start, target)   # mm in, mm out
    result.T_ct_us, result.chosen, result.confidence, result.ambiguous

:class:`comreg_core.inference.Registrar` runs it after the network's ICP unless it is turned off
(``hypotheses=False``; ``comreg register --no-hypotheses``), which reproduces the paper's plain
pipeline exactly; ``comreg evaluate --method comreg --method comreg-plain`` compares both in one
run. The stage repairs symmetric confusions of a coarse pose that is otherwise near the truth;
for arbitrary starting orientations the network itself must be trained for them (training
config ``data.pose: full``, the full-rotation sampler; evaluate with ``--perturbation full``).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import torch

from comreg_core.config import require
from comreg_core.errors import InvalidGeometryError
from comreg_core.evaluation.metrics import rotation_error_deg
from comreg_core.model.diff_icp import differentiable_icp
from comreg_core.model.normalization import Normalization
from comreg_core.model.ops import subsample
from comreg_core.surface_icp import SurfaceMatcher, point_to_plane_icp
from comreg_core.transforms import apply_transform, as_points, check_rigid, orthonormalize

#: The polish stops once an update moves no US point by more than this (mm).
POLISH_TOLERANCE_MM = 0.01
#: US points and most iterations of the quick polish that compares poses tied with the best.
QUICK_POLISH_POINTS = 512
QUICK_POLISH_ITERATIONS = 30


@dataclass(frozen=True)
class HypothesisConfig:
    """Settings of the hypotheses stage (module docstring).

    Attributes:
        enabled: run the stage at all (False = the paper's plain pipeline).
        shaft_rotations: rotations about the long axis per base, ``360 / shaft_rotations``
            deg apart, the base included (1 = only the base).
        axis_flips: also flip each of them end to end (180 deg about a short axis).
        include_coarse: the network's coarse pose is a base too (when one is given).
        principal_axes_solve: the principal-axes solve of the completion vs the CT is a base
            too (needs a completion).
        slide_step_mm: also try each rotation hypothesis slid along its long axis in steps of
            this (mm; suffix ``+slide16`` etc.; 0 = no slides).
        slide_range_mm: the largest slide (mm); None = half the CT's length.
        screen_points, screen_iterations, screen_score_points: the screening of all starts
            (:func:`screen_starts`): US points and iterations of its quick ICP, US points of
            its quick score.
        refine_top: starts refined by the full ICP and scored (the network's own pose and
            the best screened distinct others); 0 = all of them, unscreened.
        icp_points: US points in the hypotheses' ICP and score.
        icp_subset: how those points are picked: ``"random"`` (a seeded uniform subset, in
            sweep order: it keeps the sweep's own share of false echoes) or ``"fps"``
            (farthest-point sampling, as the network's input: even coverage, but it picks
            isolated false echoes first; on simulated fibula sweeps it raised their share
            from ~3 % of the sweep to 10-15 % of the subset, more than ``icp_trim`` drops).
        target_points: area-uniform CT surface samples: the ICP target and the score's cloud.
        icp_mode: ``"plane"``: batched point-to-plane ICP against the CT samples' normals
            (:func:`point_to_plane_icp_batch`, the default: it converges along shafts);
            ``"hard"`` / ``"soft"``: point-to-point
            :func:`~comreg_core.model.diff_icp.differentiable_icp` (nearest neighbour / soft
            correspondences) against the same CT cloud, kept for comparison.
        icp_iterations: ``"plane"``: iterations of its last stage, on all ``icp_points``;
            ``"hard"`` / ``"soft"``: all iterations.
        icp_schedule: ``"plane"``: the coarse stages before, ``(US points, iterations)`` each
            (:func:`point_to_plane_icp_batch`).
        icp_margin_mm: ``"plane"``: after each stage only the hypotheses whose residual
            (trimmed RMS, mm) is within this of the best go on (the others are far behind;
            this only saves time).
        icp_sigma: softness of ``"soft"`` correspondences, normalised units (CT extent = 1).
        icp_neighbors: candidates of a soft correspondence.
        icp_trim: share of the worst residuals left out of each ICP step.
        score_trim: share of the largest distances left out of the score.
        tie_break: among the tied poses (scores within ``1 / (1 - min_confidence)`` of the
            best), ``"network"``
            keeps the best-scoring of those rotated like the one rotated least from the
            network's pose (the learned prior decides a flip or spin the geometry cannot; a
            slide is still decided by the score), ``"score"`` the best score.
        distinct_deg, distinct_mm: two refined poses are different poses when their rotations
            differ by more than ``distinct_deg`` or they place the US centroid more than
            ``distinct_mm`` apart; otherwise the later one is a duplicate.
        retry_ambiguous: when the result is ambiguous, search again from the starts
            interleaved with the first grid (rotations and slides shifted by half a step) and
            choose among both rounds' hypotheses (step 7).
        polish: polish the best pose and those tied with it by point-to-plane ICP to the
            exact closest points of the CT mesh and re-score them (step 5 of the module
            docstring; needs the mesh, skipped without one).
        polish_top: at most this many poses are polished.
        polish_max_distance_mm: pairs farther apart than this are left out of the polish.
        polish_iterations: most iterations of a polish.
        score_floor_mm: score differences are measured relative to at least this (mm) in the
            confidence: below it they are noise (step 6).
        min_confidence: a result is ambiguous when its confidence is below this (a different
            pose scores within ``1 / (1 - min_confidence)`` times the chosen one's score, or
            within ``min_confidence * score_floor_mm`` of it).
    """

    enabled: bool = True
    shaft_rotations: int = 8
    axis_flips: bool = True
    include_coarse: bool = True
    principal_axes_solve: bool = True
    slide_step_mm: float = 8.0
    slide_range_mm: float | None = None
    screen_points: int = 64
    screen_iterations: int = 20
    screen_score_points: int = 128
    refine_top: int = 12
    icp_points: int = 2048
    icp_subset: Literal["random", "fps"] = "random"
    target_points: int = 20_000
    icp_mode: Literal["plane", "hard", "soft"] = "plane"
    icp_iterations: int = 20
    icp_schedule: tuple[tuple[int, int], ...] = ((128, 30), (512, 30))
    icp_margin_mm: float = 1.0
    icp_sigma: float = 5e-3
    icp_neighbors: int = 16
    icp_trim: float = 0.1
    score_trim: float = 0.2
    tie_break: Literal["network", "score"] = "network"
    distinct_deg: float = 10.0
    distinct_mm: float = 5.0
    retry_ambiguous: bool = True
    polish: bool = True
    polish_top: int = 4
    polish_max_distance_mm: float = 2.0
    polish_iterations: int = 100
    score_floor_mm: float = 0.05
    min_confidence: float = 0.3

    def __post_init__(self) -> None:
        require(isinstance(self.enabled, bool), "hypotheses.enabled", "must be true or false")
        require(self.shaft_rotations >= 1, "hypotheses.shaft_rotations", "must be at least 1")
        require(self.shaft_rotations <= 36, "hypotheses.shaft_rotations",
                "must be at most 36 (10 deg apart)")
        require(self.slide_step_mm >= 0, "hypotheses.slide_step_mm", "must be 0 (off) or more")
        require(self.slide_range_mm is None or self.slide_range_mm >= 0,
                "hypotheses.slide_range_mm", "must be 0 or more (or null: half the CT length)")
        require(self.screen_points >= 6, "hypotheses.screen_points", "must be at least 6")
        require(self.screen_iterations >= 0, "hypotheses.screen_iterations", "must be 0 or more")
        require(self.screen_score_points >= 3, "hypotheses.screen_score_points",
                "must be at least 3")
        require(self.refine_top >= 0, "hypotheses.refine_top", "must be 0 (all) or more")
        require(self.icp_points >= 3, "hypotheses.icp_points", "must be at least 3")
        require(self.icp_subset in ("random", "fps"), "hypotheses.icp_subset",
                "must be 'random' or 'fps'")
        require(self.target_points >= 100, "hypotheses.target_points", "must be at least 100")
        require(self.icp_iterations >= 0, "hypotheses.icp_iterations", "must be 0 or more")
        require(all(p >= 6 and it >= 0 for p, it in self.icp_schedule),
                "hypotheses.icp_schedule", "needs at least 6 points and 0 or more iterations "
                "per stage")
        require(self.icp_margin_mm > 0, "hypotheses.icp_margin_mm", "must be positive")
        require(self.icp_mode in ("plane", "hard", "soft"), "hypotheses.icp_mode",
                "must be 'plane', 'hard' or 'soft'")
        require(self.icp_sigma > 0, "hypotheses.icp_sigma", "must be positive")
        require(self.icp_neighbors >= 1, "hypotheses.icp_neighbors", "must be at least 1")
        require(0.0 <= self.icp_trim < 1.0, "hypotheses.icp_trim", "must be in [0, 1)")
        require(0.0 <= self.score_trim < 1.0, "hypotheses.score_trim", "must be in [0, 1)")
        require(self.tie_break in ("network", "score"), "hypotheses.tie_break",
                "must be 'network' or 'score'")
        require(self.distinct_deg > 0, "hypotheses.distinct_deg", "must be positive")
        require(self.distinct_mm > 0, "hypotheses.distinct_mm", "must be positive")
        require(isinstance(self.polish, bool), "hypotheses.polish", "must be true or false")
        require(isinstance(self.retry_ambiguous, bool), "hypotheses.retry_ambiguous",
                "must be true or false")
        require(self.polish_top >= 1, "hypotheses.polish_top", "must be at least 1")
        require(self.score_floor_mm > 0, "hypotheses.score_floor_mm", "must be positive (mm)")
        require(self.polish_max_distance_mm > 0, "hypotheses.polish_max_distance_mm",
                "must be positive (mm)")
        require(self.polish_iterations >= 1, "hypotheses.polish_iterations",
                "must be at least 1")
        require(0.0 <= self.min_confidence < 1.0, "hypotheses.min_confidence",
                "must be in [0, 1)")


def as_hypothesis_config(value) -> HypothesisConfig:
    """``None``/``True`` -> the defaults, ``False`` -> turned off, a :class:`HypothesisConfig`
    or a mapping of its keys -> that config."""
    if value is None or value is True:
        return HypothesisConfig()
    if value is False:
        return HypothesisConfig(enabled=False)
    if isinstance(value, HypothesisConfig):
        return value
    if isinstance(value, dict):
        from comreg_core.config import from_dict

        return from_dict(HypothesisConfig, value, "hypotheses")
    from comreg_core.config import ConfigError

    raise ConfigError(f"Cannot use a {type(value).__name__} as the hypotheses setting.",
                      "Pass True, False, a HypothesisConfig or a mapping of its keys.")


def principal_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid ``(3,)`` and principal axes ``(3, 3)`` (columns by decreasing variance,
    right-handed) of ``(N, 3)`` points."""
    pts = as_points(points, "points")
    centre = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
    axes = vt.T.copy()
    axes[:, 2] = np.cross(axes[:, 0], axes[:, 1])
    return centre, axes


def rotation_about(centre: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """``(4, 4)`` rotation by ``angle`` (rad) about the line through ``centre`` along ``axis``."""
    from scipy.spatial.transform import Rotation

    axis = np.asarray(axis, dtype=np.float64)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre
    return T


def us_subset(points: np.ndarray, count: int, method: str = "random") -> np.ndarray:
    """``min(count, N)`` of the ``(N, 3)`` US points (mm) for the hypotheses' ICP and score:
    ``"random"``, a uniform subset (seed 0: the same points every run) kept in sweep order, or
    ``"fps"``, the farthest-point-sampling subset (:func:`comreg_core.model.ops.subsample`)."""
    if len(points) <= count:
        return points
    if method == "fps":
        cloud = torch.from_numpy(points).float()[None]  # 1 N 3
        return subsample(cloud, count, 0)[0].double().numpy()
    return points[np.sort(np.random.default_rng(0).choice(len(points), count, replace=False))]


def _apply_batch(poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(n, 3)`` points moved by each of ``(B, 4, 4)`` poses: ``(B, n, 3)``."""
    return points @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3]


def _strided(points: np.ndarray, count: int) -> np.ndarray:
    """``min(count, N)`` evenly strided rows of ``(N, 3)`` points (first and last included)."""
    return points[np.linspace(0, len(points) - 1, min(count, len(points))).astype(np.int64)]


def _trimmed_mean(distances: np.ndarray, trim: float) -> np.ndarray:
    """``(B,)`` mean of the smallest ``1 - trim`` share (at least one) of each row of ``(B, n)``
    distances: the hypotheses' score."""
    n = distances.shape[1]
    return np.sort(distances, axis=1)[:, :max(1, n - int(trim * n))].mean(axis=1)


def _same_pose(poses: np.ndarray, centroids: np.ndarray, i: int, others: np.ndarray,
               config: HypothesisConfig, *, rotation_only: bool = False) -> np.ndarray:
    """Which of the poses ``others`` (indices) are the same pose as pose ``i``: rotated apart by
    at most ``distinct_deg`` and, unless ``rotation_only``, placing the US centroid within
    ``distinct_mm``. ``poses`` ``(B, 4, 4)``, ``centroids`` ``(B, 3)`` mm (the US centroid
    placed by each pose); returns ``(len(others),)`` bool."""
    cos = (np.einsum("kij,ij->k", poses[others, :3, :3], poses[i, :3, :3]) - 1.0) / 2.0
    same = cos >= math.cos(math.radians(config.distinct_deg))
    if not rotation_only:
        same &= np.linalg.norm(centroids[others] - centroids[i], axis=1) <= config.distinct_mm
    return same


class HypothesisTarget:
    """The CT side of the hypotheses stage, prepared once per CT: a dense cloud of the CT
    surface (ICP target and score reference, with its KD-tree), the normalisation of the ICP,
    and the CT's principal frame.

    Args:
        points: ``(M, 3)`` mm, dense points on the CT bone surface (e.g. area-uniform samples).
        normalization: the network's normalisation (default: from ``points``, the CT's
            bounding-box centre and largest extent).
        device: torch device of the ICP.
        normals: ``(M, 3)`` unit normals of ``points`` (default: estimated from the cloud).
        surface: the CT mesh (:class:`~comreg_core.evaluation.metrics.SurfaceReference`) for
            the polish (:attr:`matcher`); None = no polish.
    """

    def __init__(self, points: np.ndarray, normalization: Normalization | None = None,
                 device: str | torch.device = "cpu", *, normals: np.ndarray | None = None,
                 surface=None):
        from pykdtree.kdtree import KDTree

        self.points = as_points(points, "CT points")
        if len(self.points) < 10:
            raise InvalidGeometryError("The CT cloud of the hypotheses has fewer than 10 points.",
                                       "Pass the CT bone surface.")
        self.normalization = normalization or Normalization.from_ct(self.points)
        self.device = torch.device(device)
        self.model_points = torch.from_numpy(
            self.normalization.points_to_model(self.points)).float()[None].to(self.device)
        self.tree = KDTree(np.ascontiguousarray(self.points))
        self.normals = (estimate_normals(self.points, self.tree) if normals is None
                        else as_points(normals, "CT normals"))
        if self.normals.shape != self.points.shape:
            raise InvalidGeometryError("The CT normals and points differ in number.",
                                       "Pass one normal per CT point.")
        self.centre, self.axes = principal_frame(self.points)
        self.surface = surface

    #: Dense CT surface samples of the polish's :class:`~comreg_core.surface_icp.SurfaceMatcher`.
    MATCHER_SAMPLES = 200_000

    @functools.cached_property
    def matcher(self) -> SurfaceMatcher | None:
        """Exact closest points on the CT mesh for the polish (built on first use, ~0.2 s on a
        fibula), None without a mesh."""
        return None if self.surface is None else SurfaceMatcher(self.surface,
                                                                self.MATCHER_SAMPLES)

    @classmethod
    def from_mesh(cls, mesh, n_points: int = HypothesisConfig.target_points, *,
                  normalization: Normalization | None = None,
                  device: str | torch.device = "cpu") -> HypothesisTarget:
        """From a CT mesh (anything :class:`~comreg_core.evaluation.metrics.SurfaceReference`
        takes: a path, SurfaceMesh, trimesh, ``(V, F)``) sampled at ``n_points`` area-uniform
        points (fixed seed). The normalisation defaults to the mesh's bounding box."""
        from comreg_core.evaluation.metrics import SurfaceReference

        surface = mesh if isinstance(mesh, SurfaceReference) else SurfaceReference(mesh)
        if normalization is None:
            normalization = Normalization.from_ct(surface.vertices)
        points, normals = surface.samples(int(n_points))
        return cls(points, normalization, device, normals=normals, surface=surface)

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (mm) and indices of the nearest CT points of ``(..., 3)`` points."""
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        d, idx = self.tree.query(pts, k=1)
        shape = np.shape(points)[:-1]
        return np.asarray(d, dtype=np.float64).reshape(shape), idx.astype(np.int64).reshape(shape)

    def nearest_approx(self, points: np.ndarray) -> np.ndarray:
        """Indices of (nearly) the nearest CT points of ``(..., 3)`` points, read from a
        closest-point grid over the CT's bounding box plus :attr:`GRID_MARGIN_MM` (built on
        first use, :attr:`GRID_VOXELS` voxels at most): the nearest CT point of the voxel's
        centre, points outside the grid clamped onto it. Off by up to about half a voxel
        diagonal (~2.5 mm on a fibula): for screening many poses, not for the final fit."""
        origin, spacing, grid = self.closest_point_grid
        pts = np.asarray(points, dtype=np.float64)
        ijk = np.rint((pts - origin) / spacing).astype(np.int64)
        ijk = np.clip(ijk, 0, np.array(grid.shape) - 1)
        return grid[ijk[..., 0], ijk[..., 1], ijk[..., 2]]

    GRID_MARGIN_MM = 30.0
    GRID_VOXELS = 400_000

    @functools.cached_property
    def closest_point_grid(self) -> tuple[np.ndarray, float, np.ndarray]:
        """``(origin (3,) mm, spacing mm, (I, J, K) int32 indices of the nearest CT point of
        each voxel centre)`` (:meth:`nearest_approx`)."""
        low = self.points.min(axis=0) - self.GRID_MARGIN_MM
        size = self.points.max(axis=0) + self.GRID_MARGIN_MM - low
        spacing = max(1.0, float(np.cbrt(np.prod(size) / self.GRID_VOXELS)))
        shape = np.ceil(size / spacing).astype(np.int64) + 1
        axes = [low[i] + spacing * np.arange(shape[i]) for i in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        _, idx = self.tree.query(np.ascontiguousarray(centres), k=1)
        return low, spacing, idx.astype(np.int32).reshape(tuple(shape))

    def surface_distances(self, points: np.ndarray, approximate: bool = False) -> np.ndarray:
        """Distances (mm) of ``(..., 3)`` points to the CT surface, approximated by the tangent
        plane at the nearest CT point: ``|(p - q) . n_q|``. On a smooth surface this is the
        point-to-surface distance without most of the sampling bias of the plain
        nearest-neighbour distance (about half the sample spacing, ~0.4 mm at 20,000 samples
        of a fibula); it never exceeds the nearest-neighbour distance. ``approximate``: with
        :meth:`nearest_approx`'s CT points (fast, for screening)."""
        pts = np.asarray(points, dtype=np.float64)
        idx = self.nearest_approx(pts) if approximate else self.nearest(pts)[1]
        return np.abs(np.einsum("...i,...i->...", pts - self.points[idx], self.normals[idx]))


def estimate_normals(points: np.ndarray, tree=None, k: int = 12) -> np.ndarray:
    """Unit normals ``(N, 3)`` of a surface cloud by local PCA (the least-variance direction of
    each point's ``k`` nearest neighbours; the sign is arbitrary, which point-to-plane ICP does
    not mind)."""
    from pykdtree.kdtree import KDTree

    pts = as_points(points, "points")
    tree = tree or KDTree(np.ascontiguousarray(pts))
    _, idx = tree.query(np.ascontiguousarray(pts), k=min(k, len(pts)))
    nb = pts[idx.astype(np.int64)]  # N k 3
    nb = nb - nb.mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))  # ascending eigenvalues
    return vecs[:, :, 0]


def point_to_plane_icp_batch(source: np.ndarray, T_init: np.ndarray, target: HypothesisTarget,
                             *, iterations: int = 20,
                             schedule: tuple[tuple[int, int], ...] = ((128, 30), (512, 30)),
                             margin_mm: float | None = None, trim_fraction: float = 0.0,
                             tolerance_mm: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Batched rigid point-to-plane ICP (Gauss-Newton) of one source cloud from ``B`` starts.

    Each iteration matches every moved source point ``p_i`` to its nearest CT point ``q_i``
    (KD-tree) with that point's normal ``n_i``, leaves out the ``trim_fraction`` of the points
    farthest from their match, and solves ``min sum ((R p_i + t - q_i) . n_i)^2`` linearised
    about the matched points' centroid (6x6 normal equations per start, with a tiny damping so
    that directions the surface does not constrain, e.g. sliding along a cylinder, get no
    update), then applies the exact rotation of the solved rotation vector. A start stops once
    its update moves no source point by more than ``tolerance_mm``.

    Coarse to fine: first the ``schedule`` stages ``(points, iterations)`` on evenly strided
    subsets of the source (the long way from a poor start is cheap there), then ``iterations``
    on all points. After each stage only the starts whose residual is within ``margin_mm`` of
    the best one go on (all when None); the others keep their pose and residual so far (they
    are far behind: this only saves time).

    No gradient: this is the hypotheses' refinement, not a network layer (the network's ICP is
    :func:`~comreg_core.model.diff_icp.differentiable_icp`). Point-to-plane converges along a
    shaft, where the surface slides under the points, in a few iterations; point-to-point ICP
    crawls there (measured in ``tests/benchmarks/bench_hypotheses.py``).

    Args:
        source: ``(n, 3)`` mm, US points (US frame).
        T_init: ``(B, 4, 4)`` mm, start poses ``T_ct_us``.
        target: the CT side (points, normals, KD-tree).
        iterations: iterations of the last stage, on all ``n`` points.
        schedule: the stages before it; stages with ``points >= n`` are skipped.
        margin_mm: which starts go on after a stage (see above).
        trim_fraction: in [0, 1).
        tolerance_mm: convergence threshold (largest point displacement of an update).

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
        sub = _strided(src, points)
        T[going], rmse[going] = _point_to_plane(sub, T[going], target, its, trim_fraction,
                                                tolerance_mm)
        if margin_mm is not None and i < len(stages) - 1 and np.isfinite(rmse[going]).any():
            going &= ~(rmse > np.nanmin(rmse[going]) + margin_mm)
    return T, rmse


def _point_to_plane(src: np.ndarray, T: np.ndarray, target: HypothesisTarget, iterations: int,
                    trim_fraction: float, tolerance_mm: float, approximate: bool = False
                    ) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    T = T.copy()
    B, n = len(T), len(src)
    keep = max(6, n - int(trim_fraction * n))
    extent = float(np.linalg.norm(np.ptp(src, axis=0))) or 1.0
    rmse = np.full(B, np.nan)
    active = np.arange(B)  # starts still moving; converged ones are left alone
    for _ in range(iterations):
        Ta = T[active]
        m = len(active)
        moved = _apply_batch(Ta, src)  # m n 3
        d, idx = (None, target.nearest_approx(moved)) if approximate else \
            target.nearest(moved)  # m n
        q, nrm = target.points[idx], target.normals[idx]  # m n 3
        if d is None:
            d = np.linalg.norm(moved - q, axis=2)
        if keep < n:
            limit = np.partition(d, keep - 1, axis=1)[:, keep - 1:keep]  # m 1
            w = (d <= limit).astype(np.float64)  # m n
        else:
            w = np.ones((m, n))
        r = np.einsum("bni,bni->bn", moved - q, nrm)  # m n, signed distance to the plane
        rmse[active] = np.sqrt((w * r * r).sum(1) / w.sum(1))
        c = (w[..., None] * moved).sum(1) / w.sum(1)[:, None]  # m 3
        A = np.concatenate([np.cross(moved - c[:, None], nrm), nrm], axis=2)  # m n 6
        Aw = A * w[..., None]
        H = Aw.transpose(0, 2, 1) @ A  # m 6 6
        g = (Aw.transpose(0, 2, 1) @ r[..., None])[..., 0]  # m 6
        damp = (1e-6 * np.trace(H, axis1=1, axis2=2)[:, None, None] + 1e-12) * np.eye(6)
        x = np.linalg.solve(H + damp, -g[..., None])[..., 0]  # m 6
        step = np.tile(np.eye(4), (m, 1, 1))
        step[:, :3, :3] = Rotation.from_rotvec(x[:, :3]).as_matrix()
        step[:, :3, 3] = c - np.einsum("bij,bj->bi", step[:, :3, :3], c) + x[:, 3:]
        T[active] = step @ Ta
        # bound on the largest displacement of a source point by this update
        moving = np.linalg.norm(x[:, :3], axis=1) * extent + np.linalg.norm(x[:, 3:], axis=1)
        active = active[moving >= tolerance_mm]
        if len(active) == 0:
            break
    return T, rmse


@dataclass(frozen=True)
class Hypothesis:
    """One refined hypothesis: ``name``, its start ``T_start`` and refined ``T_ct_us``
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
class HypothesisResult:
    """The outcome of :func:`search_hypotheses` (module docstring for the definitions).

    Attributes:
        T_ct_us: ``(4, 4)`` mm, the chosen hypothesis' refined (and polished) pose.
        chosen: its name.
        runner_up: the best-scoring genuinely different pose's name, None if there is none.
        score_gap_mm: ``score(runner_up) - score(chosen)`` (mm), None without a runner-up.
        confidence: ``max(score_gap_mm, 0) / max(score(runner_up), score_floor_mm)`` in
            [0, 1]; 1.0 without a runner-up.
        ambiguous: ``confidence < min_confidence``.
        hypotheses: every refined :class:`Hypothesis`, in generation order.
        starts_tried: start poses built and screened before the best ``refine_top`` were refined.
    """

    T_ct_us: np.ndarray
    chosen: str
    runner_up: str | None
    score_gap_mm: float | None
    confidence: float
    ambiguous: bool
    hypotheses: tuple[Hypothesis, ...] = field(default=())
    starts_tried: int = 0

    @property
    def polish(self) -> dict[str, Any] | None:
        """The chosen pose's polish (:attr:`Hypothesis.polish`), None when it was not run."""
        return self.best.polish

    @property
    def polished(self) -> list[str]:
        """Names of the polished hypotheses (the best and those tied with it)."""
        return [h.name for h in self.hypotheses if h.polish is not None]

    @property
    def scores(self) -> dict[str, float]:
        """``{name: score_mm}`` of every hypothesis."""
        return {h.name: h.score_mm for h in self.hypotheses}

    @property
    def best(self) -> Hypothesis:
        return next(h for h in self.hypotheses if h.name == self.chosen)

    def to_json(self) -> dict[str, Any]:
        """JSON-able summary (``result.json``'s ``hypotheses`` block)."""
        return {"chosen": self.chosen, "runner_up": self.runner_up,
                "score_mm": self.best.score_mm, "score_gap_mm": self.score_gap_mm,
                "confidence": self.confidence, "ambiguous": self.ambiguous,
                "starts_tried": self.starts_tried, "scores_mm": self.scores,
                "polish": self.polish, "polished": self.polished}


def build_hypotheses(T_start: np.ndarray, target: HypothesisTarget,
                     completion: np.ndarray | None = None,
                     config: HypothesisConfig | None = None, *,
                     T_coarse: np.ndarray | None = None,
                     grid_offset: float = 0.0) -> dict[str, np.ndarray]:
    """The start poses ``{name: T_ct_us (4, 4) mm}`` of the hypotheses (module docstring).

    Args:
        T_start: ``(4, 4)`` mm, the pose the alternatives are built around.
        target: the CT side (its principal frame is used without a completion).
        completion: ``(M, 3)`` mm, the completed bone in the US frame, or None.
        config: settings (default :class:`HypothesisConfig`).
        T_coarse: ``(4, 4)`` mm, the network's coarse pose, or None.
        grid_offset: shift of the rotations and slides, as a share of their steps (0.5: the
            grid interleaved with the default one; the bases themselves are not included).
    """
    cfg = config or HypothesisConfig()
    bases = {"network": check_rigid(T_start)}
    if T_coarse is not None and cfg.include_coarse:
        bases["coarse"] = check_rigid(T_coarse)
    if completion is not None and cfg.principal_axes_solve:
        c_us, a_us = principal_frame(completion)
        T = np.eye(4)
        T[:3, :3] = target.axes @ a_us.T
        T[:3, 3] = target.centre - T[:3, :3] @ c_us
        bases["pca"] = T
    starts: dict[str, np.ndarray] = {}
    slides = slide_offsets_mm(target, cfg) + grid_offset * cfg.slide_step_mm
    for base, T_base in bases.items():
        if completion is not None:
            centre, axes = principal_frame(apply_transform(T_base, completion))
        else:
            centre, axes = target.centre, target.axes
        flip = rotation_about(centre, axes[:, 1], math.pi)
        for flipped in ((False, True) if cfg.axis_flips else (False,)):
            for k in range(cfg.shaft_rotations):
                angle = 360.0 * (k + grid_offset) / cfg.shaft_rotations
                G = rotation_about(centre, axes[:, 0], math.radians(angle))
                G = G @ flip if flipped else G
                name = base + ("+flip" if flipped else "") + (f"+rot{angle:g}" if angle else "")
                for slide in slides:
                    S = np.eye(4)
                    S[:3, 3] = slide * axes[:, 0]
                    starts[name + (f"+slide{slide:g}" if slide else "")] = S @ G @ T_base
    return starts


def slide_offsets_mm(target: HypothesisTarget, config: HypothesisConfig) -> np.ndarray:
    """Slides along the long axis tried per rotation hypothesis (mm, 0 first, then by
    increasing size): multiples of ``slide_step_mm`` up to ``slide_range_mm`` (default half
    the CT's length along its long axis); just ``[0]`` when ``slide_step_mm`` is 0."""
    if config.slide_step_mm == 0:
        return np.zeros(1)
    reach = config.slide_range_mm
    if reach is None:
        along = (target.points - target.centre) @ target.axes[:, 0]
        reach = 0.5 * float(along.max() - along.min())
    steps = np.arange(1, int(reach // config.slide_step_mm) + 1) * config.slide_step_mm
    return np.concatenate([[0.0], np.stack([steps, -steps], axis=1).ravel()])


def screen_starts(us_points: np.ndarray, starts: np.ndarray, target: HypothesisTarget,
                  config: HypothesisConfig, *, keep_first: bool = True
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Pick the starts worth a full ICP: ``screen_iterations`` of point-to-plane ICP on
    ``screen_points`` US points for every start at once (correspondences from the CT's
    closest-point grid, :meth:`HypothesisTarget.nearest_approx`), then a quick score (trimmed
    mean distance of ``screen_score_points`` US points to the CT); keep the first start (the
    network's own pose, unmoved; unless ``keep_first`` is False) and then the best-scoring
    ones, skipping those within
    ``distinct_deg`` and ``distinct_mm`` (US centroid) of one already kept, up to
    ``refine_top`` in all (all of them, unmoved, when ``refine_top`` is 0 or not below ``B``).

    Args:
        us_points: ``(n, 3)`` mm, US points (US frame).
        starts: ``(B, 4, 4)`` mm start poses ``T_ct_us``.

    Returns:
        ``(K,)`` indices of the kept starts and their ``(K, 4, 4)`` screened poses.
    """
    if config.refine_top == 0 or len(starts) <= config.refine_top:
        return np.arange(len(starts)), starts

    poses, _ = _point_to_plane(_strided(us_points, config.screen_points), starts, target,
                               config.screen_iterations, config.icp_trim, 0.1, approximate=True)
    sub = _strided(us_points, config.screen_score_points)
    moved = _apply_batch(poses, sub)  # B n 3
    scores = _trimmed_mean(target.surface_distances(moved, approximate=True), config.score_trim)
    centroids = _apply_batch(poses, us_points.mean(axis=0)[None])[:, 0]  # B 3
    chosen = [0] if keep_first else []
    for i in np.argsort(scores, kind="stable"):
        if len(chosen) == config.refine_top:
            break
        if not chosen or not _same_pose(poses, centroids, i, np.array(chosen), config).any():
            chosen.append(int(i))
    kept = np.array(chosen)
    screened = poses[kept]
    if keep_first:
        screened[0] = starts[0]
    return kept, screened


def search_hypotheses(us_points: np.ndarray, T_start: np.ndarray, target: HypothesisTarget,
                      completion: np.ndarray | None = None,
                      config: HypothesisConfig | None = None, *,
                      T_coarse: np.ndarray | None = None) -> HypothesisResult:
    """Build, refine (one batched ICP) and score the pose hypotheses; keep the best.

    With ``retry_ambiguous``, an ambiguous result gets a second round from the grid of starts
    interleaved with the first (rotations and slides shifted by half a step), and the choice
    is made again among the hypotheses of both rounds.

    Args:
        us_points: ``(N, 3)`` mm, the observed US bone points in their own (US) frame.
        T_start: ``(4, 4)`` mm, the start ``T_ct_us`` (the network's pose after its ICP).
        target: the CT side, :class:`HypothesisTarget` (e.g. ``from_mesh``).
        completion: ``(M, 3)`` mm, the completed bone in the US frame (the network's output),
            or None (the CT's principal frame stands in; no principal-axes solve).
        config: settings (default :class:`HypothesisConfig`; ``enabled`` is not looked at
            here: calling this function runs the stage).
        T_coarse: ``(4, 4)`` mm, the coarse pose before the network's ICP, or None.

    Returns:
        :class:`HypothesisResult` (all mm).
    """
    cfg = config or HypothesisConfig()
    pts = as_points(us_points, "US points")
    if len(pts) < 6:  # 6 point-to-surface constraints for the 6 degrees of freedom
        raise InvalidGeometryError(f"The US cloud has {len(pts)} points; the hypotheses need at "
                                   "least 6.", "Pass a denser US bone surface.")
    if completion is not None:
        completion = as_points(completion, "completion points")
        if len(completion) < 4:
            completion = None
    subset_mm = us_subset(pts, cfg.icp_points, cfg.icp_subset)  # n 3
    centroid = pts.mean(axis=0)  # the US centroid, placed by each pose
    T_network = check_rigid(T_start)
    names: list[str] = []
    starts: list[np.ndarray] = []
    poses = np.zeros((0, 4, 4))
    scores, rmse = np.zeros(0), np.zeros(0)
    polishes: list[dict[str, Any] | None] = []
    tried = 0
    for offset in (0.0, 0.5) if cfg.retry_ambiguous else (0.0,):
        grid = build_hypotheses(T_network, target, completion, cfg, T_coarse=T_coarse,
                                grid_offset=offset)
        tried += len(grid)
        new_names, new_starts, new_poses, new_rmse = _refine_round(
            subset_mm, grid, target, cfg, keep_first=offset == 0.0)
        names += new_names
        starts += new_starts
        poses = np.concatenate([poses, new_poses])
        rmse = np.concatenate([rmse, new_rmse])
        scores = np.concatenate([scores, _trimmed_mean(
            target.surface_distances(_apply_batch(new_poses, subset_mm)), cfg.score_trim)])
        polishes += [None] * len(new_names)
        best, runner = _choose_and_polish(subset_mm, centroid, poses, scores, polishes,
                                          T_network, target, cfg)
        confidence = 1.0 if runner is None else float(_confidence(scores[best], scores[runner],
                                                                  cfg))
        if confidence >= cfg.min_confidence:
            break
    gap = None if runner is None else float(scores[runner] - scores[best])
    hypotheses = tuple(Hypothesis(n, starts[i], poses[i], float(scores[i]),
                                  float(rmse[i]) if math.isfinite(rmse[i]) else float("nan"),
                                  polishes[i])
                       for i, n in enumerate(names))
    return HypothesisResult(T_ct_us=poses[best], chosen=names[best],
                            runner_up=None if runner is None else names[runner],
                            score_gap_mm=gap, confidence=confidence,
                            ambiguous=confidence < cfg.min_confidence,
                            hypotheses=hypotheses, starts_tried=tried)


def _refine_round(subset_mm: np.ndarray, grid: dict[str, np.ndarray], target: HypothesisTarget,
                  config: HypothesisConfig, *, keep_first: bool
                  ) -> tuple[list[str], list[np.ndarray], np.ndarray, np.ndarray]:
    """Steps 2-3 of the module docstring for the start poses ``grid`` ``{name: (4, 4)}``:
    screen them (``keep_first``: the first one, the network's own pose, always goes on), refine
    the kept ones. Returns their names, start poses, ``(K, 4, 4)`` refined poses (mm) and
    ``(K,)`` ICP residuals (mm)."""
    all_names = list(grid)
    kept, screened = screen_starts(subset_mm, np.stack(list(grid.values())), target, config,
                                   keep_first=keep_first)
    names = [all_names[i] for i in kept]
    if config.icp_mode == "plane":
        refined, rmse = point_to_plane_icp_batch(
            subset_mm, screened, target,
            iterations=config.icp_iterations, schedule=config.icp_schedule,
            margin_mm=config.icp_margin_mm, trim_fraction=config.icp_trim)
        poses = np.stack([orthonormalize(T) for T in refined])
    else:
        norm, device = target.normalization, target.device
        src = torch.from_numpy(norm.points_to_model(subset_mm)).float()[None].to(device)
        init = torch.from_numpy(np.stack([norm.transform_to_model(T) for T in screened])
                                ).float().to(device)  # K 4 4
        with torch.no_grad():
            icp = differentiable_icp(src.expand(len(names), -1, -1), target.model_points, init,
                                     iterations=config.icp_iterations, sigma=config.icp_sigma,
                                     neighbors=config.icp_neighbors, mode=config.icp_mode,
                                     trim_fraction=config.icp_trim)
        poses = np.stack([norm.transform_to_mm(orthonormalize(T)) for T in
                          icp.transform.double().cpu().numpy()])
        rmse = icp.rmse.double().cpu().numpy() * norm.scale
    return names, [grid[n] for n in names], poses, rmse


def _choose_and_polish(subset_mm: np.ndarray, centroid: np.ndarray, poses: np.ndarray,
                       scores: np.ndarray, polishes: list[dict[str, Any] | None],
                       T_network: np.ndarray, target: HypothesisTarget,
                       config: HypothesisConfig) -> tuple[int, int | None]:
    """Steps 5-6 of the module docstring: polish the poses tied with the best (``poses``
    ``(B, 4, 4)``, ``scores`` ``(B,)`` and ``polishes`` are updated in place; poses polished
    before are not polished again), choose, and find the runner-up. Returns ``(chosen,
    runner-up or None)`` indices."""
    eligible = np.ones(len(poses), dtype=bool)
    placed = _apply_batch(poses, centroid[None])[:, 0]  # B 3
    if config.polish and target.matcher is not None:
        # the best pose and those tied with it, polished and re-scored exactly; only polished
        # poses can be chosen (the scores of the others are not exact, and they were not tied)
        candidates = _polish_candidates(scores, poses, placed, config)
        quick = len(candidates) > 1  # several: a quick polish of each, then the chosen in full
        for i in candidates:
            if polishes[i] is None:
                poses[i], scores[i], polishes[i] = _polish(subset_mm, centroid, poses[i], target,
                                                           config, quick=quick)
        placed = _apply_batch(poses, centroid[None])[:, 0]
        eligible = np.array([p is not None for p in polishes])
    best = _choose(scores, poses, placed, T_network, config, eligible)
    if polishes[best] is not None and polishes[best]["quick"]:
        poses[best], scores[best], polishes[best] = _polish(
            subset_mm, centroid, poses[best], target, config, after=polishes[best])
        placed[best] = apply_transform(poses[best], centroid[None])[0]
    others = np.array([i for i in range(len(poses)) if i != best], dtype=np.int64)
    distinct = others[~_same_pose(poses, placed, best, others, config)]
    runner = int(distinct[np.argmin(scores[distinct])]) if len(distinct) else None
    return best, runner


def _confidence(score: float, others: np.ndarray | float, config: HypothesisConfig):
    """How clearly a pose scoring ``score`` beats poses scoring ``others`` (mm): ``max(other -
    score, 0) / max(other, score_floor_mm)``, in [0, 1] (module docstring, step 6)."""
    others = np.asarray(others, dtype=np.float64)
    return np.maximum(others - score, 0.0) / np.maximum(others, config.score_floor_mm)


def _choose(scores: np.ndarray, poses: np.ndarray, placed: np.ndarray, T_network: np.ndarray,
            config: HypothesisConfig, eligible: np.ndarray) -> int:
    """Index of the chosen pose among the ``eligible`` ones ``(B,)`` bool: the best score, or
    with ``tie_break="network"`` among the poses tied with the best (confidence below
    ``min_confidence``) the best-scoring of those rotated like the one rotated least from the
    network's pose ``T_network`` (slides: by score). ``scores`` ``(B,)`` mm, ``poses``
    ``(B, 4, 4)``, ``placed`` ``(B, 3)`` US centroids."""
    masked = np.where(eligible, scores, np.inf)
    best = int(np.argmin(masked))  # first minimum: the network's pose wins exact ties
    if config.tie_break == "network":
        tied = np.flatnonzero(eligible & (_confidence(scores[best], scores, config)
                                          < config.min_confidence))
        nearest = tied[np.argmin([rotation_error_deg(poses[i], T_network) for i in tied])]
        rotated_alike = tied[_same_pose(poses, placed, nearest, tied, config,
                                        rotation_only=True)]
        best = int(rotated_alike[np.argmin(scores[rotated_alike])])
    return best


def _polish_candidates(scores: np.ndarray, poses: np.ndarray, placed: np.ndarray,
                       config: HypothesisConfig) -> list[int]:
    """The poses worth polishing: the best-scoring one and the distinct poses tied with it
    (confidence below ``min_confidence``), the network's own pose (index 0) next if it is tied,
    then by increasing score, at most ``polish_top``."""
    order = np.argsort(scores, kind="stable")
    tied = order[_confidence(scores[order[0]], scores[order], config) < config.min_confidence]
    if 0 in tied[1:]:  # the prior: a tie the geometry cannot break may be the network's to break
        tied = np.concatenate([tied[:1], [0], tied[1:][tied[1:] != 0]])
    kept: list[int] = []
    for i in tied:
        if len(kept) == config.polish_top:
            break
        if not kept or not _same_pose(poses, placed, int(i), np.array(kept), config).any():
            kept.append(int(i))
    return kept


def _polish(subset_mm: np.ndarray, centroid: np.ndarray, T: np.ndarray,
            target: HypothesisTarget, config: HypothesisConfig, *, quick: bool = False,
            after: dict[str, Any] | None = None) -> tuple[np.ndarray, float, dict[str, Any]]:
    """Step 5 of the module docstring for one pose ``T`` ``(4, 4)``: the polished pose, its
    exact score (trimmed mean distance of ``subset_mm`` ``(n, 3)`` to the mesh, mm) and the
    polish's record (:attr:`Hypothesis.polish`; ``moved_mm`` of the US ``centroid`` ``(3,)``).
    ``quick``: on :data:`QUICK_POLISH_POINTS`
    strided points and at most :data:`QUICK_POLISH_ITERATIONS` (to compare tied poses);
    ``after``: the record of a quick polish this one continues (its counts are added)."""
    mark = time.perf_counter()
    source = _strided(subset_mm, QUICK_POLISH_POINTS) if quick else subset_mm
    iterations = (min(QUICK_POLISH_ITERATIONS, config.polish_iterations) if quick
                  else config.polish_iterations)
    polished, info = point_to_plane_icp(source, target.matcher, T,
                                        max_distance_mm=config.polish_max_distance_mm,
                                        max_iterations=iterations,
                                        tolerance_mm=POLISH_TOLERANCE_MM)
    info["moved_mm"] = float(np.linalg.norm(apply_transform(polished, centroid[None])
                                            - apply_transform(T, centroid[None])))
    _, _, distances = target.matcher.closest(apply_transform(polished, subset_mm))
    score = float(_trimmed_mean(distances[None], config.score_trim)[0])
    info["quick"] = quick
    info["runtime_s"] = time.perf_counter() - mark
    if after is not None:  # moved_mm: from before the quick polish (near enough: both small)
        info["iterations"] += after["iterations"]
        info["runtime_s"] += after["runtime_s"]
        info["moved_mm"] = float(np.hypot(info["moved_mm"], after["moved_mm"]))
    return polished, score, info
