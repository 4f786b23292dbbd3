"""A profile of the fit along one direction: the pose offset by a set amount along a slide (or
about a rotation axis), the other five parameters refitted, and the cost it ends at.

A second basin the local information matrix cannot see (the same shaft fitting 30 mm further
along, a pose rolled about the shaft) shows up as an offset whose refitted cost is close to the
chosen pose's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from comreg_core.registration.geometry.icp import strided
from comreg_core.registration.geometry.metrics import rotation_angles_deg
from comreg_core.registration.judgement import uncertainty_kernels as kern
from comreg_core.registration.judgement.uncertainty import (INLIER_SIGMAS, TOLERANCE_DEG,
                                                            TOLERANCE_MM, FitMoments,
                                                            basin_weight, residuals,
                                                            truncated_cost)
from comreg_core.transforms import (apply_transform, invert_rigid, matmul, rotate,
                                   symmetric_eigen3)

#: Offsets profiled along the weakest slide (mm) and about the weakest rotation axis (deg),
#: each to both sides.
PROFILE_MM = (15.0, 35.0)
PROFILE_DEG = (15.0, 35.0)
#: How far (mm, at the farthest target) the neighbour probe (:func:`weigh_basins`) moves the
#: chosen pose: past the 4 mm tolerance, so that a basin just beyond it is reached.
NEIGHBOUR_MM = 6.0
#: Gauss-Newton steps of each refit with the offset held, then free (the basin it falls in),
#: and the US points they use (a strided subset).
PROFILE_ITERATIONS = 3
PROFILE_POINTS = 400
#: Gauss-Newton steps of the chosen pose's own refit (:class:`ChosenBasin`): to the bottom of
#: its basin (3 steps left the refit of a real prefix from frame 30, 135 mm of bone, 3.4 mm
#: short of it and 7.7 cost units above it).
HOME_ITERATIONS = 12
#: A refit whose Gauss-Newton step moves no parameter (mm; rotations in mm at the fit's
#: scale) by more than this has converged.
CONVERGED_MM = 0.01
#: A refitted pose within the tolerance of the chosen pose's own refit is another answer only
#: when it fits better than that refit by more than this (units of ``c``: one sigma).
CLEARLY_BETTER = 1.0
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


def move_parameters(fit: FitMoments, move: np.ndarray) -> np.ndarray:
    """``(6,)`` the kernels' parameters of a rigid ``move`` ``(4, 4)``: the inverse of
    :func:`moved_pose`."""
    R = move[:3, :3]
    xi = np.empty(6)
    xi[:3] = Rotation.from_matrix(R).as_rotvec() * fit.scale
    xi[3:] = move[:3, 3] - fit.centre + rotate(fit.centre[None], R)[0]
    return xi


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


@dataclass(frozen=True)
class Refit:
    """One refit for :func:`refit_many`: from ``start`` ``(4, 4)``, with its ``kind``
    (``"slide"``/``"rotation"``) component along the unit ``axis`` held (None: all free), at
    most ``iterations`` Gauss-Newton steps."""

    start: np.ndarray
    kind: str | None = None
    axis: np.ndarray | None = None
    iterations: int = PROFILE_ITERATIONS


def refit_many(points_us: np.ndarray, refits: Sequence[Refit], surface,
               fit: FitMoments) -> np.ndarray:
    """``(K, 4, 4)``: each of the ``K`` :class:`Refit` run by point-to-plane Gauss-Newton on a
    strided subset of :data:`PROFILE_POINTS` US points (a pose whose step moves no parameter
    by more than :data:`CONVERGED_MM` stops). The active poses' closest points are found in one
    query per step; each pose's answer is what it would be alone, bit for bit."""
    bases = [_complement(r.kind, r.axis) for r in refits]
    transposed = [np.ascontiguousarray(B.T) for B in bases]
    prior = fit.prior / fit.c
    sub = strided(np.asarray(points_us, dtype=np.float64), PROFILE_POINTS)
    poses = [np.asarray(r.start, dtype=np.float64) for r in refits]
    active = [k for k, r in enumerate(refits) if r.iterations > 0]
    step_count = 0
    while active:
        points = np.concatenate([apply_transform(poses[k], sub) for k in active])
        closest, normals, signed = residuals(points, surface)
        still = []
        step_count += 1
        for j, k in enumerate(active):
            rows = slice(j * len(sub), (j + 1) * len(sub))
            ok = np.isfinite(signed[rows])
            ok[ok] = np.abs(signed[rows][ok]) <= INLIER_SIGMAS * fit.noise_mm
            if ok.sum() < 12:
                continue  # this pose stays where it is
            H, _, g = kern.moments(points[rows][ok], closest[rows][ok], normals[rows][ok],
                                   fit.centre, fit.scale,
                                   np.zeros(int(ok.sum()), dtype=np.int64), 1)
            B, Bt = bases[k], transposed[k]
            reduced = kern.product(kern.product(Bt, H + prior), B)
            step = -kern.product(kern.product(B, kern.inverse(reduced)),
                                 kern.product(Bt, g[:, None]))[:, 0]
            poses[k] = matmul(moved_pose(fit, step), poses[k])
            if np.max(np.abs(step)) > CONVERGED_MM and step_count < refits[k].iterations:
                still.append(k)  # else converged or done: it stays where it is
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
    clinical tolerance, or turns beyond it (both ``(4, 4)`` rigid, not checked: the judge's own
    poses)."""
    moved = apply_transform(matmul(T_a, invert_rigid(T_b, check=False)), targets_ct)
    far = float(np.sqrt(np.max(np.sum((moved - targets_ct) ** 2, axis=1))))
    turned = float(rotation_angles_deg(np.asarray(T_a, dtype=np.float64)[None, :3, :3],
                                       np.asarray(T_b, dtype=np.float64)[:3, :3])[0])
    return far > TOLERANCE_MM or turned > TOLERANCE_DEG


@dataclass(frozen=True)
class ChosenBasin:
    """The chosen pose ``pose`` ``(4, 4)``, its free refit ``home`` ``(4, 4)`` (the bottom of its
    basin by the judge's own cost: the search polished ``pose`` by another measure) and
    ``cost``, the lower :func:`truncated_cost` of the two (None where nothing is weighed
    against it: a live warm update's judgement). Other basins are weighed against ``cost``,
    bottom against bottom: against the pose as given, a refitted competitor gained 1-11 units
    for nothing on the real fibula's unions."""

    pose: np.ndarray
    home: np.ndarray
    cost: float | None

    def offset(self, fit: FitMoments) -> np.ndarray:
        """``(6,)`` the kernels' parameters of the move from ``pose`` to ``home``: where the
        data put the pose, seen from the pose judged."""
        return move_parameters(fit, matmul(self.home, invert_rigid(self.pose)))

    @classmethod
    def of(cls, points_us: np.ndarray, T_ct_us: np.ndarray, surface,
           fit: FitMoments) -> ChosenBasin:
        """The chosen basin of ``T_ct_us`` alone (:func:`weigh_basins` with nothing to
        weigh)."""
        return weigh_basins(points_us, T_ct_us, surface, fit).chosen

    def other_answer(self, T: np.ndarray, cost: float, targets_ct: np.ndarray) -> bool:
        """Whether a refitted pose ``T`` ``(4, 4)`` of ``cost`` is another answer than the
        chosen one: a :func:`different_answer` from ``pose``, and either from ``home`` too or
        fitting better than it by more than :data:`CLEARLY_BETTER` (a better minimum near
        the chosen basin's bottom is no part of it: on the real fibula from frame 30, a pose
        4.9 mm from the truth had its better minimum 0.9 mm from it, 3.5 mm from its own)."""
        if not different_answer(T, self.pose, targets_ct):
            return False
        return (different_answer(T, self.home, targets_ct)
                or cost < self.cost - CLEARLY_BETTER)


@dataclass(frozen=True)
class Basins:
    """What :func:`weigh_basins` found: the ``chosen`` basin, the ``profiles`` of the weakest
    directions (:func:`_profile_record` each), the ``neighbours`` (:func:`_neighbour_records`)
    and the search's ``competitor`` (:func:`_competitor_record`, None: none given)."""

    chosen: ChosenBasin
    profiles: list[dict[str, Any]] = field(default_factory=list)
    neighbours: list[dict[str, Any]] = field(default_factory=list)
    competitor: dict[str, Any] | None = None


def weigh_basins(points_us: np.ndarray, T_ct_us: np.ndarray, surface, fit: FitMoments, *,
                 directions: Sequence[tuple[str, np.ndarray]] = (), neighbours: bool = False,
                 competitor: np.ndarray | None = None, costed: bool = True) -> Basins:
    """The chosen pose ``T_ct_us`` ``(4, 4)`` refitted to the bottom of its basin
    (:class:`ChosenBasin`, :data:`HOME_ITERATIONS` steps), and weighed against it, each refitted
    (:func:`refit_many`, all in one batch: the same bits as one by one): the profiles of
    ``directions`` (``(kind, unit axis (3,))`` each: :data:`PROFILE_MM` / :data:`PROFILE_DEG`
    held, then free), the neighbour probe (``neighbours``: :data:`NEIGHBOUR_MM` along the
    information's weakest axes, free) and the search's clinically different ``competitor``
    ``(4, 4)`` (free). ``costed=False`` (nothing to weigh): the chosen basin's ``cost`` is None
    and no cost is computed."""
    T_ct_us = np.asarray(T_ct_us, dtype=np.float64)
    if competitor is not None:
        competitor = np.asarray(competitor, dtype=np.float64)
    refits = [Refit(T_ct_us, iterations=HOME_ITERATIONS)]
    plans = []
    for kind, axis in directions:
        offsets = _profile_offsets(kind)
        refits += [Refit(matmul(_offset(fit, kind, axis, offset), T_ct_us), kind, axis)
                   for offset in offsets]
        plans.append((kind, axis, offsets))
    probes = _neighbour_starts(fit, T_ct_us) if neighbours else []
    refits += [Refit(T) for T in probes]
    if competitor is not None:
        refits.append(Refit(competitor))
    done = refit_many(points_us, refits, surface, fit)
    home = done[0]
    if not costed:
        return Basins(ChosenBasin(pose=T_ct_us, home=home, cost=None))
    n_held = sum(len(offsets) for _, _, offsets in plans)
    held = done[1:1 + n_held]
    free_of_held = (refit_many(points_us, [Refit(T) for T in held], surface, fit) if n_held
                    else np.empty((0, 4, 4)))
    others = done[1 + n_held:]  # the probes', then the competitor's
    poses = np.concatenate([np.stack([T_ct_us, home]), held, free_of_held, others])
    costs = truncated_cost(points_us, poses, surface, fit)
    chosen = ChosenBasin(pose=T_ct_us, home=home, cost=float(min(costs[:2])))
    excess = costs - chosen.cost
    held_costs, free_costs = excess[2:2 + n_held], excess[2 + n_held:2 + 2 * n_held]
    other_costs = excess[2 + 2 * n_held:]
    profiles, first = [], 0
    for kind, axis, offsets in plans:
        rows = slice(first, first + len(offsets))
        profiles.append(_profile_record(kind, axis, offsets, held_costs[rows],
                                        free_of_held[rows], free_costs[rows], chosen, fit))
        first += len(offsets)
    found = _neighbour_records(others[:len(probes)], other_costs[:len(probes)], chosen, fit)
    record = None
    if competitor is not None:
        record = _competitor_record(competitor, others[-1], float(costs[-1]), chosen, fit)
    return Basins(chosen=chosen, profiles=profiles, neighbours=found, competitor=record)


def _profile_offsets(kind: str) -> list[float]:
    """The offsets profiled along a slide (mm) or about a rotation axis (deg), both sides."""
    amounts = PROFILE_MM if kind == "slide" else PROFILE_DEG
    return [sign * amount for sign in (1.0, -1.0) for amount in amounts]


def _profile_record(kind: str, axis: np.ndarray, offsets: list[float], held_costs: np.ndarray,
                    free: np.ndarray, free_costs: np.ndarray, chosen: ChosenBasin,
                    fit: FitMoments) -> dict:
    """The profile along one direction: ``{"kind", "axis_ct", "offsets": [{"offset",
    "delta_cost", "basin_delta_cost", "different", "weight"}], "flat_to"}``; ``offset`` in mm
    (slide) or deg (rotation); ``delta_cost``: the excess cost over the chosen basin's with the
    offset held (``held_costs``); then refitted free (``free`` ``(k, 4, 4)``, ``free_costs``),
    the basin's excess cost, whether it is another answer (:meth:`ChosenBasin.other_answer`),
    and its ``weight`` (:func:`basin_weight`, 0 for the same answer); ``flat_to``: the largest
    offset up to which every profiled cost stays within :data:`CHI2_95_1`."""
    rows = []
    for k, offset in enumerate(offsets):
        basin = free_costs[k]
        different = chosen.other_answer(free[k], chosen.cost + basin, fit.targets)
        rows.append({"offset": offset, "delta_cost": float(held_costs[k]),
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


def _neighbour_starts(fit: FitMoments, pose: np.ndarray) -> list[np.ndarray]:
    """The neighbour probe's 8 starts: ``pose`` moved by :data:`NEIGHBOUR_MM` at its farthest
    target along the two weakest principal axes of the information's translation block and
    about its rotation block's two weakest, both ways."""
    axes = []
    for block in (slice(0, 3), slice(3, 6)):
        for axis in symmetric_eigen3(fit.A[block, block])[1].T[1:]:  # the two weakest
            v = np.zeros(6)
            v[block] = axis
            axes.append(v)
    starts = []
    for v in axes:
        move = moved_pose(fit, v)
        shift = np.sqrt(np.max(np.sum((apply_transform(move, fit.targets) - fit.targets) ** 2,
                                      axis=1)))
        for sign in (1.0, -1.0):
            starts.append(matmul(moved_pose(fit, sign * v * NEIGHBOUR_MM / shift), pose))
    return starts


def _neighbour_records(free: np.ndarray, costs: np.ndarray, chosen: ChosenBasin,
                       fit: FitMoments) -> list[dict]:
    """The basins next to the chosen pose that the profiles' long offsets step over, from the
    probe's refits ``free`` ``(8, 4, 4)`` and their excess costs ``costs`` ``(8,)``: each
    distinct basin that is another answer (:meth:`ChosenBasin.other_answer`) once,
    ``[{"delta_cost", "weight"}]`` (:func:`basin_weight`), cheapest first. On a real fibula
    union, a neighbour 4 mm from a chosen pose fitted 3 units better, and nothing else saw
    it."""
    kept: list[tuple[float, np.ndarray]] = []
    for k in np.argsort(costs, kind="stable"):
        if chosen.other_answer(free[k], chosen.cost + costs[k], fit.targets) and all(
                different_answer(free[k], T, fit.targets) for _, T in kept):
            kept.append((float(costs[k]), free[k]))
    return [{"delta_cost": cost, "weight": basin_weight(cost)} for cost, _ in kept]


def _competitor_record(T_competitor: np.ndarray, basin: np.ndarray, cost: float,
                       chosen: ChosenBasin, fit: FitMoments) -> dict[str, Any]:
    """The search's clinically different pose ``T_competitor`` ``(4, 4)``, refitted free to
    ``basin`` ``(4, 4)`` of ``cost``: ``{"delta_cost", "weight", "same_basin"}``, its excess
    cost over the chosen basin's and its weight. A competitor within the clinical tolerance of
    the chosen pose at this fit's targets, or that falls into the chosen pose's own basin (not
    :meth:`ChosenBasin.other_answer`: the search had not finished it), is no other answer,
    ``weight`` 0. (The search calls a pose clinically different on its own subset of points:
    on a noisy simulated whole cloud, one 4.3 mm from the truth was within the tolerance
    here, and left unweighed it kept the search's ambiguity.)"""
    delta = cost - chosen.cost
    same = (not different_answer(T_competitor, chosen.pose, fit.targets)
            or not chosen.other_answer(basin, cost, fit.targets))
    return {"delta_cost": delta, "weight": 0.0 if same else basin_weight(delta),
            "same_basin": same}
