"""A sweep's extent along the bone: the one measure of how much of the bone US points span, and
the limits that use it.

The **extent** of US points ``(N, 3)`` (mm) is the length they span along an axis, from the
5th to the 95th percentile of their positions on it (:func:`extent_bounds_mm`,
:func:`spread_mm`: a few stray echoes do not lengthen a sweep), by default along their own
largest principal axis; its **share** is that over the CT bone's length
(:func:`~comreg_core.registration.geometry.surface.ct_length_mm`), in [0, 1]. Each limit below
is such a share:

- :data:`PATCH_MAX_SHARE`: the pose search treats a shorter sweep as a *patch* (starts over all
  rotations, a wider lead to trust; ``SearchConfig.patch_max_share``);
- :data:`SHORT_SWEEP_SHARE`: the verdict's *short sweep* (its best-fitting scale says nothing;
  ``comreg live`` checks that its two halves agree);
- :data:`SLIDE_PROBE_MAX_SHARE`: the slide probe of the search's choice, the extent measured
  along the CT's long axis once the chosen pose places the points.

Where a registered sweep lies along the CT's long axis (the advice's end to scan towards) is
its :func:`extent_bounds_mm` there.
"""

from __future__ import annotations

import numpy as np

from comreg_core.registration.geometry.surface import principal_frame
from comreg_core.transforms import as_points, project

#: Sweeps with an extent share under this are a *patch* to the pose search (the default of
#: ``SearchConfig.patch_max_share``).
PATCH_MAX_SHARE = 0.5
#: Sweeps with an extent share under this are *short* to the verdict.
SHORT_SWEEP_SHARE = 0.5
#: Sweeps spanning under this share of the CT's length along its long axis, as placed by the
#: chosen pose, get the slide probe (``SearchConfig.slide_probe_mm``); whole clouds do not.
SLIDE_PROBE_MAX_SHARE = 0.8


def extent_bounds_mm(along: np.ndarray) -> tuple[float, float]:
    """Where points lie along one axis, robust to stray points: the 5th and 95th percentiles
    (mm) of their positions ``along`` ``(N,)`` (mm) on that axis."""
    return float(np.percentile(along, 5)), float(np.percentile(along, 95))


def spread_mm(along: np.ndarray) -> float:
    """The length (mm) points span along one axis: from the 5th to the 95th percentile of
    their positions ``along`` ``(N,)`` (mm; :func:`extent_bounds_mm`)."""
    low, high = extent_bounds_mm(along)
    return high - low


def extent_mm(points: np.ndarray, axis: np.ndarray | None = None) -> float:
    """The extent (mm) of ``(N, 3)`` points (mm): their :func:`spread_mm` along the unit
    ``axis`` ``(3,)``, by default along their own largest principal axis."""
    pts = as_points(points, "points")
    if axis is None:
        centre, axes = principal_frame(pts)
        pts, axis = pts - centre, axes[:, 0]
    return spread_mm(project(pts, axis))


def extent_share(points: np.ndarray, ct_length_mm: float) -> float:
    """The extent of ``(N, 3)`` US points (mm, along their largest principal axis) over the CT's
    length ``ct_length_mm`` (mm), clipped to [0, 1]."""
    return float(np.clip(extent_mm(points) / max(ct_length_mm, 1e-9), 0.0, 1.0))
