"""The geometry of a prior's starts (:mod:`comreg_core.registration.search.priors`): shells of
rotations about the initial pose, shifts within its tolerance, the least rotation between two
directions, the angle between rotations."""

from __future__ import annotations

import math

import numpy as np

from comreg_core.transforms import matmul, project

#: Spacing (deg) of the rotation shells and axes of the starts around ``T_init``.
STEP_DEG = 15.0
#: At most this many rotations around ``T_init`` (the spacing grows for wide tolerances).
MAX_ROTATIONS = 100


def least_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(3, 3)``: the smallest rotation turning direction ``a`` onto direction ``b``."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(project(a, b))
    if c < -1.0 + 1e-9:  # opposite: half a turn about any axis across them
        axis = np.cross(a, np.eye(3)[np.argmin(np.abs(a))])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + matmul(K, K) / (1.0 + c)


def sphere_points(count: int) -> np.ndarray:
    """``(count, 3)`` unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def rotation_shells(max_deg: float, grid_offset: float = 0.0
                    ) -> tuple[np.ndarray, list[int]]:
    """The angles (deg) of the rotation shells up to ``max_deg`` and the number of axes of
    each: shells about :data:`STEP_DEG` apart, each with as many axes as keep neighbouring
    rotations about one shell step apart (4 pi (2 sin(angle / 2) / step)^2); the step grows
    until there are at most :data:`MAX_ROTATIONS`. ``grid_offset`` 0.5: the shells halfway
    between."""
    step = STEP_DEG
    while True:
        n = max(1, math.ceil(max_deg / step - 1e-9))
        if sum(_shell_counts(max_deg / n, n, 0.0)[1]) <= MAX_ROTATIONS or step >= 180:
            return _shell_counts(max_deg / n, n, grid_offset)
        step *= 1.25


def _shell_counts(width: float, n: int, grid_offset: float) -> tuple[np.ndarray, list[int]]:
    shells = (np.arange(1, n + 1) - grid_offset) * width
    return shells, [max(4, round(4 * math.pi * (2 * math.sin(math.radians(a) / 2)
                                                / math.radians(width)) ** 2)) for a in shells]


def shift_vectors(placed: np.ndarray, centre: np.ndarray, axes: np.ndarray, reach_mm: float,
                  slide_step_mm: float, grid_offset: float = 0.0) -> dict[str, np.ndarray]:
    """``{suffix: (3,) mm}``: the shifts tried for a start placing the US centroid at
    ``placed`` ``(3,)``, each at most ``reach_mm`` long: a slide along the CT's long axis
    ``axes[:, 0]`` by a multiple of ``slide_step_mm`` (``+ grid_offset`` steps; only 0 when the
    step is 0) plus one of: nothing, the move across the axis onto it (the line through the
    CT's ``centre``; ``+onaxis``: as the global grid starts, inside the bone, which ICP leaves
    best) and ``reach_mm / 2`` along ``axes[:, 1]`` or ``axes[:, 2]`` either way
    (``+a1+15``)."""
    a0 = axes[:, 0] / np.linalg.norm(axes[:, 0])
    slides = [0.0] if not grid_offset else []
    if slide_step_mm > 0:
        k = np.arange(1, int(reach_mm // slide_step_mm) + 2) - grid_offset
        steps = k[k * slide_step_mm <= reach_mm + 1e-9] * slide_step_mm
        slides += [s for step in steps for s in (step, -step)]
    offset = np.asarray(centre, dtype=np.float64) - placed
    across = {"": np.zeros(3), "+onaxis": offset - project(offset, a0) * a0}
    for k in (1, 2):
        for sign in (1, -1):
            across[f"+a{k}{'+' if sign > 0 else '-'}{reach_mm / 2:g}"] = \
                sign * reach_mm / 2 * axes[:, k] / np.linalg.norm(axes[:, k])
    if np.linalg.norm(across["+onaxis"]) < 1.0:  # already on it
        del across["+onaxis"]
    out = {}
    for slide in slides:
        for label, move in across.items():
            shift = slide * a0 + move
            if np.linalg.norm(shift) <= reach_mm + 1e-9:
                out[(f"+slide{slide:g}" if slide else "") + label] = shift
    return out
