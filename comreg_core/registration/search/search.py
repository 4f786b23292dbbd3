"""The pose search: many start poses, screened, refined and scored; the best kept, with a
confidence. A partial sweep of a long, near-symmetric bone fits several poses (flipped end to
end, turned about or slid along the shaft); the search tries them all. Steps (all ``T_ct_us``,
mm; docs/guide.md "The pose search" for the user's view, docs/results.md for why each step is
as it is):

1. **Starts**: around a base pose (``pca``: the US cloud's principal axes on the CT's; a
   prior's initial pose; with a completion, its principal-axes solve), rotations about the
   long axis by ``360 k / shaft_rotations`` deg, each flipped end to end, each slid along the
   axis by multiples of ``slide_step_mm`` over +-``slide_range_mm`` (names like
   ``pca+flip+rot90+slide24``). A *patch* (:func:`is_patch`) also gets
   :data:`PATCH_ORIENTATIONS` orientations over all rotations, each slid
   (:func:`patch_orientation_starts`).
2. **Screening** (:func:`~comreg_core.registration.search.screening.screen_starts`): a quick
   ICP and score of every start; the ``refine_top`` best distinct ones go on.
3. **Refinement**: one batched, coarse-to-fine point-to-plane ICP
   (:func:`~comreg_core.registration.geometry.icp.coarse_to_fine_icp`) of a seeded uniform
   subset of ``icp_points`` US points against ``target_points`` CT samples.
4. **Score** (mm, lower is better): the trimmed mean point-to-plane distance of the subset to
   the CT (the smallest ``1 - score_trim`` share).
5. **Polish and choice** (:func:`~comreg_core.registration.search.polish.choose_and_polish`):
   the best pose and those close to it (confidence below ``min_confidence``) polished on the
   exact mesh and re-scored; the best wins, ties (0.1 %,
   :func:`~comreg_core.registration.search.scoring.tied`) by generation order; a partial
   sweep's choice gets the slide probe.
6. **Confidence**: of the chosen pose over the best *distinct* one (the runner-up):
   ``max(score_b - score_a, 0) / max(score_b, score_floor_mm)``; ``ambiguous`` below
   ``min_confidence`` (``patch_min_confidence`` for a patch).
7. **Second round** for an ambiguous result: steps 1-3 on the grid interleaved with the first
   (turns and slides shifted by half a step), and the choice again among both rounds.
8. **A prior** (:mod:`comreg_core.registration.search.priors`): the starts around it, only
   poses within it polished, chosen or the runner-up, refined poses outside it pulled back
   onto its edge (``+clamped``).

Standalone (no network needed)::

    target = CTSurface("fibula.stl").cloud(20_000)
    result = search_poses(us_points, T_start, target)   # mm in, mm out
    result.T_ct_us, result.chosen, result.confidence, result.ambiguous

:class:`comreg_core.register.Registrar` runs it from the ``pca`` base (or the prior's); with a
network, the network's poses then compete as further starts
(:mod:`comreg_core.registration.search.network_starts`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from comreg_core.errors import InvalidGeometryError
from comreg_core.registration.search.advice import choice_evidence
from comreg_core.registration.search.config import SearchConfig
from comreg_core.registration.geometry.icp import coarse_to_fine_icp
from comreg_core.registration.search.polish import choose_and_polish
from comreg_core.registration.search.priors import Prior
from comreg_core.registration.search.screening import screen_starts
from comreg_core.registration.search.scoring import (Candidate, SearchResult, confidence_over,
                                                     score_poses)
from comreg_core.registration.geometry.extent import extent_share
from comreg_core.registration.geometry.tracked_nearest import NearestTracker
from comreg_core.registration.geometry.surface import SurfaceCloud, ct_length_mm, principal_frame
from comreg_core.transforms import (apply_transform, as_points, check_rigid, matmul,
                                    orthonormalize, rotate)


def rotation_about(centre: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """``(4, 4)`` rotation by ``angle`` (rad) about the line through ``centre`` along ``axis``."""
    from scipy.spatial.transform import Rotation

    axis = np.asarray(axis, dtype=np.float64)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - rotate(centre[None], R)[0]
    return T


def principal_axes_pose(points_us: np.ndarray, target: SurfaceCloud) -> np.ndarray:
    """``(4, 4)`` ``T_ct_us`` putting the principal frame of ``(N, 3)`` points (US frame, mm)
    onto the CT's: centroid onto centroid, the points' largest spread onto the CT's long axis,
    the others in order (up to the axes' signs, which the search's flips and turns cover)."""
    c_us, a_us = principal_frame(points_us)  # right-handed, like the CT's
    T = np.eye(4)
    T[:3, :3] = matmul(target.axes, a_us.T)
    T[:3, 3] = target.centre - rotate(c_us[None], T[:3, :3])[0]
    return T


def build_starts(T_start: np.ndarray, target: SurfaceCloud,
                 completion: np.ndarray | None = None,
                 config: SearchConfig | None = None, *,
                 T_coarse: np.ndarray | None = None,
                 grid_offset: float = 0.0, start_name: str = "network"
                 ) -> dict[str, np.ndarray]:
    """The start poses ``{name: T_ct_us (4, 4) mm}`` of the grid around each base (module
    docstring).

    Args:
        T_start: ``(4, 4)`` mm, the pose the alternatives are built around.
        target: the CT side (its principal frame is used without a completion).
        completion: ``(M, 3)`` mm, the completed bone in the US frame, or None.
        config: settings (default :class:`SearchConfig`).
        T_coarse: ``(4, 4)`` mm, the network's coarse pose (a base too), or None.
        grid_offset: shift of the rotations and slides, as a share of their steps (0.5: the
            grid interleaved with the default one; the bases themselves are not included).
        start_name: the name of ``T_start``'s base (``"pca"`` when the search runs without a
            network, from :func:`principal_axes_pose`).
    """
    cfg = config or SearchConfig()
    bases = {start_name: check_rigid(T_start)}
    if T_coarse is not None:
        bases["coarse"] = check_rigid(T_coarse)
    if completion is not None:
        bases["pca"] = principal_axes_pose(completion, target)
    starts: dict[str, np.ndarray] = {}
    slides = slide_offsets_mm(target, cfg) + grid_offset * cfg.slide_step_mm
    for base, T_base in bases.items():
        if completion is not None:
            centre, axes = principal_frame(apply_transform(T_base, completion))
        else:
            centre, axes = target.centre, target.axes
        flip = rotation_about(centre, axes[:, 1], math.pi)
        for flipped in (False, True):
            for k in range(cfg.shaft_rotations):
                angle = 360.0 * (k + grid_offset) / cfg.shaft_rotations
                G = rotation_about(centre, axes[:, 0], math.radians(angle))
                G = matmul(G, flip) if flipped else G
                name = base + ("+flip" if flipped else "") + (f"+rot{angle:g}" if angle else "")
                starts.update(slid_starts(name, matmul(G, T_base), slides, axes[:, 0]))
    return starts


def slid_starts(name: str, T: np.ndarray, slides: np.ndarray, axis: np.ndarray
                ) -> dict[str, np.ndarray]:
    """``{name+slideS: (4, 4)}``: the pose ``T`` (mm) followed by each slide ``S`` (mm) along
    the unit ``axis`` (the name unchanged for slide 0)."""
    poses = np.repeat(T[None], len(slides), axis=0)
    poses[:, :3, 3] += slides[:, None] * axis
    return {name + (f"+slide{slide:g}" if slide else ""): pose
            for slide, pose in zip(slides, poses)}


#: Orientations a patch gets (:func:`patch_orientation_starts`): scipy's icosahedral group
#: (``Rotation.create_group("I")``), every rotation within 45 deg of one of them.
PATCH_ORIENTATIONS = 60


def is_patch(points_us: np.ndarray, target: SurfaceCloud, config: SearchConfig) -> bool:
    """Whether ``(N, 3)`` US points (mm) are a patch of the bone: their extent share
    (:func:`~comreg_core.registration.geometry.extent.extent_share`) is under
    ``patch_max_share``."""
    return extent_share(points_us, ct_length_mm(target)) < config.patch_max_share


def patch_orientation_starts(points_us: np.ndarray, target: SurfaceCloud,
                             config: SearchConfig, grid_offset: float = 0.0
                             ) -> dict[str, np.ndarray]:
    """Starts ``{name: T_ct_us (4, 4) mm}`` that turn a patch (:func:`is_patch`) into
    :data:`PATCH_ORIENTATIONS` orientations spread evenly over all rotations (scipy's
    icosahedral group, applied to its principal-axes pose about the CT's centre), each slid
    along the CT's long axis like the other starts (``patch7+slide16``). ``grid_offset`` 0.5
    turns the whole group by half its spacing (about a fixed, generic axis) and shifts the
    slides by half a step: the retry round's starts. Empty when not a patch."""
    from scipy.spatial.transform import Rotation

    if not is_patch(points_us, target, config):
        return {}
    group = Rotation.create_group("I")  # PATCH_ORIENTATIONS
    if grid_offset:
        angles = group.magnitude()  # rad; the identity's is 0
        spacing = angles[angles > 1e-9].min()
        axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
        group = group * Rotation.from_rotvec(axis * spacing * grid_offset)
    T_base = principal_axes_pose(points_us, target)
    slides = slide_offsets_mm(target, config) + grid_offset * config.slide_step_mm
    starts: dict[str, np.ndarray] = {}
    for i, rotation in enumerate(group.as_matrix()):
        G = np.eye(4)
        G[:3, :3] = rotation
        G[:3, 3] = target.centre - rotate(target.centre[None], rotation)[0]
        name = f"patch{i}" + ("+turned" if grid_offset else "")
        starts.update(slid_starts(name, matmul(G, T_base), slides, target.axes[:, 0]))
    return starts


def slide_offsets_mm(target: SurfaceCloud, config: SearchConfig) -> np.ndarray:
    """Slides along the long axis tried per rotation (mm, 0 first, then by
    increasing size): multiples of ``slide_step_mm`` up to ``slide_range_mm`` (default half
    the CT's length along its long axis); just ``[0]`` when ``slide_step_mm`` is 0."""
    if config.slide_step_mm == 0:
        return np.zeros(1)
    reach = config.slide_range_mm
    if reach is None:
        reach = 0.5 * ct_length_mm(target)
    steps = np.arange(1, int(reach // config.slide_step_mm) + 1) * config.slide_step_mm
    return np.concatenate([[0.0], np.stack([steps, -steps], axis=1).ravel()])


def us_subset(points: np.ndarray, count: int) -> np.ndarray:
    """``min(count, N)`` of the ``(N, 3)`` US points (mm) for the candidates' ICP and score: a
    uniform subset (seed 0: the same points every run) kept in sweep order."""
    return points[us_subset_indices(len(points), count)]


def us_subset_indices(n: int, count: int) -> np.ndarray:
    """The indices of :func:`us_subset` of ``n`` points (all of them when ``n <= count``)."""
    if n <= count:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, count, replace=False))


def search_poses(us_points: np.ndarray, T_start: np.ndarray, target: SurfaceCloud,
                 completion: np.ndarray | None = None,
                 config: SearchConfig | None = None, *,
                 T_coarse: np.ndarray | None = None,
                 start_name: str = "network",
                 beam_origins: np.ndarray | None = None,
                 space: str = "LPS", prior: Prior | None = None) -> SearchResult:
    """Build, refine (one batched ICP) and score the start poses; keep the best.

    An ambiguous result gets a second round from the grid of starts
    interleaved with the first (rotations and slides shifted by half a step), and the choice
    is made again among the candidates of both rounds.

    Args:
        us_points: ``(N, 3)`` mm, the observed US bone points in their own (US) frame.
        T_start: ``(4, 4)`` mm, the start ``T_ct_us`` (the network's pose after its ICP).
        target: the CT side, :class:`SurfaceCloud` (e.g. ``from_mesh``).
        completion: ``(M, 3)`` mm, the completed bone in the US frame (the network's output),
            or None (the CT's principal frame stands in; no principal-axes solve).
        config: settings (default :class:`SearchConfig`; ``enabled`` is not looked at
            here: calling this function runs the stage).
        T_coarse: ``(4, 4)`` mm, the coarse pose before the network's ICP, or None.
        start_name: the name of ``T_start``'s base (see :func:`build_starts`).
        beam_origins: ``(N, 3)`` mm, where each US point's beam started (the probe's
            transducer element, US frame), or None. With them every score penalises poses
            under which the CT surface faces away from the probe (``facing_penalty_mm``).
        prior: a :class:`~comreg_core.registration.search.priors.Prior` (initial pose, landmarks; in
            the CT's space) or None: the starts are built around it and only poses within it
            can be chosen (:mod:`comreg_core.registration.search.priors`).
        space: the CT's patient space, for naming the bone's ends in the advice of an
            ambiguous result.

    Returns:
        :class:`SearchResult` (all mm).
    """
    cfg = config or SearchConfig()
    pts, completion, subset_mm, origins = _search_inputs(us_points, completion, beam_origins,
                                                         cfg)
    centroid = pts.mean(axis=0)  # the US centroid, placed by each pose
    patch = is_patch(pts, target, cfg)
    if patch:  # a short sweep needs a wider lead to be trusted
        cfg = replace(cfg, min_confidence=max(cfg.min_confidence, cfg.patch_min_confidence))
    T_network = check_rigid(T_start)
    pool = _Pool()
    within = None if prior is None else (lambda T: prior.allows(T, centroid))
    for offset in (0.0, 0.5):  # the second round only for an ambiguous result (step 7)
        grid = round_starts(pts, T_network, target, completion, cfg, T_coarse=T_coarse,
                            grid_offset=offset, start_name=start_name, prior=prior)
        pool.tried += len(grid)
        pool.add(*refine_starts(subset_mm, grid, target, cfg, keep_first=offset == 0.0,
                                origins=origins, within=within), prior, centroid)
        pool.scores = np.concatenate([pool.scores, score_poses(
            pool.poses[len(pool.scores):], subset_mm, target, cfg, origins=origins)])
        best, runner = choose_and_polish(subset_mm, centroid, pool.poses, pool.scores,
                                         pool.polishes, target, cfg, origins=origins,
                                         within=within)
        confidence = 1.0 if runner is None else float(
            confidence_over(pool.scores[best], pool.scores[runner], cfg))
        if confidence >= cfg.min_confidence:
            break
    return pool.result(best, runner, cfg, centroid, target, space, patch)


def _search_inputs(us_points, completion, beam_origins, cfg: SearchConfig):
    """The search's inputs checked: ``(points (N, 3), completion (M, 3) or None, the ICP and
    score subset (n, 3), its beam origins (n, 3) or None)``, all mm."""
    pts = as_points(us_points, "US points")
    if len(pts) < 6:  # 6 point-to-surface constraints for the 6 degrees of freedom
        raise InvalidGeometryError(f"The US cloud has {len(pts)} points; the search needs at "
                                   "least 6.", "Pass a denser US bone surface.")
    if completion is not None:
        completion = as_points(completion, "completion points")
        if len(completion) < 4:
            completion = None
    keep = us_subset_indices(len(pts), cfg.icp_points)
    origins = None
    if beam_origins is not None:
        origins = as_points(beam_origins, "beam origins")
        if origins.shape != pts.shape:
            raise InvalidGeometryError(f"{len(origins)} beam origins for {len(pts)} US points.",
                                       "Pass one beam origin per US point (or none).")
        origins = origins[keep]
    return pts, completion, pts[keep], origins


@dataclass
class _Pool:
    """The refined candidates of the search's rounds so far: names, starts, ``(K, 4, 4)``
    poses, ``(K,)`` scores and ICP residuals (mm), polish records; starts tried."""

    names: list[str] = field(default_factory=list)
    starts: list[np.ndarray] = field(default_factory=list)
    poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rmse: np.ndarray = field(default_factory=lambda: np.zeros(0))
    polishes: list[dict[str, Any] | None] = field(default_factory=list)
    tried: int = 0

    def add(self, names, starts, poses, rmse, prior: Prior | None, centroid) -> None:
        """One round's refined poses; with a ``prior``, those outside it also pulled back onto
        its edge (``+clamped``; no ICP residual)."""
        if prior is not None:
            out = np.flatnonzero(~prior.allows(poses, centroid))
            names = names + [names[i] + "+clamped" for i in out]
            starts = starts + [starts[i] for i in out]
            poses = np.concatenate([poses, prior.clamp(poses[out], centroid)])
            rmse = np.concatenate([rmse, np.full(len(out), np.nan)])
        self.names += names
        self.starts += starts
        self.poses = np.concatenate([self.poses, poses])
        self.rmse = np.concatenate([self.rmse, rmse])
        self.polishes += [None] * len(names)

    def result(self, best: int, runner: int | None,
               cfg: SearchConfig, centroid, target: SurfaceCloud, space: str,
               patch: bool) -> SearchResult:
        """The :class:`SearchResult` choosing ``best`` over ``runner``."""
        gap = None if runner is None else float(self.scores[runner] - self.scores[best])
        candidates = tuple(
            Candidate(n, self.starts[i], self.poses[i], float(self.scores[i]),
                      float(self.rmse[i]) if math.isfinite(self.rmse[i]) else float("nan"),
                      self.polishes[i]) for i, n in enumerate(self.names))
        confidence, ambiguous, advice = choice_evidence(self.poses, self.scores, best, runner,
                                                        cfg, centroid, target, space)
        return SearchResult(T_ct_us=self.poses[best], chosen=self.names[best],
                            runner_up=None if runner is None else self.names[runner],
                            score_gap_mm=gap, confidence=confidence, ambiguous=ambiguous,
                            candidates=candidates, starts_tried=self.tried, advice=advice,
                            patch=patch)


def round_starts(pts: np.ndarray, T_start: np.ndarray, target: SurfaceCloud,
                 completion: np.ndarray | None, config: SearchConfig, *,
                 T_coarse: np.ndarray | None, grid_offset: float, start_name: str,
                 prior: Prior | None = None) -> dict[str, np.ndarray]:
    """The start poses ``{name: T_ct_us (4, 4) mm}`` of one round (``grid_offset`` 0, then
    0.5): :func:`build_starts` and :func:`patch_orientation_starts`; with a ``prior``, its
    starts (:mod:`comreg_core.registration.search.priors`, step 1): around ``T_init``, or the usual
    rotations unslid, moved onto the landmarks; ``T_start`` first unmoved (the network's pose,
    or ``T_init`` without a network)."""
    if prior is not None and prior.T_init is not None:
        rotations = prior.init_rotations(pts.mean(axis=0), grid_offset)
    else:
        cfg = config if prior is None else replace(config, slide_step_mm=0.0)
        rotations = build_starts(T_start, target, completion, cfg, T_coarse=T_coarse,
                                 grid_offset=grid_offset, start_name=start_name)
        rotations.update(patch_orientation_starts(pts, target, cfg, grid_offset))
        if prior is None:
            return rotations
    first = {} if grid_offset or start_name == "pca" else {start_name: T_start}
    return {**first, **prior.starts(rotations, pts.mean(axis=0), target.centre, target.axes,
                                    config.slide_step_mm, grid_offset)}


def refine_starts(subset_mm: np.ndarray, grid: dict[str, np.ndarray], target: SurfaceCloud,
                  config: SearchConfig, *, keep_first: bool,
                  origins: np.ndarray | None = None, within=None
                  ) -> tuple[list[str], list[np.ndarray], np.ndarray, np.ndarray]:
    """Steps 2-3 of the module docstring for the start poses ``grid`` ``{name: (4, 4)}``:
    screen them (``keep_first``: the first one, the network's own pose, always goes on), refine
    the kept ones (``within``: see :func:`~comreg_core.registration.search.screening.screen_starts`). Returns their names, start poses,
    ``(K, 4, 4)`` refined poses (mm) and ``(K,)`` ICP residuals (mm)."""
    all_names = list(grid)
    kept, screened = screen_starts(subset_mm, np.stack(list(grid.values())), target, config,
                                   keep_first=keep_first, origins=origins, within=within)
    names = [all_names[i] for i in kept]
    refined, rmse = coarse_to_fine_icp(subset_mm, screened, NearestTracker(target),
                                       iterations=config.icp_iterations,
                                       schedule=config.icp_schedule,
                                       margin_mm=config.icp_margin_mm,
                                       trim_fraction=config.icp_trim)
    poses = np.stack([orthonormalize(T) for T in refined])
    return names, [grid[n] for n in names], poses, rmse
