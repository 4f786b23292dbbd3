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
correct. The pose's uncertainty (:mod:`~comreg_core.registration.judgement.assessment`) gives
``p_raw``; a per-CT calibration maps it to ``p_correct`` by an isotonic (non-decreasing) fit
of correctness on ``p_raw`` over simulated sweeps of this CT with realistic noise and drift,
registered by the same search (``comreg calibrate``; :mod:`comreg_core.evaluation.calibrate`).
The fit is shrunk towards ``p_correct = p_raw`` by :data:`IDENTITY_PRIOR_WEIGHT` pseudo sweeps
at each tenth of ``p_raw``, so that where the simulated sweeps are few, ``p_raw`` stands.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.registration.geometry.extent import extent_share
from comreg_core.registration.geometry.metrics import rotation_error_deg
from comreg_core.registration.search.priors import PRIOR_KINDS
from comreg_core.transforms import apply_transform

#: Clinical tolerance: target error over the sweep (mm) and rotation (deg).
TOLERANCE_MM = 4.0
TOLERANCE_DEG = 5.0
#: Scores below this (mm) are noise, not evidence (as the search's ``score_floor_mm``).
SCORE_FLOOR_MM = 0.05
#: US points used to compare two poses (a strided subset).
COMPARE_POINTS = 500
#: Weight of the pseudo sweep at each tenth of ``p_raw`` that says ``p_correct = p_raw``.
IDENTITY_PRIOR_WEIGHT = 2.0
#: ``p_correct`` at or above which a result may be OK (the verdict's limit).
OK_PROBABILITY = 0.95
#: Calibration file format version: 4 since the pose is judged about its own refit's optimum
#: and other basins bottom against bottom (:class:`~comreg_core.registration.judgement.profile.
#: ChosenBasin`), which changed ``p_raw``; format 3 (a frame counted as 4 independent points)
#: and 2 (as one point) map earlier ``p_raw``.
CALIBRATION_FORMAT = 4


def calibrated(p_raw: float, knots: dict[str, list[float]]) -> float:
    """``p_correct`` of ``p_raw`` by a calibration's ``knots`` (linear between them)."""
    return float(np.interp(p_raw, knots["p_raw"], knots["p_correct"]))


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


def clinical_competitor(search, points_us: np.ndarray,
                        allowed: Callable[[np.ndarray], bool] | None = None
                        ) -> dict[str, Any]:
    """The competitor of a search result (module docstring).

    Args:
        search: a :class:`~comreg_core.registration.search.scoring.SearchResult`.
        points_us: ``(n, 3)`` the US points the search registered (US frame, mm).
        allowed: which poses ``(4, 4)`` a prior allows (None: all).

    Returns:
        ``{"name", "score_mm", "margin", "distance_mm", "rotation_deg", "centroid_ct",
        "T_ct_us"}`` of the competitor (``name`` None and ``margin`` 1 without one);
        ``centroid_ct``: where it puts the US points' centroid in the CT (mm); ``T_ct_us``: its
        pose ``(4, 4)``.
    """
    chosen = search.best
    for h in sorted(search.candidates, key=lambda h: h.score_mm):
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
                "centroid_ct": [float(x) for x in centroid],
                "T_ct_us": [[float(x) for x in row] for row in h.T_ct_us]}
    return {"name": None, "score_mm": None, "margin": 1.0, "distance_mm": None,
            "rotation_deg": None, "centroid_ct": None, "T_ct_us": None}


