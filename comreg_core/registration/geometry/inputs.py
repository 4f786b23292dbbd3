"""The US cloud a registration is given: how many points it uses, and their beam origins."""

from __future__ import annotations

import logging

import numpy as np

from comreg_core.errors import InvalidGeometryError
from comreg_core.transforms import as_points

log = logging.getLogger(__name__)

#: The most US points a registration uses: a larger cloud is replaced by a uniform random
#: subset of this size (seeded, with a logged notice and a warning in the result), so 10 million
#: points cost about what 100,000 do. The network itself only sees a few thousand.
MAX_US_POINTS = 100_000


def limit_us_points(points: np.ndarray, seed: int = 0,
                    limit: int | None = None) -> np.ndarray:
    """``points`` unchanged up to ``limit`` (default :data:`MAX_US_POINTS`), else a uniform
    random subset of ``limit`` of them (drawn from ``seed``, original order kept), with a
    logged notice."""
    limit = MAX_US_POINTS if limit is None else int(limit)
    if len(points) <= limit:
        return points
    log.warning("%s", subset_notice(len(points), limit))
    keep = np.sort(np.random.default_rng(int(seed)).choice(len(points), limit, replace=False))
    return points[keep]


def beam_origins_for(beam_origins, n: int) -> np.ndarray:
    """``(n, 3)`` beam origins, or a clear error when they do not match the ``n`` points."""
    origins = as_points(beam_origins, "beam origins")
    if len(origins) != n:
        raise InvalidGeometryError(f"{len(origins)} beam origins for {n} US points.",
                                   "Pass one beam origin per US point (or none).")
    return origins


def subset_notice(given: int, used: int) -> str:
    """The warning that a cloud of ``given`` points was registered as a subset of ``used``."""
    return (f"The US cloud has {given:,} points; registered a uniform random subset of "
            f"{used:,} (the limit, comreg_core.registration.geometry.inputs.MAX_US_POINTS).")
