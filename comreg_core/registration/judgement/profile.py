"""A profile of the fit along one direction: the pose offset by a set amount along a slide (or
about a rotation axis), the other five parameters refitted, and the cost it ends at.

A second basin the local information matrix cannot see (the same shaft fitting 30 mm further
along, a pose rolled about the shaft) shows up as an offset whose refitted cost is close to the
chosen pose's.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from comreg_core.registration.geometry.icp import strided
from comreg_core.registration.geometry.metrics import rotation_error_deg
from comreg_core.registration.judgement import uncertainty_kernels as kern
from comreg_core.registration.judgement.uncertainty import (INLIER_SIGMAS, TOLERANCE_DEG,
                                                            TOLERANCE_MM, FitMoments,
                                                            basin_weight, residuals,
                                                            truncated_cost)
from comreg_core.transforms import apply_transform, invert_rigid, matmul, rotate

#: Offsets profiled along the weakest slide (mm) and about the weakest rotation axis (deg),
#: each to both sides.
PROFILE_MM = (15.0, 35.0)
PROFILE_DEG = (15.0, 35.0)
#: Gauss-Newton steps of each refit with the offset held, then free (the basin it falls in),
#: and the US points they use (a strided subset).
PROFILE_ITERATIONS = 3
PROFILE_POINTS = 400
#: A profiled pose within this excess cost (chi-square, 1 degree of freedom, 95 %) of the chosen
#: one is as consistent with the data.
CHI2_95_1 = 3.841458820694124


def moved_pose(fit: FitMoments, xi: np.ndarray) -> np.ndarray:
    """``(4, 4)`` the move of the kernels' parameters ``xi`` ``(6,)``: a rotation ``xi[:3] /
    scale`` (rad) about ``fit.centre``, then the translation ``xi[3:]`` (mm)."""
    R = Rotation.from_rotvec(np.asarray(xi[:3], dtype=np.float64) / fit.scale).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = fit.centre - rotate(fit.centre[None], R)[0] + xi[3:]
    return T


def _complement(kind: str, axis: np.ndarray | None) -> np.ndarray:
    """``(6, 5)`` orthonormal basis of the parameters other than the held one (``(6, 6)``
    identity when ``kind`` is None: nothing held)."""
    if kind is None:
        return np.eye(6)
    u = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    u = u / np.sqrt(np.sum(u * u))
    v = np.cross(axis, u)
    held, free = (slice(3, 6), slice(0, 3)) if kind == "slide" else (slice(0, 3), slice(3, 6))
    B = np.zeros((6, 5))
    B[held, 0], B[held, 1] = u, v
    B[free, 2:] = np.eye(3)
    return B


def refit_holding(points_us: np.ndarray, starts: np.ndarray, surface, fit: FitMoments,
                  kind: str | None, axis: np.ndarray | None) -> np.ndarray:
    """``(K, 4, 4)``: each of the ``(K, 4, 4)`` poses ``starts`` refitted by point-to-plane
    Gauss-Newton with its ``kind`` (``"slide"``/``"rotation"``) component along the unit
    ``axis`` held (None: all free). The poses' closest points are found in one query per
    step (each pose's answer is what it would be alone)."""
    B = _complement(kind, axis)
    Bt = np.ascontiguousarray(B.T)
    prior = fit.prior / fit.c
    sub = strided(np.asarray(points_us, dtype=np.float64), PROFILE_POINTS)
    poses = [np.asarray(T, dtype=np.float64) for T in starts]
    active = list(range(len(poses)))
    for _ in range(PROFILE_ITERATIONS):
        if not active:
            break
        points = np.concatenate([apply_transform(poses[k], sub) for k in active])
        closest, normals, signed = residuals(points, surface)
        still = []
        for j, k in enumerate(active):
            rows = slice(j * len(sub), (j + 1) * len(sub))
            ok = np.isfinite(signed[rows])
            ok[ok] = np.abs(signed[rows][ok]) <= INLIER_SIGMAS * fit.noise_mm
            if ok.sum() < 12:
                continue  # this pose stays where it is
            H, _, g = kern.moments(points[rows][ok], closest[rows][ok], normals[rows][ok],
                                   fit.centre, fit.scale,
                                   np.zeros(int(ok.sum()), dtype=np.int64), 1)
            reduced = kern.product(kern.product(Bt, H + prior), B)
            step = -kern.product(kern.product(B, kern.inverse(reduced)),
                                 kern.product(Bt, g[:, None]))[:, 0]
            poses[k] = matmul(moved_pose(fit, step), poses[k])
            still.append(k)
        active = still
    return np.stack(poses)


def _offset(fit: FitMoments, kind: str, axis: np.ndarray, amount: float) -> np.ndarray:
    xi = np.zeros(6)
    if kind == "slide":
        xi[3:] = axis * amount
    else:
        xi[:3] = axis * np.radians(amount) * fit.scale
    return moved_pose(fit, xi)


def different_answer(T_a: np.ndarray, T_b: np.ndarray, targets_ct: np.ndarray) -> bool:
    """Whether pose ``T_a`` moves the ``(J, 3)`` targets (placed by ``T_b``, CT mm) beyond the
    clinical tolerance, or turns beyond it."""
    moved = apply_transform(matmul(T_a, invert_rigid(T_b)), targets_ct)
    far = float(np.sqrt(np.max(np.sum((moved - targets_ct) ** 2, axis=1))))
    return far > TOLERANCE_MM or rotation_error_deg(T_a, T_b) > TOLERANCE_DEG


def profile(points_us: np.ndarray, T_ct_us: np.ndarray, surface, fit: FitMoments,
            kind: str, axis: np.ndarray, base_cost: float) -> dict:
    """The profile along one direction: ``{"kind", "axis_ct", "offsets": [{"offset",
    "delta_cost", "basin_delta_cost", "different", "weight"}], "flat_to"}``; ``offset`` in mm
    (slide) or deg (rotation); ``delta_cost``: the excess cost with the offset held; then
    refitted free, the basin's excess cost, whether it is a different answer, and its
    ``weight`` (:func:`basin_weight`, 0 for the same answer); ``flat_to``: the
    largest offset up to which every profiled cost stays within :data:`CHI2_95_1`."""
    amounts = PROFILE_MM if kind == "slide" else PROFILE_DEG
    offsets = [sign * amount for sign in (1.0, -1.0) for amount in amounts]
    starts = np.stack([matmul(_offset(fit, kind, axis, offset), T_ct_us) for offset in offsets])
    held = refit_holding(points_us, starts, surface, fit, kind, axis)
    free = refit_holding(points_us, held, surface, fit, None, None)
    costs = truncated_cost(points_us, np.concatenate([held, free]), surface, fit) - base_cost
    rows = []
    for k, offset in enumerate(offsets):
        basin = costs[len(offsets) + k]
        different = different_answer(free[k], T_ct_us, fit.targets)
        rows.append({"offset": offset, "delta_cost": float(costs[k]),
                     "basin_delta_cost": float(basin), "different": different,
                     "weight": basin_weight(basin) if different else 0.0})
    flat_to = 0.0
    for sign in (1.0, -1.0):
        for row in sorted((r for r in rows if r["offset"] * sign > 0),
                          key=lambda r: abs(r["offset"])):
            if row["delta_cost"] > CHI2_95_1:
                break
            flat_to = max(flat_to, abs(row["offset"]))
    return {"kind": kind, "axis_ct": [float(x) for x in axis], "offsets": rows,
            "flat_to": flat_to}