@dataclass(frozen=True)
class Calibration:
    """``p_correct`` of one CT (module docstring), as written to ``calibration.json``.

    Attributes:
        knots: ``{"p_raw": [...], "p_correct": [...]}``: the map, linear between knots
            (``p_raw`` increasing from 0 to 1, ``p_correct`` non-decreasing, all in [0, 1]).
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

    knots: dict[str, list[float]]
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
        object.__setattr__(self, "knots", _knots(self.knots))
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
        if self.prior_kind not in PRIOR_KINDS:
            raise ValueError(f"'settings prior' is {self.prior_kind!r}, not one of "
                             f"{', '.join(PRIOR_KINDS)}")
        _fingerprint(self.ct_fingerprint)

    def p_correct(self, p_raw: float) -> float:
        """Estimated probability that a result with this ``p_raw`` is correct."""
        return calibrated(p_raw, self.knots)

    @property
    def prior_kind(self) -> str:
        """What its sweeps were registered within (``comreg calibrate --prior``, one of
        :data:`~comreg_core.registration.search.priors.PRIOR_KINDS`; ``"none"`` when the file
        does not say)."""
        return self.settings.get("prior", "none")

    def check_fits(self, fingerprint: str, prior_kind: str, source: str | Path) -> str | None:
        """Refuse (:class:`ComRegError`) a calibration fitted on another CT mesh than the one
        whose :func:`~comreg_core.training.checkpoint.ct_fingerprint` sha256 is
        ``fingerprint`` (one without a fingerprint is taken as it is), or for registrations
        that know more than this one, whose prior is of kind ``prior_kind`` (one fitted with
        landmarks over-rates a registration without them). Returns a one-line note when it
        was fitted for registrations that know less (its ``p_correct`` then under-rates this
        one), else None. ``source`` names the calibration in the messages."""
        own = None if self.ct_fingerprint is None else self.ct_fingerprint["sha256"]
        if own is not None and own != fingerprint:
            raise ComRegError(f"The verdict calibration '{source}' was made for another CT "
                              f"mesh (CT fingerprint {own[:12]}..., not {fingerprint[:12]}... "
                              "of the CT registered to).",
                              "Calibrate on this CT ('comreg calibrate CT_MESH --out DIR') or "
                              "give that CT's calibration.")
        fitted, used = PRIOR_KINDS.index(self.prior_kind), PRIOR_KINDS.index(prior_kind)
        redo = f"'comreg calibrate CT_MESH --prior {prior_kind} --out DIR'"
        if fitted > used:
            raise ComRegError(f"The verdict calibration '{source}' was made for registrations "
                              f"with a prior of kind '{self.prior_kind}', this one has "
                              f"'{prior_kind}': its p_correct would over-rate this "
                              "registration.", f"Calibrate for it ({redo}).")
        if fitted < used:
            return (f"The verdict calibration was made for registrations with a prior of kind "
                    f"'{self.prior_kind}', this one has '{prior_kind}': its p_correct "
                    f"under-rates this registration (calibrate for it: {redo}).")
        return None

    def to_json(self) -> dict[str, Any]:
        return {"format": CALIBRATION_FORMAT, **asdict(self)}

    def save(self, path: str | Path) -> Path:
        from comreg_core.io.json_files import write_json

        return write_json(self.to_json(), path)

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        """Read a ``calibration.json`` (``comreg calibrate``): a :class:`ComRegError` naming
        what is wrong when it is not one (not strict JSON, another format, a missing, unknown,
        non-finite or out-of-range entry, knots that do not rise)."""
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
            if data.get("format") == 1:
                raise ValueError("it maps the score margin of an older ComReg (format 1), not "
                                 "the pose's uncertainty; make it again")
            if data.get("format") in (2, 3):
                raise ValueError(f"it maps the pose's uncertainty of an older ComReg (format "
                                 f"{data['format']}, before the pose was judged about its "
                                 "refit's optimum); make it again")
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
_REQUIRED = ("knots", "sweeps", "correct_share", "ct_length_mm")
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


def _knots(knots) -> dict[str, list[float]]:
    """The calibration's ``knots`` checked (class docstring), as lists of floats."""
    if not isinstance(knots, dict) or set(knots) != {"p_raw", "p_correct"}:
        raise ValueError("'knots' is not {p_raw, p_correct}")
    x, y = knots["p_raw"], knots["p_correct"]
    if not (isinstance(x, list) and isinstance(y, list)) or len(x) != len(y) or len(x) < 2:
        raise ValueError("'knots' p_raw and p_correct are not two lists of the same length "
                         "(at least 2)")
    x = [_number(v, "knots p_raw", 0.0, 1.0) for v in x]
    y = [_number(v, "knots p_correct", 0.0, 1.0) for v in y]
    if x[0] != 0.0 or x[-1] != 1.0 or any(b <= a for a, b in zip(x, x[1:])):
        raise ValueError("'knots' p_raw does not rise from 0 to 1")
    if any(b < a for a, b in zip(y, y[1:])):
        raise ValueError("'knots' p_correct falls somewhere")
    return {"p_raw": x, "p_correct": y}


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


def fit_calibration(p_raw: np.ndarray, correct: np.ndarray, *, ct_length_mm: float,
                    settings: dict[str, Any] | None = None,
                    ct_fingerprint: dict[str, Any] | None = None) -> Calibration:
    """Fit :class:`Calibration` to ``(n,)`` ``p_raw`` and correctness (bool) of simulated
    registrations: isotonic regression (``scipy.optimize.isotonic_regression``) with the
    identity prior of the module docstring. Deterministic."""
    from scipy.optimize import isotonic_regression

    x = np.asarray(p_raw, np.float64)
    y = np.asarray(correct, np.float64)
    if len(x) != len(y) or len(x) == 0:
        raise ComRegError("A calibration needs at least one registered sweep.", "")
    tenths = np.linspace(0.05, 0.95, 10)
    xs = np.concatenate([x, tenths])
    ys = np.concatenate([y, tenths])
    ws = np.concatenate([np.ones(len(x)), np.full(len(tenths), IDENTITY_PRIOR_WEIGHT)])
    order = np.lexsort((ys, xs))
    fitted = isotonic_regression(ys[order], weights=ws[order]).x
    knots_x, knots_y = [0.0], [float(fitted[0])]
    for value in np.unique(xs[order]):
        inside = xs[order] == value
        level = float(np.average(fitted[inside], weights=ws[order][inside]))
        if 0.0 < value < 1.0:
            knots_x.append(float(value))
            knots_y.append(level)
    knots_x.append(1.0)
    knots_y.append(float(fitted[-1]))
    knots_y = np.maximum.accumulate(np.clip(knots_y, 0.0, 1.0)).tolist()
    calibration = Calibration(knots={"p_raw": knots_x, "p_correct": knots_y},
                              sweeps=len(x), correct_share=float(np.mean(y)),
                              ct_length_mm=ct_length_mm, settings=dict(settings or {}),
                              ct_fingerprint=ct_fingerprint)
    p = np.array([calibration.p_correct(v) for v in x])
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


def result_evidence(search, points_us: np.ndarray, ct_length_mm: float,
                    allowed: Callable[[np.ndarray], bool] | None = None
                    ) -> tuple[dict[str, Any], float]:
    """The competitor (:func:`clinical_competitor`) and the extent share
    (:func:`extent_share`) of a search result for ``(n, 3)`` US points: what
    :meth:`Calibration.p_correct` takes."""
    return (clinical_competitor(search, points_us, allowed),
            extent_share(points_us, ct_length_mm))
