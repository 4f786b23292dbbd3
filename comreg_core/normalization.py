"""The network's normalised coordinates: CT bounding-box centre at 0, CT largest extent = 1.

Both clouds (CT and US) are normalised with the *CT's* centre and scale, never their own, so a
rigid transform between them stays rigid: a transform ``T_n`` in normalised coordinates and the
same transform ``T_mm`` in millimetres are related by ``T_mm = N^-1 T_n N`` with
``N(x) = (x - c) / s``. Rotations are unchanged; translations scale by ``s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comreg_core.errors import InvalidGeometryError
from comreg_core.transforms import as_points, check_rigid


@dataclass(frozen=True)
class Normalization:
    """``x_model = (x_mm - center) / scale``.

    Attributes:
        center: ``(3,)`` mm, the CT bounding-box centre.
        scale: mm per model unit, the CT's largest bounding-box extent.
    """

    center: np.ndarray
    scale: float

    @classmethod
    def from_ct(cls, ct_points: np.ndarray) -> Normalization:
        """From the CT bone points ``(N, 3)`` in mm."""
        pts = as_points(ct_points, "CT points")
        if len(pts) < 2:
            raise InvalidGeometryError("The CT cloud has fewer than 2 points.",
                                       "Extract the bone surface again.")
        lo, hi = pts.min(0), pts.max(0)
        scale = float((hi - lo).max())
        if scale <= 0:
            raise InvalidGeometryError("All CT points coincide; the cloud has no extent.",
                                       "Extract the bone surface again.")
        return cls(center=(lo + hi) / 2.0, scale=scale)

    def matrix(self) -> np.ndarray:
        """``(4, 4)`` matrix ``N`` taking mm to model coordinates."""
        m = np.eye(4) / self.scale
        m[3, 3] = 1.0
        m[:3, 3] = -self.center / self.scale
        return m

    def points_to_model(self, points: np.ndarray) -> np.ndarray:
        return (as_points(points) - self.center) / self.scale

    def points_to_mm(self, points: np.ndarray) -> np.ndarray:
        return as_points(points) * self.scale + self.center

    def transform_to_mm(self, T_model: np.ndarray) -> np.ndarray:
        """A rigid transform between normalised clouds as the same transform in mm."""
        T = check_rigid(T_model).copy()
        R = T[:3, :3]
        T[:3, 3] = self.center - R @ self.center + self.scale * T[:3, 3]
        return T

    def transform_to_model(self, T_mm: np.ndarray) -> np.ndarray:
        """A rigid transform in mm as the same transform between normalised clouds."""
        T = check_rigid(T_mm).copy()
        R = T[:3, :3]
        T[:3, 3] = (T[:3, 3] - self.center + R @ self.center) / self.scale
        return T
