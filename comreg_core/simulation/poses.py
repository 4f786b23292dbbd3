"""Random initial poses: the rigid misalignment a simulated cloud is moved by before training.

Each sampler returns ``T`` ``(4, 4)`` float64 with ``S^t = apply_transform(T, S)``: the perturbed
cloud plays the US frame, so ``T`` is ``T_us_ct`` and the registration target is
``T_ct_us = invert_rigid(T)``. Rotations turn about ``center`` (give the CT bounding-box centre:
the paper works in coordinates normalised about it; the default, the origin, suits already-centred
clouds); translations are in mm.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def _pose(rotvec: np.ndarray, translation: np.ndarray, center) -> np.ndarray:
    R = Rotation.from_rotvec(rotvec).as_matrix()
    c = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64).reshape(3)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c + np.asarray(translation, dtype=np.float64)
    return T


def paper_initial_pose(rng: np.random.Generator, center=None, *, max_angle_deg: float = 90.0,
                       max_translation_mm: float = 100.0, random_axis: bool = False
                       ) -> np.ndarray:
    """The paper's sampler: pick one axis, rotate about it by U(-90, 90) deg and translate along
    it by U(-100, 100) mm.

    Reading: "randomly selecting an axis" = one of the three coordinate axes x, y, z of the CT
    frame, uniformly; the same axis carries the rotation and the translation. With
    ``random_axis=True`` the axis is instead uniform on the sphere (the other possible reading).
    """
    if random_axis:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
    else:
        axis = np.eye(3)[rng.integers(3)]
    angle = np.radians(rng.uniform(-max_angle_deg, max_angle_deg))
    shift = rng.uniform(-max_translation_mm, max_translation_mm)
    return _pose(axis * angle, axis * shift, center)


def full_rotation_pose(rng: np.random.Generator, center=None, *, max_angle_deg: float = 180.0,
                       max_translation_mm: float = 500.0) -> np.ndarray:
    """Harder sampler for robustness tests: rotation by U(0, max_angle) deg about an axis uniform
    on the sphere, translation in a direction uniform on the sphere with length
    U(0, max_translation) mm."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(0.0, max_angle_deg))
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    return _pose(axis * angle, direction * rng.uniform(0.0, max_translation_mm), center)


def sample_initial_pose(rng: np.random.Generator, kind: str = "paper", center=None
                        ) -> np.ndarray:
    """``kind`` "paper" (:func:`paper_initial_pose`) or "full" (:func:`full_rotation_pose`)."""
    if kind == "paper":
        return paper_initial_pose(rng, center)
    if kind == "full":
        return full_rotation_pose(rng, center)
    from comreg_core.config import ConfigError

    raise ConfigError(f"Unknown initial-pose sampler '{kind}'.", "Use 'paper' or 'full'.")
