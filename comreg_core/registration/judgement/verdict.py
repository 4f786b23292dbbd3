"""The verdict of a registration, from its files alone: ``OK`` or ``CHECK``, with reasons in words.

Inputs: the US points as received, the transform ``T_ct_us`` (mm), the CT bone mesh, the pose's
uncertainty (:mod:`~comreg_core.registration.judgement.assessment`) and ``p_correct``. No ground
truth, no network. :func:`judge_registration` computes these figures (distances in mm, to the
triangles by :meth:`CTSurface.closest_faces
<comreg_core.registration.geometry.surface.CTSurface.closest_faces>`):

- **residuals** of the registered US points (a strided subset of at most
  :data:`RESIDUAL_POINTS`) to the CT surface: ``median_mm``, ``p90_mm``,
  ``within_2mm``, and relative to this case's own noise (the uncertainty's robust
  ``noise_mm``): ``within_noise``, the share within ``max(2 mm, 3 noise)``;
- **coverage**: the share of the CT surface area within 2 mm of a registered US point;
- **refit**: from the given pose, point-to-plane ICP of (a seeded subset of) the US points to
  the mesh, once rigid and over a scan of isotropic scales: ``refit_shift_mm`` (the RMS move of
  the rigid refit) and ``refit_scale``/``refit_scale_gain`` (a US calibration with a wrong scale
  fits best scaled);
- **the pose's uncertainty**: ``bound_mm`` (95 % bound of the target error over the surface
  under the sweep), ``p_raw`` and ``p_correct`` (the probability that the pose is within
  4 mm / 5 deg; calibrated per CT when a calibration is given).

``OK`` when ``p_correct >= ok_probability`` (0.95) and the fit checks pass: the points lie on
the bone for their own noise (the noise at most :attr:`VerdictThresholds.max_noise_mm`, at
least ``min_within_noise`` of them within 3 noise levels), the refit stays within 5 mm (the pose
is at the fit's optimum), no scale fits clearly better, and the pose is not tied with a
different one, nor one the search found nearly as good (its ``ambiguous``), unless the
uncertainty, which weighs that clinically different competitor in ``p_correct``, prefers the
chosen pose over it by at least the OK line's odds (:data:`RULED_OUT_WEIGHT`).

How the limits were chosen: docs/calibration.md ("The verdict's limits").
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from comreg_core.registration.geometry.icp import point_to_plane_icp, strided
from comreg_core.registration.judgement.calibration import OK_PROBABILITY
from comreg_core.registration.search.scoring import SCORE_TIE_SHARE
from comreg_core.registration.geometry.surface import as_surface
from comreg_core.registration.geometry.tracked_nearest import NearestTracker
from comreg_core.transforms import apply_transform, as_points, check_rigid

#: Distance (mm) within which a registered US point counts as on the CT surface (and a CT
#: surface point as touched by the sweep).
NEAR_MM = 2.0
#: US points used by the refit (a seeded uniform subset of larger clouds).
REFIT_POINTS = 2000
#: Of those, the points the scale scan fits at each scale (a strided subset: the scale found
#: for real and bundled whole clouds scaled by 0.85-1.15 is that of 2,000 points within one
#: step of :data:`SCALES`, 2026-12-05).
SCALE_POINTS = 500
#: US points whose residuals are measured (a strided subset of larger clouds: the quantiles
#: of 3,000 points are those of all within a few hundredths of a mm). Their distances are the
#: closest-point kernel's: on the bundled whole cloud the same median and 90th percentile as
#: VTK's exact ``vtkImplicitPolyDataDistance`` (45 of 3,000 points differ, by at most
#: 0.044 mm) in 2 ms instead of 12 (2026-12-05).
RESIDUAL_POINTS = 3000
#: CT surface samples for the refit's closest points.
CT_SAMPLES = 50_000
#: CT surface samples for the coverage (a figure, not a reason: 10,000 give the share of
#: 50,000 within 0.001 on the bundled whole cloud, in a fifth of the time).
COVERAGE_SAMPLES = 10_000
#: The search's ``ambiguous`` (a relative score margin, which noise dilutes: a whole cloud with
#: 0.43 mm of noise scores 0.24 mm at the truth and 0.39-0.41 mm flipped end to end, a margin
#: under the patch's 0.5) is overruled when the uncertainty weighs its clinically different
#: competitor, refitted, at most at the OK line's odds: ``exp(-dC / 2) <= (1 - p) / p`` for
#: ``p = OK_PROBABILITY`` (0.95), the fit preferring the chosen pose at least 19 to 1 (an
#: excess cost of 5.9 chi-square units or more). That weight is already in ``p_basin``, so a
#: competitor above it keeps ``p_raw`` under 0.95 by itself; below it, ``p_correct`` decides
#: (docs/calibration.md, the ambiguity at the OK line's odds).
RULED_OUT_WEIGHT = (1.0 - OK_PROBABILITY) / OK_PROBABILITY


@dataclass(frozen=True)
class VerdictThresholds:
    """Limits beyond which the verdict is ``CHECK`` (module docstring).

    Attributes:
        max_noise_mm: the robust noise (mm) of the US points about the CT beyond which they are
            not on this bone.
        min_within_noise: the least share of US points within ``max(2 mm, 3 noise)`` of it.
        max_refit_shift_mm: the RMS move (mm) of a rigid refit from the given pose: a right
            pose is at the fit's optimum, whatever the noise (the real fibula's recorded pose
            sits 3.3 mm from it).
        max_scale_error, min_scale_gain: ``CHECK`` when the best scale of the scale scan is
            farther from 1 than ``max_scale_error`` and fits at least ``min_scale_gain``
            (share) closer than scale 1.
    """

    max_noise_mm: float = 3.0
    min_within_noise: float = 0.8
    max_refit_shift_mm: float = 5.0
    max_scale_error: float = 0.06
    min_scale_gain: float = 0.15


DEFAULT_THRESHOLDS = VerdictThresholds()


@dataclass
class Verdict:
    """``verdict`` ("ok" or "check"), ``reasons`` (sentences; empty when ok), ``figures`` (the
    measured values, keys with units: ``median_mm``, ``p90_mm``, ``within_2mm``, ``noise_mm``,
    ``within_noise``, ``coverage``, ``refit_shift_mm``, ``refit_scale``,
    ``refit_scale_gain``, ``confidence``, ``bound_mm``, ``p_raw``, ``p_correct``),
    ``uncertainty`` (:meth:`~comreg_core.registration.judgement.assessment.Uncertainty.to_json`)
    and ``scan_next`` (where to scan to shrink it), None when not judged."""

    verdict: str
    reasons: list[str]
    figures: dict[str, float | None] = field(default_factory=dict)
    uncertainty: dict | None = None
    scan_next: dict | None = None

    @property
    def ok(self) -> bool:
        return self.verdict == "ok"

    @property
    def headline(self) -> str:
        """``"Verdict: OK"`` or ``"Verdict: CHECK"``."""
        return f"Verdict: {self.verdict.upper()}"

    def to_json(self) -> dict:
        """The ``result.json`` fields: ``verdict``, ``verdict_reasons``, ``verdict_figures``,
        ``p_correct``, ``uncertainty``, ``scan_next``."""
        return {"verdict": self.verdict, "verdict_reasons": list(self.reasons),
                "verdict_figures": dict(self.figures),
                "p_correct": self.figures.get("p_correct"), "uncertainty": self.uncertainty,
                "scan_next": self.scan_next}


def judge_registration(us_points, T_ct_us, ct_surface, *, uncertainty=None,
                       p_correct: float | None = None, confidence: float | None = None,
                       ambiguous: bool = False, ok_probability: float = OK_PROBABILITY,
                       short_sweep: bool = False, scale_scan: bool = True) -> Verdict:
    """The verdict of ``T_ct_us`` (``(4, 4)`` rigid, mm) for ``us_points`` (``(N, 3)`` mm, as
    received) on ``ct_surface`` (anything :func:`~comreg_core.registration.geometry.surface.as_surface`
    takes). ``uncertainty``: the pose's
    (:class:`~comreg_core.registration.judgement.assessment.Uncertainty`; None: too few points
    meet the CT, which is CHECK); ``p_correct``: from it; ``confidence``, ``ambiguous``: the
    pose search's (a tie is CHECK, and so is another clearly different pose it found nearly
    as good, unless :func:`competitor_ruled_out`). ``short_sweep``: a sweep spanning under half
    the CT's length, whose best-fitting scale says nothing, so the scale scan is left out;
    ``scale_scan=False`` skips it too (a live warm update); without it ``refit_scale`` and
    ``refit_scale_gain`` are None."""
    surface = as_surface(ct_surface)
    points = apply_transform(check_rigid(T_ct_us), as_points(us_points, "US points"))
    d = surface.closest_faces(strided(points, RESIDUAL_POINTS))[2]
    shift, scale, gain = refit(points, surface, scale_scan=scale_scan and not short_sweep)
    noise = None if uncertainty is None else uncertainty.noise_mm
    near = NEAR_MM if noise is None else max(NEAR_MM, 3.0 * noise)
    figures = {"median_mm": float(np.median(d)), "p90_mm": float(np.percentile(d, 90)),
               "within_2mm": float(np.mean(d <= NEAR_MM)), "noise_mm": noise,
               "within_noise": float(np.mean(d <= near)), "coverage": coverage(points, surface),
               "refit_shift_mm": shift, "refit_scale": scale, "refit_scale_gain": gain,
               "confidence": None if confidence is None else float(confidence),
               "bound_mm": None if uncertainty is None else uncertainty.bound_mm,
               "p_raw": None if uncertainty is None else uncertainty.p_raw,
               "p_correct": None if p_correct is None else float(p_correct)}
    reasons = _reasons(figures, uncertainty, DEFAULT_THRESHOLDS, ok_probability, short_sweep)
    competitor = None if uncertainty is None else uncertainty.competitor
    if (ambiguous and not any(r.startswith("Tie:") for r in reasons)
            and not competitor_ruled_out(competitor)):
        reasons.append("Ambiguous pose: the pose search found another, clearly different pose "
                       "that fits the US points nearly as well (confidence "
                       f"{figures['confidence'] or 0:.2f}).")
    return Verdict("check" if reasons else "ok", reasons, figures,
                   None if uncertainty is None else uncertainty.to_json(),
                   None if uncertainty is None else uncertainty.scan_next)


def competitor_ruled_out(competitor: dict | None) -> bool:
    """Whether the uncertainty's ``competitor`` record (``{"delta_cost", "weight",
    "same_basin"}``, None: none) weighs the search's clinically different pose at most
    :data:`RULED_OUT_WEIGHT` (0 when, refitted, it falls into the chosen pose's basin)."""
    return competitor is not None and competitor["weight"] <= RULED_OUT_WEIGHT


def ambiguity_words(ambiguous: bool, competitor: dict | None) -> str:
    """The search's ``ambiguous`` for a user, given the uncertainty's ``competitor`` record:
    "no", "YES: check the images", or that the fit rules the close pose out."""
    if not ambiguous:
        return "no"
    if not competitor_ruled_out(competitor):
        return "YES: check the images"
    if competitor.get("same_basin"):
        return "close in score, but refitted it falls into this pose's basin"
    return (f"close in score, but the fit rules it out (weight {competitor['weight']:.1g}, "
            f"at most {RULED_OUT_WEIGHT:.2g}: the fit favours this pose "
            f"{1.0 / RULED_OUT_WEIGHT:.0f} to 1 or more)")


def _reasons(f: dict, uncertainty, th: VerdictThresholds, ok_probability: float,
             short_sweep: bool) -> list[str]:
    if uncertainty is None:
        return ["Too few US points lie within 10 mm of the CT bone to judge the pose."]
    out = []
    if f["noise_mm"] > th.max_noise_mm or f["within_noise"] < th.min_within_noise:
        out.append(f"The US points lie off the CT bone: their noise about it is "
                   f"{f['noise_mm']:.1f} mm (at most {th.max_noise_mm:g} mm for bone) and "
                   f"{100 * f['within_noise']:.0f} % lie within 3 noise levels of its surface "
                   f"(at least {100 * th.min_within_noise:.0f} % expected).")
    if f["refit_shift_mm"] > th.max_refit_shift_mm:
        out.append(f"The US points fit the CT better {f['refit_shift_mm']:.0f} mm away from "
                   "this pose (slid along or turned about the bone?).")
    if (f["refit_scale"] is not None
            and abs(f["refit_scale"] - 1.0) > th.max_scale_error
            and f["refit_scale_gain"] > th.min_scale_gain):
        out.append(f"The US points fit the CT {100 * f['refit_scale_gain']:.0f} % closer when "
                   f"scaled by {f['refit_scale']:.2f}: check the US probe calibration (image "
                   "spacing, speed of sound).")
    if not f["p_correct"] >= ok_probability:  # a NaN p_correct is never OK
        other = (" A clinically different pose fits the US points nearly as well."
                 if uncertainty.p_basin < ok_probability else "")
        out.append(f"The pose is within 4 mm / 5 deg of the truth with an estimated "
                   f"probability of only {f['p_correct']:.2f} (OK needs {ok_probability:g}): "
                   f"{uncertainty.summary()}.{other}")
    if f["confidence"] is not None and f["confidence"] < SCORE_TIE_SHARE:
        out.append("Tie: a clearly different pose scores the same as this one (within "
                   f"{100 * SCORE_TIE_SHARE:g} %): which of the two is kept is decided by their "
                   "order, not by the data.")
    return out


def coverage(points_ct: np.ndarray, surface, radius_mm: float = NEAR_MM) -> float:
    """Share of the CT surface area within ``radius_mm`` of a registered US point
    (:data:`COVERAGE_SAMPLES` area-uniform samples of ``surface``, a CTSurface)."""
    from pykdtree.kdtree import KDTree

    samples, _ = surface.samples(COVERAGE_SAMPLES)
    d, _ = KDTree(np.ascontiguousarray(points_ct, dtype=np.float64)).query(
        np.ascontiguousarray(samples, dtype=np.float64), distance_upper_bound=radius_mm)
    return float(np.mean(d <= radius_mm))


#: Isotropic scales of the US points tried by the scale scan of :func:`refit`.
SCALES = tuple(round(1.0 + 0.04 * k, 2) for k in range(-5, 7))  # 0.80 ... 1.24


def refit(points_ct: np.ndarray, surface, *, iterations: int = 25, gate_mm: float = 10.0,
          seed: int = 0, scale_scan: bool = True
          ) -> tuple[float, float | None, float | None]:
    """``(shift_mm, scale, scale_gain)`` of refits from the registered points (``(N, 3)``, CT
    frame, mm). ``shift_mm``: the RMS move of the points under a rigid point-to-plane ICP to the
    CT. ``scale``: of the isotropic scales :data:`SCALES` (about the points' centroid, each then
    rigidly ICP-fitted), the one with the lowest trimmed mean point-to-plane distance;
    ``scale_gain``: by how much (share, 0-1) that distance is below the unscaled fit's. A scan,
    not a similarity ICP: on a partial shaft a free scale gets stuck near 1 (measured: 1.01 for
    a real sweep shrunk by 15 %) while the scan finds 1.18.
    The ICP (:func:`~comreg_core.registration.geometry.icp.point_to_plane_icp`, all scales in one batch)
    matches to the nearest of :data:`CT_SAMPLES` surface samples with their normals; pairs
    farther apart than ``gate_mm`` and the worst 10 % are left out; at most
    :data:`REFIT_POINTS` points (seeded subset), of which the scale scan uses
    :data:`SCALE_POINTS` (strided). Without ``scale_scan`` only the rigid refit
    runs: ``(shift_mm, None, None)``."""
    pts = points_ct
    if len(pts) > REFIT_POINTS:
        pts = pts[np.random.default_rng(seed).choice(len(pts), REFIT_POINTS, replace=False)]
    cloud = surface.cloud(CT_SAMPLES)
    c = pts.mean(axis=0)
    unit = SCALES.index(1.0)
    moved = point_to_plane_icp(pts, np.eye(4), NearestTracker(cloud, gate_mm),
                               iterations=iterations, trim_fraction=0.1,
                               tolerance_mm=REFIT_TOLERANCE_MM, patience=REFIT_PATIENCE).T
    rigid = apply_transform(moved, pts)
    shift = float(np.sqrt(np.mean(np.sum((rigid - pts) ** 2, axis=1))))
    if not scale_scan:
        return shift, None, None
    rigid = strided(rigid, SCALE_POINTS)  # the scan's share of the rigidly refitted points
    scaled = [k for k in range(len(SCALES)) if k != unit]  # the unscaled cloud is fitted
    sources = np.stack([c + SCALES[k] * (rigid - rigid.mean(0)) for k in scaled])  # S-1 n 3
    fits = point_to_plane_icp(sources, np.tile(np.eye(4), (len(scaled), 1, 1)),
                              NearestTracker(cloud, gate_mm),
                              iterations=iterations, trim_fraction=0.1,
                              tolerance_mm=REFIT_TOLERANCE_MM, patience=REFIT_PATIENCE).T
    fitted = {unit: rigid, **{k: apply_transform(T, src)
                              for k, T, src in zip(scaled, fits, sources)}}
    scores = [_fit_score(fitted[k], cloud, gate_mm) for k in range(len(SCALES))]
    best = int(np.argmin(scores))
    score_1 = scores[unit]
    gain = 0.0 if score_1 <= 0 else max(0.0, 1.0 - scores[best] / score_1)
    return shift, float(SCALES[best]), float(gain)


#: The refit's ICP stops once an update moves no point by more than this (mm), or once its RMS
#: has not fallen for :data:`REFIT_PATIENCE` iterations: the trimmed, gated fit jitters above
#: the tolerance and ran all 25 iterations on the bundled and real whole clouds; stopping at the
#: stall found the same scales for them scaled by 0.85-1.15, shifts within 0.07 mm, gains
#: within 0.02, in half the time (2026-12-05).
REFIT_TOLERANCE_MM = 1e-4
REFIT_PATIENCE = 3


def _fit_score(points: np.ndarray, cloud, gate_mm: float) -> float:
    """Mean point-to-plane distance (mm) of ``(n, 3)`` points to the nearest CT samples, pairs
    beyond ``gate_mm`` and the worst 10 % left out (``inf`` with fewer than 10 pairs)."""
    d, idx = cloud.nearest(points)
    ok = d <= gate_mm
    if ok.sum() < 10:
        return float("inf")
    r = np.abs(np.einsum("ij,ij->i", points[ok] - cloud.points[idx[ok]], cloud.normals[idx[ok]]))
    return float(r[r <= np.quantile(r, 0.9)].mean())


def with_prior_reasons(verdict, record: dict | None):
    """``verdict`` (:class:`Verdict`) with the prior's
    ``reasons`` (:func:`~comreg_core.registration.judgement.prior_reasons.prior_record`: a result at the edge of
    a tolerance, a clearly better pose outside the prior, no pose within it) appended and
    then ``"check"``; unchanged without a prior or reasons. The figures gain ``prior_at_edge``.
    """
    if not record:
        return verdict
    figures = {**verdict.figures, "prior_at_edge": bool(record.get("at_edge"))}
    reasons = [*verdict.reasons, *record.get("reasons", [])]
    return replace(verdict, verdict="check" if reasons else verdict.verdict, reasons=reasons,
                   figures=figures)
