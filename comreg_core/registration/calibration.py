"""What a registration's evidence is worth: the clinical competitor and ``p_correct``.

**Clinical tolerance.** A registration is *correct* when it lies within 4 mm and 5 deg of the
truth (the partial-sweep criterion: RTE < 4 mm, RRE < 5 deg). Two poses are *the same answer*
when they place every US point within :data:`TOLERANCE_MM` of each other (the target error over
the CT surface under the sweep) and are rotated apart by at most :data:`TOLERANCE_DEG`; a
competing pose only counts against the chosen one when it is a different answer.

**The competitor** (:func:`clinical_competitor`) of a search's result is the best-scoring of its
refined poses that is a different answer from the chosen one (and, with a prior, allowed by
it); its **margin** is ``max(score_competitor - score_chosen, 0) / max(score_competitor,
floor)``, in [0, 1] (1 without a competitor): how clearly the US points prefer the chosen pose
over every clinically different one.

**p_correct** (:class:`Calibration`) is the estimated probability that the chosen pose is
correct, from two figures: the margin and the sweep's *extent share* (its largest spread over
the CT's length): ``p = sigmoid(w0 + w1 margin + w2 extent_share)`` with ``w1, w2 >= 0``, so
more margin or a longer sweep never lowers it. The weights are fitted per patient on simulated
sweeps of this CT registered by the same search (``comreg calibrate``;
:mod:`comreg_core.evaluation.calibrate`), with a prior that a tie is a coin flip: two pseudo
sweeps at margin 0, one correct and one not, at each extent (:data:`TIE_PRIOR_WEIGHT`), so
that a calibration set the search always gets right cannot teach that a tie is safe.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.registration.metrics import rotation_error_deg
from comreg_core.registration.surface import principal_frame, spread_mm
from comreg_core.transforms import apply_transform

#: Clinical tolerance: target error over the sweep (mm) and rotation (deg).
TOLERANCE_MM = 4.0
TOLERANCE_DEG = 5.0
#: Scores below this (mm) are noise, not evidence (as the search's ``score_floor_mm``).
SCORE_FLOOR_MM = 0.05
#: US points used to compare two poses (a strided subset).
COMPARE_POINTS = 500
#: Weight of each of the two pseudo sweeps per extent bin that say a tie is a coin flip.
TIE_PRIOR_WEIGHT = 2.0
#: ``p_correct`` at or above which a result may be OK (the verdict's limit).
OK_PROBABILITY = 0.95
#: Calibration file format version.
CALIBRATION_FORMAT = 1


def pose_difference(T_a: np.ndarray, T_b: np.ndarray, points_us: np.ndarray
                    ) -> tuple[float, float]:
    """``(max distance mm, rotation deg)`` between where two ``(4, 4)`` poses put ``(n, 3)`` US
    points (a strided subset of :data:`COMPARE_POINTS`)."""
    step = max(1, len(points_us) // COMPARE_POINTS)
    sub = points_us[::step]
    distance = float(np.linalg.norm(apply_transform(T_a, sub) - apply_transform(T_b, sub),
                                    axis=1).max())
    return distance, rotation_error_deg(T_a, T_b)


def same_answer(T_a: np.ndarray, T_b: np.ndarray, points_us: np.ndarray) -> bool:
    """Whether two poses are clinically the same answer (module docstring)."""
    distance, angle = pose_difference(T_a, T_b, points_us)
    return distance <= TOLERANCE_MM and angle <= TOLERANCE_DEG


def clinical_competitor(hypotheses, points_us: np.ndarray,
                        allowed: Callable[[np.ndarray], bool] | None = None
                        ) -> dict[str, Any]:
    """The competitor of a search result (module docstring).

    Args:
        hypotheses: a :class:`~comreg_core.registration.scoring.HypothesisResult`.
        points_us: ``(n, 3)`` the US points the search registered (US frame, mm).
        allowed: which poses ``(4, 4)`` a prior allows (None: all).

    Returns:
        ``{"name", "score_mm", "margin", "distance_mm", "rotation_deg", "centroid_ct"}`` of the
        competitor (``name`` None and ``margin`` 1 without one); ``centroid_ct``: where it puts
        the US points' centroid in the CT (mm).
    """
    chosen = hypotheses.best
    for h in sorted(hypotheses.hypotheses, key=lambda h: h.score_mm):
        if h.name == chosen.name or not math.isfinite(h.score_mm):
            continue
        if allowed is not None and not allowed(h.T_ct_us):
            continue
        distance, angle = pose_difference(chosen.T_ct_us, h.T_ct_us, points_us)
        if distance <= TOLERANCE_MM and angle <= TOLERANCE_DEG:
            continue
        margin = max(h.score_mm - chosen.score_mm, 0.0) / max(h.score_mm, SCORE_FLOOR_MM)
        centroid = apply_transform(h.T_ct_us, points_us.mean(axis=0)[None])[0]
        return {"name": h.name, "score_mm": float(h.score_mm), "margin": float(margin),
                "distance_mm": distance, "rotation_deg": angle,
                "centroid_ct": [float(x) for x in centroid]}
    return {"name": None, "score_mm": None, "margin": 1.0, "distance_mm": None,
            "rotation_deg": None, "centroid_ct": None}


def extent_share(points_us: np.ndarray, ct_length_mm: float) -> float:
    """The sweep's spread along its largest principal axis (5th-95th percentile, mm) over the
    CT's length, clipped to [0, 1]."""
    centre, axes = principal_frame(points_us)
    spread = spread_mm((points_us - centre) @ axes[:, 0])
    return float(np.clip(spread / max(ct_length_mm, 1e-9), 0.0, 1.0))


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


