"""Where to scan next: the CT surface patch whose scan would most shrink the pose's bound.

Each patch (the CT's area-uniform samples in :data:`PATCH_MM` cells, on the side the sweep was
seen from when it has one) is scanned, in thought, at the sweep's own density of points and
noise: its point-to-plane information joins the fit's, and the 95 % target bound of the pose
with it (Fisher form, scaled to the current bound) ranks the patches.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np

from comreg_core.registration.judgement import uncertainty_kernels as kern
from comreg_core.registration.judgement.directions import side_name
from comreg_core.registration.judgement.uncertainty import (BLOCK_MM, FitMoments,
                                                            block_groups, standard_normals,
                                                            target_error)
from comreg_core.transforms import project

#: CT surface samples the patches are made of, the patch size (mm) and the least samples a
#: patch needs.
SCAN_SAMPLES = 4000
PATCH_MM = 15.0
MIN_PATCH_SAMPLES = 6
#: Pose error draws used to rank the patches.
RANK_SAMPLES = 256
#: The sweep has a side when its mean CT normal is at least this long (else any face will do).
SIDED = 0.3


#: Each CT surface's patches (:class:`_Patches`), made once: they do not depend on the pose.
_PATCHES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class _Patches:
    """The CT surface's patches with at least :data:`MIN_PATCH_SAMPLES` samples, end to end:
    patch ``p`` is rows ``starts[p]:starts[p + 1]`` of ``samples`` ``(m, 3)`` (CT mm) and
    ``normals`` ``(m, 3)``; ``means`` ``(P, 3)`` its unit mean normal."""

    samples: np.ndarray
    normals: np.ndarray
    starts: np.ndarray
    means: np.ndarray


def _surface_patches(surface) -> _Patches:
    """The :class:`_Patches` of the CT ``surface`` (made once per surface)."""
    if surface not in _PATCHES:
        samples, normals = surface.samples(SCAN_SAMPLES)
        group, count = block_groups(samples, PATCH_MM)
        members = [m for m in (group == k for k in range(count))
                   if m.sum() >= MIN_PATCH_SAMPLES]
        means = []
        for member in members:
            mean = normals[member].mean(axis=0)
            means.append(mean / max(float(np.sqrt(np.sum(mean * mean))), 1e-12))
        sizes = [int(m.sum()) for m in members]
        _PATCHES[surface] = _Patches(
            np.concatenate([samples[m] for m in members] + [np.zeros((0, 3))]),
            np.concatenate([normals[m] for m in members] + [np.zeros((0, 3))]),
            np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
            np.array(means).reshape(-1, 3))
    return _PATCHES[surface]


def _reachable(patches: _Patches, fit: FitMoments) -> np.ndarray:
    """``(P,)`` ids of the patches reachable from the side the sweep was seen from (all when
    it has no side)."""
    side = fit.normal_mean
    if float(np.sqrt(np.sum(side * side))) < SIDED:
        return np.arange(len(patches.means), dtype=np.int64)
    return np.flatnonzero(project(patches.means, side) > 0.0).astype(np.int64)


def scan_next(fit: FitMoments, covariance: np.ndarray, surface, long_axis: np.ndarray,
              bound_mm: float) -> dict[str, Any] | None:
    """``{"point_ct" (3,), "normal_ct" (3,), "bound_mm", "words"}``: the patch to scan next, its
    centre and normal (CT mm) and the 95 % bound the pose would have with it; None without a
    reachable patch. The patches are ranked in one compiled pass
    (:func:`~.uncertainty_kernels.patch_target_errors`)."""
    per_sample_area = float(surface.face_areas.sum()) / SCAN_SAMPLES
    density = fit.inliers / (fit.blocks * BLOCK_MM ** 2)  # points per mm^2 of the sweep
    weight = per_sample_area * density
    now, _ = target_error(fit, fit.c * kern.inverse(fit.A), RANK_SAMPLES)
    patches = _surface_patches(surface)
    chosen = _reachable(patches, fit)
    if not len(chosen):
        return None
    largest = kern.patch_target_errors(patches.samples, patches.normals, patches.starts, chosen,
                                       fit.A, weight, fit.c, standard_normals()[:RANK_SAMPLES],
                                       fit.targets, fit.centre, fit.scale)
    bounds = np.percentile(largest, 95, axis=1)
    best = 0
    for i in range(1, len(bounds)):  # the first lowest, as one patch at a time
        if bounds[i] < bounds[best]:
            best = i
    rows = slice(patches.starts[chosen[best]], patches.starts[chosen[best] + 1])
    point, normal = patches.samples[rows].mean(axis=0), patches.means[chosen[best]]
    predicted = bound_mm * float(bounds[best]) / max(now, 1e-12)
    return {"point_ct": [float(x) for x in point], "normal_ct": [float(x) for x in normal],
            "bound_mm": float(predicted), "words": _words(point, normal, fit, long_axis)}


def _words(point: np.ndarray, normal: np.ndarray, fit: FitMoments, long_axis: np.ndarray
           ) -> str:
    """``"Scan the bone 85 mm towards its superior end from the sweep, on its face pointing
    anterior (CT point x, y, z mm)."``"""
    along = float(project((point - fit.centre)[None], long_axis)[0])
    where = ("beside the sweep" if abs(along) < PATCH_MM else
             f"{abs(along):.0f} mm towards its {side_name(long_axis * np.sign(along))} end "
             "from the sweep")
    xyz = ", ".join(f"{x:.0f}" for x in point)
    return f"Scan the bone {where}, on its face pointing {side_name(normal)} (CT point {xyz} mm)."
