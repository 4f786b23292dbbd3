"""The verdict of a registration, from its files alone: ``OK`` or ``CHECK``, with reasons in words.

Inputs: the US points as received, the transform ``T_ct_us`` (mm) and the CT bone mesh; plus the
pose search's ``confidence`` / ``ambiguous`` when it ran. No ground truth, no
network. :func:`judge_registration` computes these figures (all distances in mm, exact
point-to-triangle distances of :class:`~comreg_core.registration.geometry.surface.CTSurface`):

- **residuals** of the registered US points to the CT surface: ``median_mm``, ``p90_mm`` and
  ``within_2mm`` (share of points at most 2 mm from the surface);
- **coverage**: the share of the CT surface area within 2 mm of a registered US point (area-
  uniform CT samples), i.e. how much of the bone the sweep touches;
- **refit**: starting from the given pose, point-to-plane ICP of (a seeded subset of) the US
  points to the mesh, once rigid and once with a free isotropic scale. ``refit_shift_mm`` is the
  RMS distance the rigid refit moves the points, ``refit_scale`` the scale the similarity refit
  settles on. A slide along the shaft or a pose turned about it leaves the points near the bone
  surface (small residuals) but is not where they fit best: the refit moves them back. A US
  calibration with a wrong scale fits best with a scale far from 1. These two catch what the
  residuals of a long, smooth bone cannot;
- **ambiguity**: with a per-patient calibration, ``p_correct``, the estimated probability that
  the pose is within 4 mm / 5 deg of the truth (:mod:`comreg_core.registration.judgement.calibration`;
  ``CHECK`` below its ``ok_probability``, 0.95); without one, the pose check's ``confidence``
  (< 0.3 = ``ambiguous``), when given.

``CHECK`` when any figure is beyond its threshold (:class:`VerdictThresholds`), else ``OK``.

How the thresholds were chosen: docs/calibration.md ("The verdict's fixed limits").
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from comreg_core.registration.geometry.icp import point_to_plane_icp
from comreg_core.registration.search.scoring import SCORE_TIE_SHARE
from comreg_core.registration.geometry.surface import as_surface
from comreg_core.transforms import apply_transform, as_points, check_rigid

#: Distance (mm) within which a registered US point counts as on the CT surface (and a CT
#: surface point as touched by the sweep).
NEAR_MM = 2.0
#: US points used by the refit (a seeded uniform subset of larger clouds).
REFIT_POINTS = 2000
#: CT surface samples for the coverage and the refit's closest points.
CT_SAMPLES = 50_000


@dataclass(frozen=True)
class VerdictThresholds:
    """Limits beyond which the verdict is ``CHECK`` (module docstring: how they were chosen).

    Attributes:
        max_median_mm: the median residual of the registered US points to the CT (mm).
        max_p90_mm: their 90th percentile (mm).
        min_within_2mm: the least share of US points within 2 mm of the CT surface.
        min_coverage: the least share of the CT surface area within 2 mm of a US point.
        max_refit_shift_mm: the RMS move (mm) of a rigid refit from the given pose.
        max_scale_error, min_scale_gain: ``CHECK`` when the best scale of the scale scan is
            farther from 1 than ``max_scale_error`` and fits at least ``min_scale_gain``
            (share) closer than scale 1.
        min_confidence: the least pose-check confidence (the hypotheses stage's own limit).
    """

    max_median_mm: float = 1.0
    max_p90_mm: float = 3.0
    min_within_2mm: float = 0.8
    min_coverage: float = 0.02
    max_refit_shift_mm: float = 5.0
    max_scale_error: float = 0.06
    min_scale_gain: float = 0.15
    min_confidence: float = 0.3


DEFAULT_THRESHOLDS = VerdictThresholds()


@dataclass
class Verdict:
    """``verdict`` ("ok" or "check"), ``reasons`` (sentences; empty when ok) and ``figures``
    (the measured values, keys with units: ``median_mm``, ``p90_mm``, ``within_2mm``,
    ``coverage``, ``refit_shift_mm``, ``refit_scale``, ``refit_scale_gain``, ``confidence``)."""

    verdict: str
    reasons: list[str]
    figures: dict[str, float | None] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.verdict == "ok"

    @property
    def headline(self) -> str:
        """``"Verdict: OK"`` or ``"Verdict: CHECK"``."""
        return f"Verdict: {self.verdict.upper()}"

    def to_json(self) -> dict:
        """The ``result.json`` fields: ``verdict``, ``verdict_reasons``, ``verdict_figures``."""
        return {"verdict": self.verdict, "verdict_reasons": list(self.reasons),
                "verdict_figures": dict(self.figures)}


def judge_registration(us_points, T_ct_us, ct_surface, *, confidence: float | None = None,
                       ambiguous: bool | None = None, p_correct: float | None = None,
                       ok_probability: float = 0.95, short_sweep: bool = False,
                       scale_scan: bool = True) -> Verdict:
    """The verdict of ``T_ct_us`` (``(4, 4)`` rigid, mm) for ``us_points`` (``(N, 3)`` mm, as
    received) on ``ct_surface`` (anything :func:`~comreg_core.registration.geometry.surface.as_surface`
    takes). ``confidence``/``ambiguous``: the pose check's, None when it did not run.
    ``p_correct``: the calibrated probability that the pose is correct, None without a
    calibration; given, it replaces ``confidence``/``ambiguous`` (``CHECK`` below
    ``ok_probability``) and the coverage check (whether the sweep pins the pose is what
    ``p_correct`` estimates). ``short_sweep``: a sweep spanning under half the CT's length,
    whose best-fitting scale says nothing (a short stretch of shaft fits at many scales: at
    their true pose 4 of 11 real 30-60 mm fibula runs fit 16-25 % closer scaled by 0.8-1.16), so
    the scale check is left out. ``scale_scan=False`` skips the refit's scale scan and so the scale
    check (``refit_scale`` and ``refit_scale_gain`` are None; a short sweep ignores them
    anyway): a live update's verdict, up to ~0.1 s sooner."""
    surface = as_surface(ct_surface)
    points = apply_transform(check_rigid(T_ct_us), as_points(us_points, "US points"))
    d = surface.distance(points)
    shift, scale, gain = refit(points, surface, scale_scan=scale_scan)
    figures = {"median_mm": float(np.median(d)), "p90_mm": float(np.percentile(d, 90)),
               "within_2mm": float(np.mean(d <= NEAR_MM)), "coverage": coverage(points, surface),
               "refit_shift_mm": shift, "refit_scale": scale, "refit_scale_gain": gain,
               "confidence": None if confidence is None else float(confidence),
               "p_correct": None if p_correct is None else float(p_correct)}
    reasons = _reasons(figures, bool(ambiguous), DEFAULT_THRESHOLDS, ok_probability, short_sweep)
    return Verdict("check" if reasons else "ok", reasons, figures)


def _reasons(f: dict, ambiguous: bool, th: VerdictThresholds, ok_probability: float,
             short_sweep: bool) -> list[str]:
    out = []
    if f["median_mm"] > th.max_median_mm or f["p90_mm"] > th.max_p90_mm:
        out.append(f"The US points lie off the CT bone: median {f['median_mm']:.1f} mm, 90 % "
                   f"within {f['p90_mm']:.1f} mm of its surface (limits {th.max_median_mm:g} "
                   f"and {th.max_p90_mm:g} mm).")
    if f["within_2mm"] < th.min_within_2mm:
        out.append(f"Only {100 * f['within_2mm']:.0f} % of the US points are within "
                   f"{NEAR_MM:g} mm of the CT bone (at least {100 * th.min_within_2mm:.0f} % "
                   "expected).")
    if f["coverage"] < th.min_coverage and f["p_correct"] is None:
        out.append(f"The sweep touches only {100 * f['coverage']:.1f} % of the CT bone surface "
                   f"(at least {100 * th.min_coverage:g} % needed to pin the pose).")
    if f["refit_shift_mm"] > th.max_refit_shift_mm:
        out.append(f"The US points fit the CT better {f['refit_shift_mm']:.0f} mm away from "
                   "this pose (slid along or turned about the bone?).")
    if (not short_sweep and f["refit_scale"] is not None
            and abs(f["refit_scale"] - 1.0) > th.max_scale_error
            and f["refit_scale_gain"] > th.min_scale_gain):
        out.append(f"The US points fit the CT {100 * f['refit_scale_gain']:.0f} % closer when "
                   f"scaled by {f['refit_scale']:.2f}: check the US probe calibration (image "
                   "spacing, speed of sound).")
    if f["p_correct"] is not None:
        if not f["p_correct"] >= ok_probability:  # a NaN p_correct is never OK
            out.append(f"The pose is within 4 mm / 5 deg of the truth with an estimated "
                       f"probability of only {f['p_correct']:.2f} (OK needs "
                       f"{ok_probability:g}): a clinically different pose fits the US points "
                       "nearly as well.")
    elif ambiguous or (f["confidence"] is not None and f["confidence"] < th.min_confidence):
        out.append("Ambiguous pose: another, clearly different pose fits the US points nearly as "
                   f"well (confidence {f['confidence'] if f['confidence'] is not None else 0:.2f}"
                   f", below {th.min_confidence:g}).")
    if f["confidence"] is not None and f["confidence"] < SCORE_TIE_SHARE:
        out.append("Tie: a clearly different pose scores the same as this one (within "
                   f"{100 * SCORE_TIE_SHARE:g} %): which of the two is kept is decided by their "
                   "order, not by the data.")
    return out


def coverage(points_ct: np.ndarray, surface, radius_mm: float = NEAR_MM) -> float:
    """Share of the CT surface area within ``radius_mm`` of a registered US point
    (:data:`CT_SAMPLES` area-uniform samples of ``surface``, a CTSurface)."""
    from pykdtree.kdtree import KDTree

    samples, _ = surface.samples(CT_SAMPLES)
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
    :data:`REFIT_POINTS` points (seeded subset). Without ``scale_scan`` only the rigid refit
    runs: ``(shift_mm, None, None)``."""
    pts = points_ct
    if len(pts) > REFIT_POINTS:
        pts = pts[np.random.default_rng(seed).choice(len(pts), REFIT_POINTS, replace=False)]
    cloud = surface.cloud(CT_SAMPLES)
    c = pts.mean(axis=0)
    unit = SCALES.index(1.0)
    moved = point_to_plane_icp(pts, np.eye(4), partial(cloud.match, max_distance=gate_mm),
                               iterations=iterations, trim_fraction=0.1,
                               tolerance_mm=REFIT_TOLERANCE_MM).T
    rigid = apply_transform(moved, pts)
    shift = float(np.sqrt(np.mean(np.sum((rigid - pts) ** 2, axis=1))))
    if not scale_scan:
        return shift, None, None
    scaled = [k for k in range(len(SCALES)) if k != unit]  # the unscaled cloud is fitted
    sources = np.stack([c + SCALES[k] * (rigid - rigid.mean(0)) for k in scaled])  # S-1 n 3
    fits = point_to_plane_icp(sources, np.tile(np.eye(4), (len(scaled), 1, 1)),
                              partial(cloud.match, max_distance=gate_mm),
                              iterations=iterations, trim_fraction=0.1,
                              tolerance_mm=REFIT_TOLERANCE_MM).T
    fitted = {unit: rigid, **{k: apply_transform(T, src)
                              for k, T, src in zip(scaled, fits, sources)}}
    scores = [_fit_score(fitted[k], cloud, gate_mm) for k in range(len(SCALES))]
    best = int(np.argmin(scores))
    score_1 = scores[unit]
    gain = 0.0 if score_1 <= 0 else max(0.0, 1.0 - scores[best] / score_1)
    return shift, float(SCALES[best]), float(gain)


#: The refit's ICP stops once an update moves no point by more than this (mm).
REFIT_TOLERANCE_MM = 1e-4


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
