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

import math
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.registration.geometry.metrics import rotation_error_deg
from comreg_core.registration.geometry.surface import principal_frame, spread_mm
from comreg_core.transforms import apply_transform, project

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
        hypotheses: a :class:`~comreg_core.registration.search.scoring.HypothesisResult`.
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
    spread = spread_mm(project(points_us - centre, axes[:, 0]))
    return float(np.clip(spread / max(ct_length_mm, 1e-9), 0.0, 1.0))


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


@dataclass(frozen=True)
class Calibration:
    """``p_correct`` of one CT (module docstring), as written to ``calibration.json``.

    Attributes:
        weights: ``(w0, w1, w2)``: intercept, margin, extent share (finite; ``w1, w2 >= 0``).
        sweeps: simulated sweeps it was fitted on (>= 1); correct_share: the share the search
            got right, in [0, 1].
        reliability: rows ``{"p_low", "p_high", "count", "predicted", "observed"}``.
        ok_probability: ``p_correct`` at or above which the verdict may be OK, in [0.5, 1].
        tolerance_mm, tolerance_deg: what "correct" means (> 0).
        ct_length_mm: the CT's length, for the extent share (mm, > 0).
        settings: how the sweeps were made (lengths, seed, ...), for the record.
        ct_fingerprint: the CT mesh it belongs to (``{"sha256", ...}``), or None.

    Checked on construction: a ValueError says which entry is missing, of the wrong type,
    not finite or out of range (:meth:`load` turns it into a :class:`ComRegError`).
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

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", _weights(self.weights))
        for name, low, high, low_open in _NUMBERS:
            object.__setattr__(self, name, _number(getattr(self, name), name, low, high,
                                                   low_open))
        if isinstance(self.sweeps, bool) or not isinstance(self.sweeps, int) \
                or self.sweeps < 1:
            raise ValueError(f"'sweeps' is {self.sweeps!r}, not a whole number of at least 1")
        if not isinstance(self.reliability, list):
            raise ValueError("'reliability' is not a list of rows")
        for row in self.reliability:
            _reliability_row(row)
        if not isinstance(self.settings, dict):
            raise ValueError("'settings' is not an object")
        _fingerprint(self.ct_fingerprint)

    def p_correct(self, margin: float, extent: float) -> float:
        """Estimated probability that a result with this margin and extent share is correct."""
        w0, w1, w2 = self.weights
        return float(_sigmoid(w0 + w1 * margin + w2 * extent))

    def check_ct(self, fingerprint: str, source: str | Path) -> None:
        """Refuse (:class:`ComRegError`) a calibration fitted on another CT mesh than the one
        whose :func:`~comreg_core.training.checkpoint.ct_fingerprint` sha256 is
        ``fingerprint``; ``source`` names the calibration in the message. A calibration
        without a fingerprint is taken as it is."""
        own = None if self.ct_fingerprint is None else self.ct_fingerprint["sha256"]
        if own is not None and own != fingerprint:
            raise ComRegError(f"The verdict calibration '{source}' was made for another CT "
                              f"mesh (CT fingerprint {own[:12]}..., not {fingerprint[:12]}... "
                              "of the CT registered to).",
                              "Calibrate on this CT ('comreg calibrate CT_MESH --out DIR') or "
                              "give that CT's calibration.")

    def to_json(self) -> dict[str, Any]:
        return {"format": CALIBRATION_FORMAT, **asdict(self)}

    def save(self, path: str | Path) -> Path:
        from comreg_core.io.json_files import write_json

        return write_json(self.to_json(), path)

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        """Read a ``calibration.json`` (``comreg calibrate``): a :class:`ComRegError` naming
        what is wrong when it is not one (not strict JSON, another format, a missing, unknown,
        non-finite or out-of-range entry, weights not three)."""
        from comreg_core.errors import CorruptFileError
        from comreg_core.io.json_files import NULL_REASONS, read_json

        try:
            data = read_json(path, "calibration file")
        except CorruptFileError as exc:
            raise ComRegError(exc.problem, _CALIBRATE_HINT) from None
        try:
            if not isinstance(data, dict):
                raise ValueError("it is not a JSON object")
            data = {key: value for key, value in data.items() if key != NULL_REASONS}
            if data.pop("format", None) != CALIBRATION_FORMAT:
                raise ValueError(f"its 'format' is not {CALIBRATION_FORMAT}")
            missing = [name for name in _REQUIRED if name not in data]
            unknown = sorted(set(data) - {f.name for f in fields(cls)})
            if missing or unknown:
                raise ValueError(f"it lacks '{missing[0]}'" if missing
                                 else f"it has an unknown entry '{unknown[0]}'")
            return cls(**data)
        except ValueError as exc:
            raise ComRegError(f"'{path}' is not a ComReg calibration file: {exc}.",
                              _CALIBRATE_HINT) from None


_CALIBRATE_HINT = "Make one with 'comreg calibrate CT_MESH --out DIR'."
#: Entries of a calibration without a default.
_REQUIRED = ("weights", "sweeps", "correct_share", "ct_length_mm")
#: ``(name, low, high, low excluded)`` of the calibration's single numbers.
_NUMBERS = (("correct_share", 0.0, 1.0, False), ("ct_length_mm", 0.0, math.inf, True),
            ("ok_probability", 0.5, 1.0, False), ("tolerance_mm", 0.0, math.inf, True),
            ("tolerance_deg", 0.0, math.inf, True))
_RELIABILITY_KEYS = ("p_low", "p_high", "count", "predicted", "observed")


def _number(value, name: str, low: float = -math.inf, high: float = math.inf,
            low_open: bool = False) -> float:
    """``value`` as a float when it is a finite number in ``[low, high]`` (``(low, high]``
    with ``low_open``), else a ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value):
        raise ValueError(f"'{name}' is {value!r}, not a finite number")
    if value < low or (low_open and value == low) or value > high:
        raise ValueError(f"'{name}' is {value:g}, outside {'(' if low_open else '['}{low:g}, "
                         f"{high:g}]")
    return float(value)