@dataclass(frozen=True)
class Calibration:
    """``p_correct`` of one CT (module docstring), as written to ``calibration.json``.

    Attributes:
        weights: ``(w0, w1, w2)``: intercept, margin, extent share.
        sweeps: simulated sweeps it was fitted on; correct_share: the share the search got right.
        reliability: rows ``{"p_low", "p_high", "count", "predicted", "observed"}``.
        ok_probability: ``p_correct`` at or above which the verdict may be OK.
        tolerance_mm, tolerance_deg: what "correct" means.
        ct_length_mm: the CT's length, for the extent share.
        settings: how the sweeps were made (lengths, seed, ...), for the record.
        ct_fingerprint: the CT mesh it belongs to.
    """

    weights: tuple[float, float, float]
    sweeps: int
    correct_share: float
    ct_length_mm: float
    reliability: list[dict[str, float]] = field(default_factory=list)
    ok_probability: float = OK_PROBABILITY
    tolerance_mm: float = TOLERANCE_MM
    tolerance_deg: float = TOLERANCE_DEG
    settings: dict[str, Any] = field(default_factory=dict)
    ct_fingerprint: dict[str, Any] | None = None

    def p_correct(self, margin: float, extent: float) -> float:
        """Estimated probability that a result with this margin and extent share is correct."""
        w0, w1, w2 = self.weights
        return float(_sigmoid(w0 + w1 * margin + w2 * extent))

    def to_json(self) -> dict[str, Any]:
        return {"format": CALIBRATION_FORMAT, **asdict(self)}

    def save(self, path: str | Path) -> Path:
        from comreg_core.io._files import atomic_output

        path = Path(path)
        with atomic_output(path) as tmp:
            tmp.write_text(json.dumps(self.to_json(), indent=2) + "\n", encoding="utf-8")
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        """Read a ``calibration.json`` (``comreg calibrate``), with a clear error when it is not
        one."""
        from comreg_core.io._files import require_input_file

        path = require_input_file(path, "calibration file")
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            if data.pop("format") != CALIBRATION_FORMAT:
                raise ValueError("format")
            data["weights"] = tuple(float(w) for w in data["weights"])
            return cls(**data)
        except (ValueError, KeyError, TypeError, AttributeError):
            raise ComRegError(f"'{path}' is not a ComReg calibration file.",
                              "Make one with 'comreg calibrate CT_MESH --out DIR'.") from None


