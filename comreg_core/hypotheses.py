"""Test-time pose hypotheses: no flips, no spins about the shaft, and a confidence flag.

A partial US sweep of a long, near-symmetric bone (fibula, tibia or femur shaft) fits several
poses: flipped end to end, turned about the shaft, or the one the network found. The learned
coarse pose only has to land in ICP's basin; when it lands in the basin of a symmetric
alternative, plain ICP converges there and the result is a flip. This module tries the
alternatives at test time, with no extra training data:

1. **Hypotheses** (all ``T_ct_us``, mm), built around a start pose ``T_start`` (the network's
   result after its ICP):

   - ``network``: ``T_start`` itself;
   - its symmetric alternatives ``G @ T_start``, with ``G`` a rotation of the *CT frame* about
     the principal axes of the completed bone placed by ``T_start`` (centroid ``c``, axes
     ``a0`` = long, ``a1``, ``a2`` = the two short ones): rotations about the long axis ``a0``
     by ``360 k / shaft_rotations`` degrees (``network+rot90``, ...) and, with ``axis_flips``,
     each of them combined with the end-to-end flip, 180 deg about ``a1`` (``network+flip``,
     ``network+flip+rot90``, ...). Together that is the dihedral group of the shaft: with 4
     rotations it holds the 180 deg turns about all three principal axes. Without a completion,
     the CT's own principal frame is used instead (the completion of a well-placed cloud *is*
     the CT bone);
   - with a completion and ``centred_copies``: each of these shifted so that the completion's
     centroid meets the CT's (``network+centred``, ``network+flip+centred``, ...): a full
     shape shares its centroid with the CT, which undoes the network's slides along the shaft
     (its most common error) that ICP cannot;
   - ``coarse``: the network's coarse pose before its ICP (when given);
   - with ``principal_axes_solve`` and a completion: the full-to-full solve of the completed
     shape against the CT by principal axes, one hypothesis per sign choice of the axes that
     gives a proper rotation (``pca+++``, ``pca--+``, ``pca-+-``, ``pca+--``).

2. **Refinement**: all hypotheses are refined together, in one batch, of an FPS subset of the
   US cloud (``icp_points``) against a dense cloud of the CT surface (``target_points``
   area-uniform samples with their triangles' normals). By default (``icp_mode="plane"``) with
   the batched point-to-plane ICP :func:`point_to_plane_icp_batch`, coarse to fine: the
   ``icp_schedule`` stages on evenly strided subsets (128, then 512 US points, 30 iterations
   each), then ``icp_iterations`` on all ``icp_points``; after each stage only the hypotheses
   whose residual is within ``icp_margin_mm`` of the best go on. Measured on simulated fibula
   sweeps from starts 15 deg / 10 mm off (flipped or not), it lands 84-100% of them within
   2 mm / 2 deg where the point-to-point
   :func:`~comreg_core.model.diff_icp.differentiable_icp` (``"hard"`` / ``"soft"``, kept as
   options, run in one batched call in normalised units) lands 20-50% in the same or more time:
   along a shaft the surface slides under the points and point-to-point ICP crawls
   (``tests/benchmarks/bench_hypotheses.py``).

3. **Score** (mm, lower is better): the trimmed mean distance of the hypothesis' registered US
   subset to the CT surface: the mean of the smallest ``1 - score_trim`` share of the
   point-to-surface distances, each taken to the tangent plane of the nearest dense CT point
   (KD-tree, pykdtree; :meth:`HypothesisTarget.surface_distances`: unlike the plain
   nearest-point distance it has almost no bias from the sample spacing, so a perfect fit
   scores near 0 and the gaps between poses are not blurred). Trimming keeps false bone echoes
   and parts of the sweep the CT does not explain from dominating.

4. **Choice and confidence**: the best score wins (ties go to the earlier hypothesis, i.e. the
   network's own pose). The *runner-up* is the best-scoring hypothesis whose refined pose is a
   genuinely different pose from the winner: rotated by more than ``distinct_deg`` or with the
   US cloud's centroid moved by more than ``distinct_mm``; hypotheses that converged onto the
   winner's pose are duplicates and never count. ``score_gap_mm = score(runner-up) -
   score(best)``; ``confidence = score_gap_mm / score(runner-up)`` (= ``1 - best / runner-up``,
   in [0, 1]: 0 is a tie, 1 no competing pose; 1 when no distinct runner-up exists); and
   ``ambiguous = score_gap_mm < ambiguity_gap_mm``: another, clearly different pose explains
   the US points (nearly) as well as the chosen one, e.g. a sweep of a featureless stretch of
   shaft.

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

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import torch

from comreg_core.config import require
from comreg_core.errors import InvalidGeometryError
from comreg_core.model.diff_icp import differentiable_icp
from comreg_core.model.normalization import Normalization
from comreg_core.model.ops import subsample
from comreg_core.transforms import apply_transform, as_points, check_rigid, orthonormalize

#: Sign choices of the principal-axes solve that give proper rotations (det = +1).
_PCA_SIGNS = {"pca+++": (1, 1, 1), "pca--+": (-1, -1, 1), "pca-+-": (-1, 1, -1),
              "pca+--": (1, -1, -1)}


@dataclass(frozen=True)
class HypothesisConfig:
    """Settings of the hypotheses stage (module docstring).

    Attributes:
        enabled: run the stage at all (False = the paper's plain pipeline).
        shaft_rotations: rotations about the long axis, ``360 / shaft_rotations`` deg apart, the
            start pose included (1 = only the start pose).
        axis_flips: also flip each of them end to end (180 deg about a short axis).
        include_coarse: also refine the network's coarse pose (when one is given).
        principal_axes_solve: add the 4 principal-axes solves of the completion vs the CT
            (needs a completion).
        centred_copies: with a completion, also try each rotation hypothesis (the start pose
            and its alternatives) shifted so that the completion's centroid meets the CT's:
            the full shape and the CT share a centroid, so this undoes a slide along the shaft
            that ICP cannot (suffix ``+centred``).
        shaft_shifts_mm: also try each rotation hypothesis slid along the long axis by these
            distances (mm; suffix ``+shift20`` etc.).
        icp_points: US points (FPS subset) in the hypotheses' ICP and score.
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
        distinct_deg, distinct_mm: two refined poses are different poses when their rotations
            differ by more than ``distinct_deg`` or they place the US centroid more than
            ``distinct_mm`` apart; otherwise the later one is a duplicate.
        ambiguity_gap_mm: a result is ambiguous when a different pose scores within this of the
            best.
    """

    enabled: bool = True
    shaft_rotations: int = 4
    axis_flips: bool = True
    include_coarse: bool = True
    principal_axes_solve: bool = True
    centred_copies: bool = False
    shaft_shifts_mm: tuple[float, ...] = ()
    icp_points: int = 2048
    target_points: int = 20_000
    icp_mode: Literal["plane", "hard", "soft"] = "plane"
    icp_iterations: int = 20
    icp_schedule: tuple[tuple[int, int], ...] = ((128, 30), (512, 30))
    icp_margin_mm: float = 1.0
    icp_sigma: float = 5e-3
    icp_neighbors: int = 16
    icp_trim: float = 0.1
    score_trim: float = 0.2
    distinct_deg: float = 10.0
    distinct_mm: float = 5.0
    ambiguity_gap_mm: float = 0.2

    def __post_init__(self) -> None:
        require(isinstance(self.enabled, bool), "hypotheses.enabled", "must be true or false")
        require(self.shaft_rotations >= 1, "hypotheses.shaft_rotations", "must be at least 1")
        require(self.shaft_rotations <= 36, "hypotheses.shaft_rotations",
                "must be at most 36 (10 deg apart)")
        require(self.icp_points >= 3, "hypotheses.icp_points", "must be at least 3")
        require(self.target_points >= 100, "hypotheses.target_points", "must be at least 100")
        require(self.icp_iterations >= 0, "hypotheses.icp_iterations", "must be 0 or more")
        require(all(p >= 6 and it >= 0 for p, it in self.icp_schedule),
                "hypotheses.icp_schedule", "needs at least 6 points and 0 or more iterations "
                "per stage")
        require(self.icp_margin_mm > self.ambiguity_gap_mm, "hypotheses.icp_margin_mm",
                "must be above ambiguity_gap_mm")
        require(self.icp_mode in ("plane", "hard", "soft"), "hypotheses.icp_mode",
                "must be 'plane', 'hard' or 'soft'")
        require(self.icp_sigma > 0, "hypotheses.icp_sigma", "must be positive")
        require(self.icp_neighbors >= 1, "hypotheses.icp_neighbors", "must be at least 1")
        require(0.0 <= self.icp_trim < 1.0, "hypotheses.icp_trim", "must be in [0, 1)")
        require(0.0 <= self.score_trim < 1.0, "hypotheses.score_trim", "must be in [0, 1)")
        require(self.distinct_deg > 0, "hypotheses.distinct_deg", "must be positive")
        require(self.distinct_mm > 0, "hypotheses.distinct_mm", "must be positive")
        require(self.ambiguity_gap_mm >= 0, "hypotheses.ambiguity_gap_mm", "must be 0 or more")


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


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (deg) of the relative rotation ``R_a^T R_b`` (3x3 parts of 3x3 or 4x4 inputs)."""
    R = np.asarray(R_a)[:3, :3].T @ np.asarray(R_b)[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


class HypothesisTarget:
    """The CT side of the hypotheses stage, prepared once per CT: a dense cloud of the CT
    surface (ICP target and score reference, with its KD-tree), the normalisation of the ICP,
    and the CT's principal frame.

    Args:
        points: ``(M, 3)`` mm, dense points on the CT bone surface (e.g. area-uniform samples).
        normalization: the network's normalisation (default: from ``points``, the CT's
            bounding-box centre and largest extent).
        device: torch device of the ICP.
    """

    def __init__(self, points: np.ndarray, normalization: Normalization | None = None,
                 device: str | torch.device = "cpu", *, normals: np.ndarray | None = None):
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
        return cls(points, normalization, device, normals=normals)

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (mm) and indices of the nearest CT points of ``(..., 3)`` points."""
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        d, idx = self.tree.query(pts, k=1)
        shape = np.shape(points)[:-1]
        return np.asarray(d, dtype=np.float64).reshape(shape), idx.astype(np.int64).reshape(shape)

    def surface_distances(self, points: np.ndarray) -> np.ndarray:
        """Distances (mm) of ``(..., 3)`` points to the CT surface, approximated by the tangent
        plane at the nearest CT point: ``|(p - q) . n_q|``. On a smooth surface this is the
        point-to-surface distance without most of the sampling bias of the plain
        nearest-neighbour distance (about half the sample spacing, ~0.4 mm at 20,000 samples
        of a fibula); it never exceeds the nearest-neighbour distance."""
        pts = np.asarray(points, dtype=np.float64)
        _, idx = self.nearest(pts)
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
        sub = src if points >= len(src) else \
            src[np.linspace(0, len(src) - 1, points).astype(np.int64)]
        T[going], rmse[going] = _point_to_plane(sub, T[going], target, its, trim_fraction,
                                                tolerance_mm)
        if margin_mm is not None and i < len(stages) - 1 and np.isfinite(rmse[going]).any():
            going &= ~(rmse > np.nanmin(rmse[going]) + margin_mm)
    return T, rmse


def _point_to_plane(src: np.ndarray, T: np.ndarray, target: HypothesisTarget, iterations: int,
                    trim_fraction: float, tolerance_mm: float) -> tuple[np.ndarray, np.ndarray]:
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
        moved = np.einsum("bij,nj->bni", Ta[:, :3, :3], src) + Ta[:, None, :3, 3]  # m n 3
        d, idx = target.nearest(moved)  # m n
        q, nrm = target.points[idx], target.normals[idx]  # m n 3
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
        H = np.einsum("bni,bnj->bij", Aw, A)  # m 6 6
        g = np.einsum("bni,bn->bi", Aw, r)  # m 6
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
    (``(4, 4)`` mm), ``score_mm`` (trimmed mean distance to the CT, mm) and the ICP's final
    ``icp_rmse_mm``."""

    name: str
    T_start: np.ndarray
    T_ct_us: np.ndarray
    score_mm: float
    icp_rmse_mm: float


@dataclass(frozen=True)
class HypothesisResult:
    """The outcome of :func:`search_hypotheses` (module docstring for the definitions).

    Attributes:
        T_ct_us: ``(4, 4)`` mm, the chosen hypothesis' refined pose.
        chosen: its name.
        runner_up: the best-scoring genuinely different pose's name, None if there is none.
        score_gap_mm: ``score(runner_up) - score(chosen)`` (mm), None without a runner-up.
        confidence: ``score_gap_mm / score(runner_up)`` in [0, 1]; 1.0 without a runner-up.
        ambiguous: ``score_gap_mm < ambiguity_gap_mm``.
        hypotheses: every refined :class:`Hypothesis`, in generation order.
    """

    T_ct_us: np.ndarray
    chosen: str
    runner_up: str | None
    score_gap_mm: float | None
    confidence: float
    ambiguous: bool
    hypotheses: tuple[Hypothesis, ...] = field(default=())

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
                "scores_mm": self.scores}


def build_hypotheses(T_start: np.ndarray, target: HypothesisTarget,
                     completion: np.ndarray | None = None,
                     config: HypothesisConfig | None = None, *,
                     T_coarse: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The start poses ``{name: T_ct_us (4, 4) mm}`` of the hypotheses (module docstring).

    Args:
        T_start: ``(4, 4)`` mm, the pose the alternatives are built around.
        target: the CT side (its principal frame is used without a completion).
        completion: ``(M, 3)`` mm, the completed bone in the US frame, or None.
        config: settings (default :class:`HypothesisConfig`).
        T_coarse: ``(4, 4)`` mm, the network's coarse pose, or None.
    """
    cfg = config or HypothesisConfig()
    T_start = check_rigid(T_start)
    if completion is not None:
        centre, axes = principal_frame(apply_transform(T_start, completion))
    else:
        centre, axes = target.centre, target.axes
    starts: dict[str, np.ndarray] = {}
    flip = rotation_about(centre, axes[:, 1], math.pi)
    for flipped in ((False, True) if cfg.axis_flips else (False,)):
        for k in range(cfg.shaft_rotations):
            degrees = round(360.0 * k / cfg.shaft_rotations)
            G = rotation_about(centre, axes[:, 0], math.radians(360.0 * k / cfg.shaft_rotations))
            name = "network" + ("+flip" if flipped else "") + (f"+rot{degrees}" if k else "")
            starts[name] = (G @ flip if flipped else G) @ T_start
    rotations = list(starts.items())
    for shift_mm in cfg.shaft_shifts_mm:
        shift = np.eye(4)
        shift[:3, 3] = shift_mm * axes[:, 0]
        starts.update({f"{name}+shift{shift_mm:g}": shift @ T for name, T in rotations})
    if completion is not None and cfg.centred_copies:
        # the alternatives turn about the completion's centroid c, so one shift serves them all
        shift = np.eye(4)
        shift[:3, 3] = target.centre - centre
        starts.update({f"{name}+centred": shift @ T for name, T in rotations})
    if T_coarse is not None and cfg.include_coarse:
        starts["coarse"] = check_rigid(T_coarse)
    if completion is not None and cfg.principal_axes_solve:
        c_us, a_us = principal_frame(completion)
        c_ct, a_ct = target.centre, target.axes
        for name, signs in _PCA_SIGNS.items():
            T = np.eye(4)
            T[:3, :3] = a_ct @ np.diag(signs) @ a_us.T
            T[:3, 3] = c_ct - T[:3, :3] @ c_us
            starts[name] = T
    return starts


def search_hypotheses(us_points: np.ndarray, T_start: np.ndarray, target: HypothesisTarget,
                      completion: np.ndarray | None = None,
                      config: HypothesisConfig | None = None, *,
                      T_coarse: np.ndarray | None = None) -> HypothesisResult:
    """Build, refine (one batched ICP) and score the pose hypotheses; keep the best.

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
    if len(pts) < 3:
        raise InvalidGeometryError(f"The US cloud has {len(pts)} points; the hypotheses need at "
                                   "least 3.", "Pass a denser US bone surface.")
    if completion is not None:
        completion = as_points(completion, "completion points")
        if len(completion) < 4:
            completion = None
    starts = build_hypotheses(T_start, target, completion, cfg, T_coarse=T_coarse)
    names = list(starts)
    norm, device = target.normalization, target.device

    src = torch.from_numpy(norm.points_to_model(pts)).float()[None].to(device)  # 1 N 3
    src = subsample(src, cfg.icp_points, 0)  # 1 n 3
    subset_mm = norm.points_to_mm(src[0].double().cpu().numpy())  # n 3
    B = len(names)
    if cfg.icp_mode == "plane":
        refined, rmse = point_to_plane_icp_batch(
            subset_mm, np.stack([starts[n] for n in names]), target,
            iterations=cfg.icp_iterations, schedule=cfg.icp_schedule,
            margin_mm=cfg.icp_margin_mm, trim_fraction=cfg.icp_trim)
        finals = [orthonormalize(T) for T in refined]
    else:
        init = torch.from_numpy(np.stack([norm.transform_to_model(starts[n]) for n in names])
                                ).float().to(device)  # B 4 4
        with torch.no_grad():
            icp = differentiable_icp(src.expand(B, -1, -1), target.model_points, init,
                                     iterations=cfg.icp_iterations, sigma=cfg.icp_sigma,
                                     neighbors=cfg.icp_neighbors, mode=cfg.icp_mode,
                                     trim_fraction=cfg.icp_trim)
        finals = [norm.transform_to_mm(orthonormalize(T)) for T in
                  icp.transform.double().cpu().numpy()]
        rmse = icp.rmse.double().cpu().numpy() * norm.scale
    moved = np.stack([apply_transform(T, subset_mm) for T in finals])  # B n 3
    d = np.sort(target.surface_distances(moved), axis=1)  # B n
    keep = max(1, len(subset_mm) - int(cfg.score_trim * len(subset_mm)))
    scores = d[:, :keep].mean(axis=1)
    hypotheses = tuple(Hypothesis(n, starts[n], finals[i], float(scores[i]),
                                  float(rmse[i]) if math.isfinite(rmse[i]) else float("nan"))
                       for i, n in enumerate(names))
    best = int(np.argmin(scores))  # first minimum: the network's pose wins ties
    centroid = pts.mean(axis=0)
    at_best = apply_transform(finals[best], centroid[None])[0]
    runner, runner_score = None, math.inf
    for i in range(B):
        if i == best or scores[i] >= runner_score:
            continue
        moved_c = apply_transform(finals[i], centroid[None])[0]
        if (rotation_angle_deg(finals[i], finals[best]) > cfg.distinct_deg
                or np.linalg.norm(moved_c - at_best) > cfg.distinct_mm):
            runner, runner_score = i, float(scores[i])
    if runner is None:
        gap, confidence, ambiguous = None, 1.0, False
    else:
        gap = runner_score - float(scores[best])
        confidence = float(gap / runner_score) if runner_score > 0 else 0.0
        ambiguous = bool(gap < cfg.ambiguity_gap_mm)
    return HypothesisResult(T_ct_us=finals[best], chosen=names[best],
                            runner_up=None if runner is None else names[runner],
                            score_gap_mm=gap, confidence=confidence, ambiguous=ambiguous,
                            hypotheses=hypotheses)
