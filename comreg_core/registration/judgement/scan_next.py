"""Where to scan next: the CT surface patch whose scan would most shrink the pose's bound.

Each patch (the CT's area-uniform samples in :data:`PATCH_MM` cells, on the side the sweep was
seen from when it has one) is scanned, in thought, at the sweep's own density of points and
noise: its point-to-plane information joins the fit's, and the 95 % target bound of the pose
with it (Fisher form, scaled to the current bound) ranks the patches.
"""

from __future__ import annotations

import weakref
from typing import Any

import numpy as np

from comreg_core.registration.judgement import uncertainty_kernels as kern
from comreg_core.registration.judgement.directions import side_name
from comreg_core.registration.judgement.uncertainty import (BLOCK_MM, FitMoments,
                                                            block_groups, target_error)
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


#: Each CT surface's patches (:func:`_surface_patches`), made once: they do not depend on the pose.
_PATCHES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _surface_patches(surface) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``[(samples (m, 3), normals (m, 3), unit mean normal (3,))]`` of every patch of the CT
    ``surface`` with at least :data:`MIN_PATCH_SAMPLES` samples (made once per surface)."""
    if surface not in _PATCHES:
        samples, normals = surface.samples(SCAN_SAMPLES)
        group, count = block_groups(samples, PATCH_MM)
        out = []
        for k in range(count):
            member = group == k
            if member.sum() < MIN_PATCH_SAMPLES:
                continue
            mean = normals[member].mean(axis=0)
            mean = mean / max(float(np.sqrt(np.sum(mean * mean))), 1e-12)
            out.append((samples[member], normals[member], mean))
        _PATCHES[surface] = out
    return _PATCHES[surface]


def _patches(surface, fit: FitMoments) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The :func:`_surface_patches` reachable from the side the sweep was seen from (all when
    it has no side)."""
    side = fit.normal_mean
    sided = float(np.sqrt(np.sum(side * side))) >= SIDED
    return [patch for patch in _surface_patches(surface)
            if not sided or project(patch[2][None], side)[0] > 0.0]


def scan_next(fit: FitMoments, covariance: np.ndarray, surface, long_axis: np.ndarray,
              bound_mm: float) -> dict[str, Any] | None:
    """``{"point_ct" (3,), "normal_ct" (3,), "bound_mm", "words"}``: the patch to scan next, its
    centre and normal (CT mm) and the 95 % bound the pose would have with it; None without a
    reachable patch."""
    per_sample_area = float(surface.face_areas.sum()) / SCAN_SAMPLES
    density = fit.inliers / (fit.blocks * BLOCK_MM ** 2)  # points per mm^2 of the sweep
    weight = per_sample_area * density
    now, _ = target_error(fit, fit.c * kern.inverse(fit.A), RANK_SAMPLES)
    best = None
    for samples, normals, mean in _patches(surface, fit):
        H, _, _ = kern.moments(samples, samples, normals, fit.centre, fit.scale,
                               np.zeros(len(samples), dtype=np.int64), 1)
        bound, _ = target_error(fit, fit.c * kern.inverse(fit.A + weight * H), RANK_SAMPLES)
        if best is None or bound < best[0]:
            best = (bound, samples.mean(axis=0), mean)
    if best is None:
        return None
    predicted = bound_mm * best[0] / max(now, 1e-12)
    return {"point_ct": [float(x) for x in best[1]], "normal_ct": [float(x) for x in best[2]],
            "bound_mm": float(predicted), "words": _words(best[1], best[2], fit, long_axis)}


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