def fit_calibration(margins: np.ndarray, extents: np.ndarray, correct: np.ndarray, *,
                    ct_length_mm: float, settings: dict[str, Any] | None = None,
                    ct_fingerprint: dict[str, Any] | None = None) -> Calibration:
    """Fit :class:`Calibration` to ``(n,)`` margins, extent shares and correctness (bool) of
    simulated registrations: penalised maximum likelihood (L-BFGS-B, ``w1, w2 >= 0``, a small
    ridge on ``w1, w2``), with the tie prior of the module docstring. Deterministic."""
    from scipy.optimize import minimize

    m = np.asarray(margins, np.float64)
    e = np.asarray(extents, np.float64)
    y = np.asarray(correct, np.float64)
    if not (len(m) == len(e) == len(y)) or len(m) == 0:
        raise ComRegError("A calibration needs at least one registered sweep.", "")
    bins = np.unique(np.round(np.quantile(e, [0.1, 0.5, 0.9]), 3))
    m = np.concatenate([m, np.zeros(2 * len(bins))])
    e = np.concatenate([e, np.repeat(bins, 2)])
    y = np.concatenate([y, np.tile([1.0, 0.0], len(bins))])
    w = np.concatenate([np.ones(len(margins)), np.full(2 * len(bins), TIE_PRIOR_WEIGHT)])
    X = np.stack([np.ones_like(m), m, e], axis=1)

    def loss(beta):
        z = X @ beta
        nll = np.sum(w * (np.logaddexp(0.0, z) - y * z))
        grad = X.T @ (w * (_sigmoid(z) - y))
        ridge = 1e-3 * (beta[1] ** 2 + beta[2] ** 2)
        return nll + ridge, grad + 2e-3 * np.array([0.0, beta[1], beta[2]])

    fit = minimize(loss, np.zeros(3), jac=True, method="L-BFGS-B",
                   bounds=[(None, None), (0.0, None), (0.0, None)])
    weights = tuple(float(b) for b in fit.x)
    calibration = Calibration(weights=weights, sweeps=len(margins),
                              correct_share=float(np.mean(correct)), ct_length_mm=ct_length_mm,
                              settings=dict(settings or {}), ct_fingerprint=ct_fingerprint)
    p = np.array([calibration.p_correct(a, b) for a, b in zip(margins, extents)])
    return replace(calibration, reliability=reliability_table(p, np.asarray(correct, bool)))


def reliability_table(p: np.ndarray, correct: np.ndarray,
                      edges=(0.0, 0.5, 0.8, 0.9, 0.95, 1.0)) -> list[dict[str, float]]:
    """Rows of predicted against observed correctness per ``p`` bin (empty bins left out)."""
    rows = []
    for low, high in zip(edges[:-1], edges[1:]):
        inside = (p >= low) & ((p < high) if high < 1.0 else (p <= high))
        if inside.any():
            rows.append({"p_low": low, "p_high": high, "count": int(inside.sum()),
                         "predicted": float(p[inside].mean()),
                         "observed": float(correct[inside].mean())})
    return rows


def result_evidence(hypotheses, points_us: np.ndarray, ct_length_mm: float,
                    allowed: Callable[[np.ndarray], bool] | None = None
                    ) -> tuple[dict[str, Any], float]:
    """The competitor (:func:`clinical_competitor`) and the extent share
    (:func:`extent_share`) of a search result for ``(n, 3)`` US points: what
    :meth:`Calibration.p_correct` takes."""
    return (clinical_competitor(hypotheses, points_us, allowed),
            extent_share(points_us, ct_length_mm))
