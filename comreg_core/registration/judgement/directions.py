"""Directions on the CT in words: a slide or rotation axis against the bone's long axis, and
the patient side a direction points to (LPS)."""

from __future__ import annotations

import numpy as np

from comreg_core.registration.search.advice import end_names

#: A direction within this angle (deg) of the bone's long axis is "along"/"about" it.
ALONG_DEG = 30.0


def direction_words(kind: str, axis: np.ndarray, long_axis: np.ndarray) -> str:
    """``"along the bone's long axis"`` / ``"across the bone's long axis"`` for a ``"slide"``,
    ``"about the bone's long axis"`` / ``"tilting the bone's long axis"`` for a
    ``"rotation"`` axis ``(3,)`` (unit vectors)."""
    along = abs(float(np.dot(axis, long_axis))) >= np.cos(np.radians(ALONG_DEG))
    if kind == "slide":
        return "along the bone's long axis" if along else "across the bone's long axis"
    return "about the bone's long axis" if along else "tilting the bone's long axis"


def side_name(direction: np.ndarray) -> str:
    """The patient side (LPS) a ``(3,)`` direction points to most (e.g. ``"superior"``)."""
    return end_names(np.asarray(direction, dtype=np.float64))[0]
