"""Settings of the pose search (:mod:`comreg_core.registration.search.search`): the ``search``
section of a registration config (``comreg register/evaluate --config FILE``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from comreg_core.config import ConfigError, RetiredCheck, from_dict, load_config, require
from comreg_core.registration.geometry.extent import PATCH_MAX_SHARE

#: The polish stops once an update moves no US point by more than this (mm), or once its
#: RMS has stalled for :data:`~comreg_core.registration.geometry.icp.POLISH_PATIENCE`
#: iterations.
POLISH_TOLERANCE_MM = 0.01
#: US points and most iterations of the quick polish that compares poses tied with the best.
QUICK_POLISH_POINTS = 512
QUICK_POLISH_ITERATIONS = 30
#: A slid pose replaces the chosen one when its exact score is lower by at least this share
#: (less is noise: the same basin, polished from elsewhere).
SLIDE_PROBE_GAIN = 0.02


@dataclass(frozen=True)
class SearchConfig:
    """Settings of the pose search (steps in :mod:`comreg_core.registration.search.search`).

    The search always builds every kind of start (the network's pose, its coarse pose and the
    principal-axes solve of the completion as bases, each also flipped end to end; a patch's
    orientations over all rotations), always polishes the best pose and those tied with it on
    the mesh (when there is one), and always gives an ambiguous result a second round: the
    switches that turned these off were removed (:data:`RETIRED_KEYS`). What is left is the
    search itself and numbers a user sets to trade time for reach or to match
    their data; each says why.

    Attributes:
        enabled: run the search at all. False = the paper's plain pipeline (network + ICP only:
            ``comreg register --no-search``, the ``comreg-plain`` method), to reproduce the
            paper or to compare against it.
        shaft_rotations: rotations about the long axis per base, ``360 / shaft_rotations``
            deg apart, the base included (1 = only the base). Fewer for a faster search when
            the starts are known to be near the truth about the shaft; more when they may be
            far off (the second round halves the spacing only for ambiguous results).
        slide_step_mm: also try each rotation slid along its long axis in steps of
            this (mm; suffix ``+slide16`` etc.; 0 = no slides). Coarser (or 0) for a faster
            search when the sweep's place along the bone is known; finer when the bone's
            shaft has features shorter than 8 mm that fix the place.
        slide_range_mm: the largest slide (mm); None = half the CT's length. Smaller when the
            sweep's place along the bone is roughly known (fewer starts, fewer wrong places
            that fit as well).
        screen_points, screen_iterations, screen_score_points: the screening of all starts
            (:func:`~comreg_core.registration.search.screening.screen_starts`): US points and
            iterations of its quick ICP, US points of its quick score. More when the right
            basin is screened out on a hard bone (a near-symmetric shaft), fewer on a slow
            machine: the screening runs on every start (thousands) and dominates the time.
        refine_top: starts refined by the full ICP and scored (the network's own pose and
            the best screened distinct others); 0 = all of them, unscreened (only for a small
            grid: every start then gets the full ICP). More when the right basin ranks low
            after the screening, at the cost of a larger refinement batch.
        icp_points: US points in the search's ICP and score: a seeded uniform subset of
            the US cloud, kept in sweep order: it keeps the sweep's own share of false echoes
            (a farthest-point subset picks isolated false echoes first: on simulated fibula
            sweeps 10-15 % of it instead of ~3 %, more than ``icp_trim`` drops). More for a
            noisy or sparse sweep (less noise in the score), at linear cost
            (``tests/benchmarks/bench_search.py`` compares 2048 and 4096).
        target_points: area-uniform CT surface samples: the ICP target and the score's cloud.
            Denser for a small bone or a fine CT mesh (the samples' spacing should stay well
            under the features that tell poses apart), sparser for a very large bone.
        icp_iterations: iterations of the refinement's last stage, on all ``icp_points``
            (point-to-plane, :func:`~comreg_core.registration.geometry.icp.coarse_to_fine_icp`).
        icp_schedule: its coarse stages before, ``(US points, iterations)`` each. Both: more
            when refined poses stop short of their basin's minimum (a long bone, starts far
            off), fewer for speed.
        icp_margin_mm: after each stage only the poses whose residual (trimmed RMS, mm)
            is within this of the best go on (the others are far behind; this only saves
            time). Larger when the US cloud is noisy enough that the right pose's residual
            can trail a wrong one's by more than 1 mm before the last stage.
        icp_trim: share of the worst residuals left out of each ICP step.
        score_trim: share of the largest distances left out of the score. Both: the share of
            false echoes and of US points the CT does not explain; raise them for a noisier
            detector or a CT segmentation that misses part of the imaged bone.
        distinct_deg, distinct_mm: two refined poses are different poses when their rotations
            differ by more than ``distinct_deg`` or they place the US centroid more than
            ``distinct_mm`` apart; otherwise the later one is a duplicate. Set them to the
            error a procedure can tolerate: poses closer than that are not a competing pose.
        polish_top: at most this many poses are polished (each costs a polish on the mesh;
            raise it on a near-symmetric bone where more than 4 distinct poses tie).
        polish_max_distance_mm: pairs farther apart than this are left out of the polish (the
            false echoes). Raise it when the right pose's US points may lie further than 2 mm
            from the CT (a coarse segmentation, a swollen soft-tissue interface); lower it for
            clean data.
        polish_iterations: most iterations of a polish (it stops earlier once it moves no
            point by more than 0.01 mm; raise it if polishes end unconverged in
            ``result.json``).
        score_floor_mm: score differences are measured relative to at least this (mm) in the
            confidence: below it they are noise (step 6). Raise it for a coarse CT mesh or
            noisy US points, where near-perfect fits differ by more than 0.05 mm by chance.
        patch_max_share: a US cloud whose extent share (its 5th-95th percentile spread along
            its largest principal axis over the CT's length,
            :mod:`comreg_core.registration.geometry.extent`) is under this is a *patch* (a
            short sweep): it also gets 60 orientations spread evenly
            over all rotations (scipy's icosahedral group) as starts, each with the patch's
            centroid on the CT's centre and slid along the long axis (a short sweep's own
            axes say little about the bone's: on simulated 40-50 mm one-face fibula sweeps,
            without them the search missed the right basin in 2 of 20, with them in 0 of 20),
            and must lead by ``patch_min_confidence``. Raise it when sweeps longer than half
            the bone still run across it (the extra starts cost ~1 s), lower it to keep
            longer sweeps on the cheaper grid alone.
        patch_min_confidence: for a patch, a result is ambiguous below this confidence
            instead of ``min_confidence`` (the larger of the two counts). On the real fibula
            sweep cut into 30-60 mm runs, the pose ICP reaches from the recorded tracking
            scored worse than a wrong pose in 7 of 11 runs, by 4-42 % of its score (69 % in
            one run whose tracked pose fits badly): on real short sweeps a 30 % lead is no
            evidence. Whole clouds keep ``min_confidence``.
        facing_penalty_mm: with beam origins (a tracked sweep knows where the probe was for
            every echo), each US point whose matched CT surface faces away from its probe adds
            this to its distance in every score (screening, refinement, polish): a pose the
            beams could not have seen loses to one they could, whatever its fit; 0 = off, for
            beam origins that cannot be trusted (a doubtful probe calibration).
        slide_probe_mm: a partial sweep (spanning less than
            :data:`~comreg_core.registration.geometry.extent.SLIDE_PROBE_MAX_SHARE` of the CT's
            length) has its chosen pose polished again from this far along the
            CT's long axis, both ways, and the better-scoring pose kept: a shaft's surface
            slides under the points, and the search can stop in the basin next to the right
            one (on the real fibula sweep's first 29-30 frames, 3.8 mm off with a 16-17 % worse
            score than the probed pose, 0.7 mm from the pseudo ground truth). 0 = off.
        min_confidence: a result is ambiguous when its confidence is below this (a different
            pose scores within ``1 / (1 - min_confidence)`` times the chosen one's score, or
            within ``min_confidence * score_floor_mm`` of it). Higher flags more results for
            a visual check (fewer unflagged wrong poses), lower flags fewer; the verdict's
            ``min_confidence`` (:mod:`comreg_core.registration.judgement.verdict`) is the same 0.3.
    """

    enabled: bool = True
    shaft_rotations: int = 8
    slide_step_mm: float = 8.0
    slide_range_mm: float | None = None
    screen_points: int = 64
    screen_iterations: int = 20
    screen_score_points: int = 128
    refine_top: int = 12
    icp_points: int = 2048
    target_points: int = 20_000
    icp_iterations: int = 20
    icp_schedule: tuple[tuple[int, int], ...] = ((128, 30), (512, 30))
    icp_margin_mm: float = 1.0
    icp_trim: float = 0.1
    score_trim: float = 0.2
    distinct_deg: float = 10.0
    distinct_mm: float = 5.0
    polish_top: int = 4
    polish_max_distance_mm: float = 2.0
    polish_iterations: int = 100
    score_floor_mm: float = 0.05
    min_confidence: float = 0.3
    facing_penalty_mm: float = 5.0
    patch_max_share: float = PATCH_MAX_SHARE
    patch_min_confidence: float = 0.5
    slide_probe_mm: float = 5.0

    #: Removed switches (every registration folder's ``config.yaml`` written before carries
    #: them): dropped when they hold what the search now always does, refused otherwise.
    #: ``include_coarse: false`` is accepted too: ``Registrar.from_ct`` wrote it, where there
    #: is no coarse pose and it did nothing.
    RETIRED_KEYS: ClassVar[dict[str, RetiredCheck]] = {
        "axis_flips": lambda value, section: value is True,
        "include_coarse": lambda value, section: isinstance(value, bool),
        "principal_axes_solve": lambda value, section: value is True,
        "retry_ambiguous": lambda value, section: value is True,
        "polish": lambda value, section: value is True,
        "patch_axes": lambda value, section: type(value) is int and value == 1,
        "patch_orientations": lambda value, section: type(value) is int and value == 60,
        # ties now always go to the score (the network's pose wins exact ties only): on real
        # fibula runs the network's tie-break lost 1 of 22 that the search got (docs/results.md)
        "tie_break": lambda value, section: value in ("network", "score"),
    }

    def __post_init__(self) -> None:
        require(isinstance(self.enabled, bool), "search.enabled", "must be true or false")
        require(self.shaft_rotations >= 1, "search.shaft_rotations", "must be at least 1")
        require(self.shaft_rotations <= 36, "search.shaft_rotations",
                "must be at most 36 (10 deg apart)")
        require(self.slide_step_mm >= 0, "search.slide_step_mm", "must be 0 (off) or more")
        require(self.slide_range_mm is None or self.slide_range_mm >= 0,
                "search.slide_range_mm", "must be 0 or more (or null: half the CT length)")
        require(self.screen_points >= 6, "search.screen_points", "must be at least 6")
        require(self.screen_iterations >= 0, "search.screen_iterations", "must be 0 or more")
        require(self.screen_score_points >= 3, "search.screen_score_points",
                "must be at least 3")
        require(self.refine_top >= 0, "search.refine_top", "must be 0 (all) or more")
        require(self.icp_points >= 3, "search.icp_points", "must be at least 3")
        require(self.target_points >= 100, "search.target_points", "must be at least 100")
        require(self.icp_iterations >= 0, "search.icp_iterations", "must be 0 or more")
        require(all(p >= 6 and it >= 0 for p, it in self.icp_schedule),
                "search.icp_schedule", "needs at least 6 points and 0 or more iterations "
                "per stage")
        require(self.icp_margin_mm > 0, "search.icp_margin_mm", "must be positive")
        require(0.0 <= self.icp_trim < 1.0, "search.icp_trim", "must be in [0, 1)")
        require(0.0 <= self.score_trim < 1.0, "search.score_trim", "must be in [0, 1)")
        require(self.distinct_deg > 0, "search.distinct_deg", "must be positive")
        require(self.distinct_mm > 0, "search.distinct_mm", "must be positive")
        require(self.polish_top >= 1, "search.polish_top", "must be at least 1")
        require(self.score_floor_mm > 0, "search.score_floor_mm", "must be positive (mm)")
        require(self.polish_max_distance_mm > 0, "search.polish_max_distance_mm",
                "must be positive (mm)")
        require(self.slide_probe_mm >= 0, "search.slide_probe_mm", "must be >= 0")
        require(self.polish_iterations >= 1, "search.polish_iterations",
                "must be at least 1")
        require(0.0 <= self.min_confidence < 1.0, "search.min_confidence",
                "must be in [0, 1)")
        require(self.facing_penalty_mm >= 0, "search.facing_penalty_mm",
                "must be 0 (off) or more (mm)")
        require(0.0 < self.patch_max_share <= 1.0, "search.patch_max_share",
                "must be in (0, 1]")
        require(0.0 <= self.patch_min_confidence < 1.0, "search.patch_min_confidence",
                "must be in [0, 1)")


def as_search_config(value) -> SearchConfig:
    """``None``/``True`` -> the defaults, ``False`` -> turned off, a :class:`SearchConfig`
    or a mapping of its keys -> that config."""
    if value is None or value is True:
        return SearchConfig()
    if value is False:
        return SearchConfig(enabled=False)
    if isinstance(value, SearchConfig):
        return value
    if isinstance(value, dict):
        return from_dict(SearchConfig, value, "search")
    raise ConfigError(f"Cannot use a {type(value).__name__} as the search setting.",
                      "Pass True, False, a SearchConfig or a mapping of its keys.")


@dataclass(frozen=True)
class RegisterConfig:
    """The settings of ``comreg register --config FILE``: section ``search:`` (the pose
    search, :class:`SearchConfig`; a file's ``hypotheses:``, its older name, is read as
    ``search:``). A registration's own ``config.yaml`` is such a file (its ``inputs:`` record
    is ignored when it is read back)."""

    search: SearchConfig = field(default_factory=SearchConfig)


#: Sections read under their new name: ``hypotheses:`` is the pose search's older name.
RENAMED_SECTIONS = {"hypotheses": "search"}


def load_register_config(path: str | Path | None = None,
                         overrides: dict | None = None) -> RegisterConfig:
    """:class:`RegisterConfig` from a YAML file (None: the defaults) and ``overrides``."""
    return load_config(RegisterConfig, path, overrides, ignore=("inputs",),
                       renamed=RENAMED_SECTIONS)
