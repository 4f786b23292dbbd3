"""Rigid transform and coordinate-system helpers: the one home for 4x4 matrix conventions.

A rigid transform is a ``(4, 4)`` float64 array named ``T_<to>_<from>``: ``T_ct_us @ p_us = p_ct``
for homogeneous column vectors. Patient coordinate systems are ``"LPS"`` (DICOM, ITK, files written
by 3D Slicer) and ``"RAS"`` (3D Slicer's scene); they differ by negating x and y.
"""

from __future__ import annotations

import math

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
    return rotate(points, T[:3, :3]) + T[:3, 3]


def invert_rigid(T: np.ndarray, check: bool = True) -> np.ndarray:
    """Inverse of a rigid ``(4, 4)`` transform: ``[R | t]^-1 = [R^T | -R^T t]``.
    ``check=False`` trusts ``T`` to be rigid (a pose the code computed; the check costs ~0.1 ms,
    which a loop over many poses feels)."""
    T = check_rigid(T) if check else np.asarray(T, dtype=np.float64)
    inv = np.eye(4)
    inv[:3, :3] = T[:3, :3].T
    inv[:3, 3] = -rotate(T[:3, 3], T[:3, :3].T)
    return inv


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """``T`` as float64 with its 3x3 part replaced by the nearest rotation (the polar factor,
    reflection fixed: what an SVD gives, computed by :func:`symmetric_eigen3` so that every CPU
    gets the same bits) and its last row ``0 0 0 1``: removes float32 drift from a computed
    rigid transform."""
    T = np.asarray(T, dtype=np.float64).copy()
    R = T[:3, :3]
    values, V = symmetric_eigen3(matmul(R.T, R))  # R = Q S, S = V diag(sigma) V^T
    sigma = np.sqrt(np.maximum(values, 0.0))
    if sigma[2] <= 1e-12 * max(sigma[0], 1e-300):  # singular: no unique nearest rotation
        U, _, Vt = np.linalg.svd(R)
        U[:, -1] *= 1.0 if np.linalg.det(U @ Vt) > 0 else -1.0
        T[:3, :3] = U @ Vt
    else:
        det = (R[0, 0] * (R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1])
               - R[0, 1] * (R[1, 0] * R[2, 2] - R[1, 2] * R[2, 0])
               + R[0, 2] * (R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0]))
        scale = np.array([1.0, 1.0, 1.0 if det > 0 else -1.0]) / sigma
        T[:3, :3] = matmul(R, matmul(V * scale, V.T))
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


# -- arithmetic that gives the same bits on every CPU -------------------------------------------
# numpy's ``@``, ``dot`` and ``linalg`` call the BLAS/LAPACK library, whose kernels (chosen per
# CPU, e.g. by OPENBLAS_CORETYPE) sum in different orders: the last bits of a product differ
# between machines, and an ICP along a smooth shaft turns such bits into different poses. The
# registration's geometry uses these helpers instead: elementwise products summed in a fixed
# order (each IEEE operation is exactly rounded, so every machine gets the same bits).

def rotate(points: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``points @ R^T`` in a fixed order: ``(..., N, 3)`` points by ``(3, 3)`` or ``(B, 3, 3)``
    rotations (``(B, N, 3)`` out; ``(N, 3)`` points are broadcast over ``B``)."""
    points = np.asarray(points, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    rows = R[..., None, :, :]  # ... 1 3 3
    return (points[..., 0:1] * rows[..., 0] + points[..., 1:2] * rows[..., 1]
            + points[..., 2:3] * rows[..., 2])


def matmul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` for small matrices ``(..., m, k)`` and ``(..., k, n)``, summed over ``k`` in
    order (the same bits on every CPU)."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    out = A[..., :, 0:1] * B[..., 0:1, :]
    for k in range(1, A.shape[-1]):
        out = out + A[..., :, k:k + 1] * B[..., k:k + 1, :]
    return out


def project(points: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """``(...)`` the ``(..., 3)`` points' coordinates along ``direction`` ``(3,)``:
    ``points @ direction`` in a fixed order."""
    points = np.asarray(points, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    return points[..., 0] * d[0] + points[..., 1] * d[1] + points[..., 2] * d[2]


def symmetric_eigen3(C: np.ndarray, sweeps: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues ``(3,)`` (decreasing) and unit eigenvectors ``(3, 3)`` (columns; each
    signed so that its largest component is positive) of a symmetric ``(3, 3)`` matrix, by
    cyclic Jacobi rotations in plain float arithmetic (the same bits on every CPU)."""
    a = [[float(C[i][j]) for j in range(3)] for i in range(3)]
    v = [[1.0 if i == j else 0.0 for j in range(3)] for i in range(3)]
    for _ in range(sweeps):
        off = abs(a[0][1]) + abs(a[0][2]) + abs(a[1][2])
        if off == 0.0:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            if a[p][q] == 0.0:
                continue
            theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q])
            t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):  # A <- A J (columns p, q), then J^T A (rows p, q)
                akp, akq = a[k][p], a[k][q]
                a[k][p], a[k][q] = c * akp - s * akq, s * akp + c * akq
            for k in range(3):
                apk, aqk = a[p][k], a[q][k]
                a[p][k], a[q][k] = c * apk - s * aqk, s * apk + c * aqk
            for k in range(3):
                vkp, vkq = v[k][p], v[k][q]
                v[k][p], v[k][q] = c * vkp - s * vkq, s * vkp + c * vkq
    values = np.array([a[i][i] for i in range(3)])
    vectors = np.array(v)
    order = np.argsort(-values, kind="stable")
    values, vectors = values[order], vectors[:, order]
    for j in range(3):
        if vectors[np.argmax(np.abs(vectors[:, j])), j] < 0:
            vectors[:, j] = -vectors[:, j]
    return values, vectors
