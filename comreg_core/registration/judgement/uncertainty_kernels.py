"""Compiled kernels (numba) of :mod:`~comreg_core.registration.judgement.uncertainty`.

Every sum runs in a fixed order in plain float arithmetic (no BLAS, no LAPACK), so that the
uncertainty has the same bits on every CPU, as the pose search's kernels do.

Pose parameters: ``xi = (w / scale, t)``, ``(6,)``: a small rotation ``w`` (rad) about
``centre`` times ``scale`` (mm, so that the six are all in mm) and a translation ``t`` (mm).
A point ``p`` moves by ``w x (p - centre) + t``; its point-to-plane residual against the normal
``n`` changes by ``J xi`` with ``J = ((p - centre) x n / scale, n)``.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def moments(points, closest, normals, centre, scale, group, n_groups):
    """``(H (6, 6), M (6, 6), g (6,))`` of the point-to-plane fit of ``(n, 3)`` points to their
    ``closest`` CT points with unit ``normals``: ``H = sum J_i J_i^T``, the gradient ``g =
    sum J_i r_i`` and ``M = sum_b g_b g_b^T`` over the groups ``group`` ``(n,)`` (ids
    ``0 .. n_groups - 1``) of points whose errors may be alike (one frame, one block)."""
    H = np.zeros((6, 6))
    M = np.zeros((6, 6))
    g = np.zeros(6)
    gb = np.zeros((n_groups, 6))
    J = np.zeros(6)
    for i in range(points.shape[0]):
        dx = points[i, 0] - centre[0]
        dy = points[i, 1] - centre[1]
        dz = points[i, 2] - centre[2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        J[0] = (dy * nz - dz * ny) / scale
        J[1] = (dz * nx - dx * nz) / scale
        J[2] = (dx * ny - dy * nx) / scale
        J[3], J[4], J[5] = nx, ny, nz
        r = ((points[i, 0] - closest[i, 0]) * nx + (points[i, 1] - closest[i, 1]) * ny) \
            + (points[i, 2] - closest[i, 2]) * nz
        for a in range(6):
            g[a] += J[a] * r
            gb[group[i], a] += J[a] * r
            for b in range(6):
                H[a, b] += J[a] * J[b]
    for k in range(n_groups):
        for a in range(6):
            for b in range(6):
                M[a, b] += gb[k, a] * gb[k, b]
    return H, M, g


@njit(cache=True)
def cholesky(A):
    """The lower Cholesky factor ``(k, k)`` of a symmetric positive definite ``(k, k)``."""
    k = A.shape[0]
    L = np.zeros((k, k))
    for j in range(k):
        s = A[j, j]
        for m in range(j):
            s -= L[j, m] * L[j, m]
        L[j, j] = np.sqrt(max(s, 1e-300))
        for i in range(j + 1, k):
            s = A[i, j]
            for m in range(j):
                s -= L[i, m] * L[j, m]
            L[i, j] = s / L[j, j]
    return L


@njit(cache=True)
def inverse(A):
    """The inverse ``(k, k)`` of a symmetric positive definite ``(k, k)`` (by Cholesky)."""
    k = A.shape[0]
    L = cholesky(A)
    out = np.zeros((k, k))
    y = np.zeros(k)
    for c in range(k):
        for i in range(k):
            s = 1.0 if i == c else 0.0
            for m in range(i):
                s -= L[i, m] * y[m]
            y[i] = s / L[i, i]
        for i in range(k - 1, -1, -1):
            s = y[i]
            for m in range(i + 1, k):
                s -= L[m, i] * out[m, c]
            out[i, c] = s / L[i, i]
    return out


@njit(cache=True)
def product(A, B):
    """``A @ B`` of ``(a, k)`` and ``(k, b)`` matrices, summed in index order."""
    out = np.zeros((A.shape[0], B.shape[1]))
    for i in range(A.shape[0]):
        for j in range(B.shape[1]):
            s = 0.0
            for m in range(A.shape[1]):
                s += A[i, m] * B[m, j]
            out[i, j] = s
    return out


@njit(cache=True)
def target_errors(L, z, targets, centre, scale, offset):
    """For each of ``K`` pose errors ``xi = offset + L z_k`` (``offset`` ``(6,)``, ``L``
    ``(6, 6)``, ``z`` ``(K, 6)`` standard normal): ``(largest displacement (K,) mm of the
    (J, 3) targets, rotation (K,) deg)``."""
    K = z.shape[0]
    largest = np.zeros(K)
    angle = np.zeros(K)
    xi = np.zeros(6)
    for k in range(K):
        for a in range(6):
            s = offset[a]
            for b in range(a + 1):
                s += L[a, b] * z[k, b]
            xi[a] = s
        wx, wy, wz = xi[0] / scale, xi[1] / scale, xi[2] / scale
        angle[k] = np.sqrt(wx * wx + wy * wy + wz * wz) * (180.0 / np.pi)
        best = 0.0
        for j in range(targets.shape[0]):
            dx = targets[j, 0] - centre[0]
            dy = targets[j, 1] - centre[1]
            dz = targets[j, 2] - centre[2]
            ux = (wy * dz - wz * dy) + xi[3]
            uy = (wz * dx - wx * dz) + xi[4]
            uz = (wx * dy - wy * dx) + xi[5]
            d = ux * ux + uy * uy + uz * uz
            if d > best:
                best = d
        largest[k] = np.sqrt(best)
    return largest, angle


@njit(cache=True)
def patch_target_errors(samples, normals, starts, chosen, A, weight, c, z, targets, centre,
                        scale):
    """The largest target displacements ``(P, K)`` mm of :func:`target_errors` (draws ``z``
    ``(K, 6)``) for each of the ``P`` patches ``chosen`` ``(P,)`` scanned in thought: patch
    ``p`` is rows ``starts[p]:starts[p + 1]`` of the ``(m, 3)`` CT ``samples`` and their
    ``normals``, its information ``H_p`` their :func:`moments` on themselves, its covariance
    ``c * inverse(A + weight * H_p)``. The same arithmetic as one patch at a time."""
    out = np.empty((len(chosen), z.shape[0]))
    for i in range(len(chosen)):
        a, b = starts[chosen[i]], starts[chosen[i] + 1]
        H, _, _ = moments(samples[a:b], samples[a:b], normals[a:b], centre, scale,
                          np.zeros(b - a, dtype=np.int64), 1)
        covariance = c * inverse(A + weight * H)
        out[i], _ = target_errors(cholesky(covariance), z, targets, centre, scale, np.zeros(6))
    return out


def compile_uncertainty_kernels() -> None:
    """Compile (or load from numba's cache) every kernel here on a tiny problem."""
    pts = np.random.default_rng(0).normal(size=(12, 3))
    nrm = pts / np.sqrt((pts ** 2).sum(axis=1))[:, None]
    H, M, _ = moments(pts, pts * 0.9, nrm, np.zeros(3), 1.0, np.zeros(12, dtype=np.int64), 1)
    A = H + np.eye(6)
    product(inverse(A), A)
    target_errors(cholesky(A), np.ones((2, 6)), pts, np.zeros(3), 1.0, np.zeros(6))
    patch_target_errors(pts, nrm, np.array([0, 6, 12]), np.array([1, 0]), A, 0.5, 1.0,
                        np.ones((2, 6)), pts, np.zeros(3), 1.0)
