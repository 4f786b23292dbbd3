"""Rigid transform and coordinate-system helpers: the one home for 4x4 matrix conventions.

A rigid transform is a ``(4, 4)`` float64 array named ``T_<to>_<from>``: ``T_ct_us @ p_us = p_ct``
for homogeneous column vectors. Patient coordinate systems are ``"LPS"`` (DICOM, ITK, files written
by 3D Slicer) and ``"RAS"`` (3D Slicer's scene); they differ by negating x and y.
"""

from __future__ import annotations

import numpy as np

from comreg_core.errors import InvalidGeometryError, InvalidTransformError

SPACES = ("LPS", "RAS")

#: Converts LPS coordinates to RAS and back (its own inverse).
T_RAS_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


def check_space(space: str) -> str:
    """Normalise a space name ("lps", "left-posterior-superior", ...) to "LPS" or "RAS"."""
    aliases = {
        "lps": "LPS",
        "left-posterior-superior": "LPS",
        "ras": "RAS",
        "right-anterior-superior": "RAS",
    }
    key = str(space).strip().lower()
    if key not in aliases:
        raise InvalidGeometryError(
            f"Unknown patient coordinate system '{space}'.", "Use 'LPS' or 'RAS'."
        )
    return aliases[key]


def space_change(from_space: str, to_space: str) -> np.ndarray:
    """``(4, 4)`` matrix mapping homogeneous points from ``from_space`` to ``to_space``."""
    if check_space(from_space) == check_space(to_space):
        return np.eye(4)
    return T_RAS_LPS.copy()


def as_points(points: np.ndarray, what: str = "points") -> np.ndarray:
    """Validate an ``(N, 3)`` array of finite coordinates and return it as float64."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidGeometryError(
            f"The {what} have shape {arr.shape}, expected (N, 3).",
            "Pass one x, y, z row per point.",
        )
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise InvalidGeometryError(
            f"{int(bad.sum())} of {len(arr)} {what} have non-finite (NaN or infinite) coordinates.",
            "Remove or fix those points before using the data.",
        )
    return arr


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a ``(4, 4)`` transform to ``(N, 3)`` points; returns ``(N, 3)`` float64."""
    T = np.asarray(T, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    return points @ T[:3, :3].T + T[:3, 3]


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid ``(4, 4)`` transform: ``[R | t]^-1 = [R^T | -R^T t]``."""
    T = check_rigid(T)
    inv = np.eye(4)
    inv[:3, :3] = T[:3, :3].T
    inv[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return inv


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """``T`` as float64 with its 3x3 part projected onto SO(3) (SVD, reflection fixed) and its
    last row ``0 0 0 1``: removes float32 drift from a computed rigid transform."""
    T = np.asarray(T, dtype=np.float64).copy()
    U, _, Vt = np.linalg.svd(T[:3, :3])
    if np.linalg.det(U @ Vt) < 0:
        U[:, -1] *= -1
    T[:3, :3] = U @ Vt
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


def check_rigid(T: np.ndarray, atol: float = 1e-4) -> np.ndarray:
    """Return ``T`` as float64 if it is a finite rigid ``(4, 4)`` matrix, else raise."""
    T = check_affine(T)
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=atol) or np.linalg.det(R) < 0:
        raise InvalidTransformError(
            "The transform is not rigid (its 3x3 part is not a rotation).",
            "Pass a rotation + translation; scaling, shear or mirroring are not allowed here.",
        )
    return T


def check_affine(T: np.ndarray) -> np.ndarray:
    """Return ``T`` as float64 if it is a finite ``(4, 4)`` matrix with last row ``0 0 0 1``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InvalidTransformError(
            f"Expected a finite 4x4 matrix, got shape {T.shape}.",
            "Transforms are 4x4 homogeneous matrices in millimetres.",
        )
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise InvalidTransformError(
            "The last row of the 4x4 transform is not [0, 0, 0, 1].",
            "Pass an affine homogeneous matrix.",
        )
    if abs(np.linalg.det(T[:3, :3])) < 1e-12:
        raise InvalidTransformError("The transform is singular.", "Pass an invertible matrix.")
    return T