def _weights(weights) -> tuple[float, float, float]:
    """``(w0, w1, w2)`` as floats: three finite numbers, ``w1, w2 >= 0`` (module docstring)."""
    if not isinstance(weights, (list, tuple)):
        raise ValueError(f"'weights' is {weights!r}, not a list of 3 numbers")
    if len(weights) != 3:
        raise ValueError(f"'weights' has {len(weights)} numbers, not 3 (intercept, margin, "
                         "extent)")
    w0 = _number(weights[0], "weights[0]")
    return w0, _number(weights[1], "weights[1]", 0.0), _number(weights[2], "weights[2]", 0.0)


def _reliability_row(row) -> None:
    """Check one reliability row: its five entries, finite, shares in [0, 1]."""
    if not isinstance(row, dict) or set(row) != set(_RELIABILITY_KEYS):
        raise ValueError(f"a 'reliability' row is not {{{', '.join(_RELIABILITY_KEYS)}}}")
    for key in ("p_low", "p_high", "predicted", "observed"):
        _number(row[key], f"reliability {key}", 0.0, 1.0)
    if isinstance(row["count"], bool) or not isinstance(row["count"], int) or row["count"] < 0:
        raise ValueError(f"a 'reliability' count is {row['count']!r}, not a whole number")


def _fingerprint(fingerprint) -> None:
    """Check a calibration's ``ct_fingerprint``: None, or an object with a ``sha256`` of 64
    hexadecimal digits."""
    if fingerprint is None:
        return
    sha = fingerprint.get("sha256") if isinstance(fingerprint, dict) else None
    if not (isinstance(sha, str) and len(sha) == 64
            and all(c in "0123456789abcdef" for c in sha)):
        raise ValueError("its 'ct_fingerprint' has no 'sha256' of 64 hexadecimal digits")


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
