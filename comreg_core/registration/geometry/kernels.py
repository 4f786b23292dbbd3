"""Compiled kernels (numba) of the pose search's screening: the same point-to-plane ICP and
trimmed score as :func:`~comreg_core.registration.geometry.icp.point_to_plane_icp` with
:meth:`SurfaceCloud.match_approx` and :func:`~comreg_core.registration.search.scoring.score_poses`
with ``approximate=True``, for thousands of start poses at once.

Why compiled: the screening runs ~20 ICP iterations on every start (about 3,900 for a short
sweep, twice with the retry round); in numpy each iteration makes a dozen passes over
``(B, n, 3)`` arrays and spent ~50 ms, 200 ns a point (``docs/performance.md``). Here a start's
whole ICP runs in one loop over its points; starts are spread over threads by ``prange``, each
start computed alone, so the result does not depend on the thread count.

The closest-point grid is the one of :meth:`SurfaceCloud.closest_point_grid`: ``origin``
``(3,)`` mm, ``spacing`` mm and ``grid`` ``(I, J, K)`` int32 indices into the cloud's
``points``/``normals`` ``(M, 3)``. Compiled on first use and cached next to this file.
"""

from __future__ import annotations

import threading

import numba
import numpy as np
from numba import njit, prange

#: numba's own thread pool, not OpenMP: numba's OpenMP layer changed the results of torch's
#: OpenMP computations run after it in the same process (a resumed DDP training no longer
#: matched the uninterrupted one bit for bit, tests/training/test_distributed.py). The pool
#: takes one parallel launch at a time: callers hold :data:`PARALLEL` around each.
numba.config.THREADING_LAYER = "workqueue"
PARALLEL = threading.Lock()

#: Fewest kept pairs an ICP update needs (six unknowns): :data:`icp.MIN_PAIRS`.
_MIN_PAIRS = 6


@njit(cache=True, inline="always")
def _grid_index(x, y, z, origin, spacing, grid):
    """The cloud index the closest-point grid holds for the voxel nearest ``(x, y, z)`` mm
    (points outside the grid clamped onto it)."""
    i = min(max(np.int64(np.rint((x - origin[0]) / spacing)), 0), grid.shape[0] - 1)
    j = min(max(np.int64(np.rint((y - origin[1]) / spacing)), 0), grid.shape[1] - 1)
    k = min(max(np.int64(np.rint((z - origin[2]) / spacing)), 0), grid.shape[2] - 1)
    return grid[i, j, k]


@njit(cache=True)
def _rotation_from_rotvec(v, R):
    """Write into ``R`` ``(3, 3)`` the rotation of the rotation vector ``v`` (rad), as scipy's
    ``from_rotvec``."""
    angle = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if angle < 1e-3:  # Taylor terms, as scipy uses below this angle
        a2 = angle * angle
        s = 1.0 - a2 / 6.0 + a2 * a2 / 120.0  # sin(a) / a
        c = 0.5 - a2 / 24.0 + a2 * a2 / 720.0  # (1 - cos(a)) / a^2
    else:
        s = np.sin(angle) / angle
        c = (1.0 - np.cos(angle)) / (angle * angle)
    x, y, z = v[0], v[1], v[2]
    R[0, 0] = 1.0 - c * (y * y + z * z)
    R[1, 1] = 1.0 - c * (x * x + z * z)
    R[2, 2] = 1.0 - c * (x * x + y * y)
    R[0, 1] = c * x * y - s * z
    R[1, 0] = c * x * y + s * z
    R[0, 2] = c * x * z + s * y
    R[2, 0] = c * x * z - s * y
    R[1, 2] = c * y * z - s * x
    R[2, 1] = c * y * z + s * x


@njit(cache=True)
def _solve6(H, g, x):
    """Solve ``H x = -g`` for a symmetric positive definite ``(6, 6)`` ``H`` (Cholesky, in
    place: ``H`` is overwritten)."""
    for j in range(6):
        s = H[j, j]
        for k in range(j):
            s -= H[j, k] * H[j, k]
        H[j, j] = np.sqrt(s)
        for i in range(j + 1, 6):
            s = H[i, j]
            for k in range(j):
                s -= H[i, k] * H[j, k]
            H[i, j] = s / H[j, j]
    for i in range(6):  # L y = -g
        s = -g[i]
        for k in range(i):
            s -= H[i, k] * x[k]
        x[i] = s / H[i, i]
    for i in range(5, -1, -1):  # L^T x = y
        s = x[i]
        for k in range(i + 1, 6):
            s -= H[k, i] * x[k]
        x[i] = s / H[i, i]


@njit(cache=True)
def _select(values, count, k):
    """The ``k``-th smallest (0-based) of ``values[:count]`` (Hoare's selection; reorders
    them in place)."""
    low, high = 0, count - 1
    while low < high:
        pivot = values[(low + high) // 2]
        i, j = low, high
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i += 1
                j -= 1
        if k <= j:
            high = j
        elif k >= i:
            low = i
        else:
            break
    return values[k]


@njit(cache=True)
def pose_work(n):
    """Work arrays of :func:`pose_step` for ``n`` points: ``(scratch (n,), H (6, 6), g (6,),
    x (6,), R (3, 3), new (3, 4))``."""
    return (np.empty(n), np.empty((6, 6)), np.empty(6), np.empty(6), np.empty((3, 3)),
            np.empty((3, 4)))


@njit(cache=True)
def pose_step(moved, q, nrm, d, trim, T, work):
    """One Gauss-Newton point-to-plane update (:func:`~comreg_core.registration.geometry.icp.
    point_to_plane_icp`'s) for one start: its moved source points ``moved`` ``(n, 3)``, their
    matches ``q`` and normals ``nrm`` ``(n, 3)`` and distances ``d`` ``(n,)`` (``inf``:
    unmatched). Leaves out the ``trim`` share of the matched pairs farthest from their match
    (at least six kept), applies the step to ``T`` ``(4, 4)`` in place and returns ``(RMS
    point-to-plane residual of the kept pairs (mm), rotation-vector norm (rad), translation
    norm (mm), matched share)``; RMS NaN (and ``T`` untouched) when fewer than six pairs are
    kept. ``work``: :func:`pose_work` ``(n)``."""
    scratch, H, g, x, R, new = work
    n = moved.shape[0]
    matched = 0
    for p in range(n):
        if np.isfinite(d[p]):
            scratch[matched] = d[p]
            matched += 1
    limit = np.inf
    if trim > 0 and matched > 0:
        keep = min(matched, max(_MIN_PAIRS, matched - np.int64(trim * matched)))
        limit = _select(scratch, matched, keep - 1)
    weight = 0.0
    c0 = c1 = c2 = 0.0
    for p in range(n):
        if d[p] <= limit and np.isfinite(d[p]):
            weight += 1.0
            c0 += moved[p, 0]
            c1 += moved[p, 1]
            c2 += moved[p, 2]
    share = matched / n
    if weight < _MIN_PAIRS:
        return np.nan, 0.0, 0.0, share
    c0, c1, c2 = c0 / weight, c1 / weight, c2 / weight
    H[:] = 0.0
    g[:] = 0.0
    sq = 0.0
    for p in range(n):
        if not (d[p] <= limit and np.isfinite(d[p])):
            continue
        u0, u1, u2 = moved[p, 0] - c0, moved[p, 1] - c1, moved[p, 2] - c2
        n0, n1, n2 = nrm[p, 0], nrm[p, 1], nrm[p, 2]
        a0, a1, a2 = u1 * n2 - u2 * n1, u2 * n0 - u0 * n2, u0 * n1 - u1 * n0
        r = ((moved[p, 0] - q[p, 0]) * n0 + (moved[p, 1] - q[p, 1]) * n1
             + (moved[p, 2] - q[p, 2]) * n2)
        sq += r * r
        g[0] += a0 * r
        g[1] += a1 * r
        g[2] += a2 * r
        g[3] += n0 * r
        g[4] += n1 * r
        g[5] += n2 * r
        H[0, 0] += a0 * a0
        H[1, 0] += a1 * a0
        H[1, 1] += a1 * a1
        H[2, 0] += a2 * a0
        H[2, 1] += a2 * a1
        H[2, 2] += a2 * a2
        H[3, 0] += n0 * a0
        H[3, 1] += n0 * a1
        H[3, 2] += n0 * a2
        H[3, 3] += n0 * n0
        H[4, 0] += n1 * a0
        H[4, 1] += n1 * a1
        H[4, 2] += n1 * a2
        H[4, 3] += n1 * n0
        H[4, 4] += n1 * n1
        H[5, 0] += n2 * a0
        H[5, 1] += n2 * a1
        H[5, 2] += n2 * a2
        H[5, 3] += n2 * n0
        H[5, 4] += n2 * n1
        H[5, 5] += n2 * n2
    damp = 1e-12
    for i in range(6):
        damp += 1e-6 * H[i, i]
    for i in range(6):
        H[i, i] += damp
    _solve6(H, g, x)
    _rotation_from_rotvec(x[:3], R)
    for i in range(3):
        for j in range(4):
            new[i, j] = R[i, 0] * T[0, j] + R[i, 1] * T[1, j] + R[i, 2] * T[2, j]
    for i in range(3):  # t = c - R c + x[3:]
        new[i, 3] += c0 * (i == 0) + c1 * (i == 1) + c2 * (i == 2) - (
            R[i, 0] * c0 + R[i, 1] * c1 + R[i, 2] * c2) + x[3 + i]
    T[:3, :] = new
    return (np.sqrt(sq / weight), np.sqrt(x[0] ** 2 + x[1] ** 2 + x[2] ** 2),
            np.sqrt(x[3] ** 2 + x[4] ** 2 + x[5] ** 2), share)


@njit(cache=True)
def _icp_one_start(src, T, extent, origin, spacing, grid, cloud, normals, iterations, trim,
                   tolerance):
    """One start of :func:`grid_icp`: refines ``T`` ``(4, 4)`` in place; returns its RMS
    residual of the kept pairs at the last matching (NaN if never enough) and iterations."""
    n = src.shape[0]
    moved = np.empty((n, 3))
    q = np.empty((n, 3))
    nrm = np.empty((n, 3))
    d = np.empty(n)
    work = pose_work(n)
    rmse = np.nan
    done = 0
    for _ in range(iterations):
        for p in range(n):
            for a in range(3):
                moved[p, a] = (T[a, 0] * src[p, 0] + T[a, 1] * src[p, 1] + T[a, 2] * src[p, 2]
                               + T[a, 3])
            idx = _grid_index(moved[p, 0], moved[p, 1], moved[p, 2], origin, spacing, grid)
            dist2 = 0.0
            for a in range(3):
                q[p, a] = cloud[idx, a]
                nrm[p, a] = normals[idx, a]
                dist2 += (moved[p, a] - q[p, a]) ** 2
            d[p] = np.sqrt(dist2)
        done += 1
        step_rmse, turn, shift, _ = pose_step(moved, q, nrm, d, trim, T, work)
        if not np.isfinite(step_rmse):
            break
        rmse = step_rmse
        if turn * extent + shift < tolerance:
            break
    return rmse, done


@njit(cache=True, parallel=True)
def grid_icp(src, T_init, origin, spacing, grid, cloud, normals, iterations, trim, tolerance):
    """Point-to-plane ICP of ``src`` ``(n, 3)`` mm from ``(B, 4, 4)`` start poses with the
    closest-point grid's correspondences (module docstring): ``(B, 4, 4)`` refined poses,
    ``(B,)`` RMS residuals (mm) and ``(B,)`` iterations done. The same steps, trimming,
    damping and stopping rule as :func:`~comreg_core.registration.geometry.icp.point_to_plane_icp`."""
    B = T_init.shape[0]
    T = T_init.copy()
    rmse = np.empty(B)
    done = np.empty(B, dtype=np.int64)
    span = np.zeros(3)
    for a in range(3):
        span[a] = src[:, a].max() - src[:, a].min()
    extent = np.sqrt(span[0] ** 2 + span[1] ** 2 + span[2] ** 2)
    if extent <= 0:
        extent = 1.0
    for b in prange(B):
        rmse[b], done[b] = _icp_one_start(src, T[b], extent, origin, spacing, grid, cloud,
                                          normals, iterations, trim, tolerance)
    return T, rmse, done


@njit(cache=True, parallel=True)
def grid_scores(poses, points, origins, origin, spacing, grid, cloud, normals, trim,
                facing_penalty):
    """``(B,)`` scores (mm) of ``(B, 4, 4)`` poses for ``points`` ``(n, 3)``: the trimmed mean
    of the distances to the tangent plane at the grid's nearest cloud point, plus
    ``facing_penalty`` for each point whose surface faces away from its beam origin
    (``origins`` ``(n, 3)``, US frame; an empty ``(0, 3)`` array for none). The same as
    :func:`~comreg_core.registration.search.scoring.score_poses` with ``approximate=True``."""
    B, n = poses.shape[0], points.shape[0]
    keep = max(1, n - np.int64(trim * n))
    scores = np.empty(B)
    beams = origins.shape[0] == n
    for b in prange(B):
        T = poses[b]
        d = np.empty(n)
        for p in range(n):
            m = np.empty(3)
            for a in range(3):
                m[a] = (T[a, 0] * points[p, 0] + T[a, 1] * points[p, 1]
                        + T[a, 2] * points[p, 2] + T[a, 3])
            idx = _grid_index(m[0], m[1], m[2], origin, spacing, grid)
            dist = 0.0
            for a in range(3):
                dist += (m[a] - cloud[idx, a]) * normals[idx, a]
            d[p] = abs(dist)
            if beams and facing_penalty > 0:
                facing = 0.0
                for a in range(3):
                    beam = (T[a, 0] * origins[p, 0] + T[a, 1] * origins[p, 1]
                            + T[a, 2] * origins[p, 2] + T[a, 3])
                    facing += normals[idx, a] * (beam - m[a])
                if facing < 0:
                    d[p] += facing_penalty
        scores[b] = np.sort(d)[:keep].mean()
    return scores


@njit(cache=True)
def pose_steps(moved, q, nrm, d, trim, T):
    """:func:`pose_step` for ``m`` starts at once: ``moved``, ``q``, ``nrm`` ``(m, n, 3)``,
    ``d`` ``(m, n)``, ``T`` ``(m, 4, 4)`` updated in place. Returns ``(m, 4)``: RMS (mm; NaN
    when too few pairs were kept), rotation-vector norm (rad), translation norm (mm) and
    matched share of each start's update."""
    m, n = moved.shape[0], moved.shape[1]
    out = np.empty((m, 4))
    work = pose_work(n)  # one start after the other: a few starts, a thread pool costs more
    for b in range(m):
        out[b, 0], out[b, 1], out[b, 2], out[b, 3] = pose_step(moved[b], q[b], nrm[b], d[b],
                                                               trim, T[b], work)
    return out


@njit(cache=True)
def transform_points(R, t, points):
    """``(B, n, 3)``: ``points`` ``(1 or B, n, 3)`` moved by each of ``B`` rotations ``R``
    ``(B, 3, 3)`` and translations ``t`` ``(B, 3)``, summed in the fixed order
    ``((x R_j0 + y R_j1) + z R_j2) + t_j`` (the bits of ``transforms.rotate`` plus ``t``)."""
    B, n = R.shape[0], points.shape[1]
    out = np.empty((B, n, 3))
    for b in range(B):
        cloud = points[b] if points.shape[0] == B else points[0]
        for i in range(n):
            x, y, z = cloud[i, 0], cloud[i, 1], cloud[i, 2]
            for j in range(3):
                out[b, i, j] = ((x * R[b, j, 0] + y * R[b, j, 1]) + z * R[b, j, 2]) + t[b, j]
    return out


def compile_kernels() -> None:
    """Compile (or load from numba's cache) every kernel on a tiny problem: the set-up script
    calls it so that the first registration, bone detection, live update or volume does not
    wait for the compiler (tests/registration/test_kernels.py checks that none is left out)."""
    eye = np.tile(np.eye(4), (2, 1, 1))
    points = np.random.default_rng(0).normal(size=(12, 3))
    normals = points / np.linalg.norm(points, axis=1, keepdims=True)
    grid = np.zeros((2, 2, 2), dtype=np.int32)
    grid_icp(points, eye, np.zeros(3), 1.0, grid, points, normals, 2, 0.1, 0.1)
    grid_scores(eye, points, np.zeros((0, 3)), np.zeros(3), 1.0, grid, points, normals, 0.2, 5.0)
    grid_scores(eye, points, points, np.zeros(3), 1.0, grid, points, normals, 0.2, 5.0)
    pose_steps(np.stack([points] * 2), np.stack([points] * 2), np.stack([normals] * 2),
               np.ones((2, 12)), 0.1, eye.copy())
    transform_points(eye[:, :3, :3].copy(), eye[:, :3, 3].copy(), points[None])
    from comreg_core.registration.geometry.mesh_kernels import (closest_on_candidates,
                                                                closest_on_candidates_serial)

    for closest in (closest_on_candidates, closest_on_candidates_serial):
        closest(points, np.zeros((12, 2), dtype=np.int64), points,
                np.array([[0, 1, 2], [3, 4, 5]], dtype=np.int64))
    from comreg_core.registration.geometry.mesh_normals import smooth_normals

    smooth_normals(points, np.array([[0, 1, 2]]), normals, points[:2], np.array([0, -1]))
    from comreg_core.registration.geometry.surface import SurfaceCloud
    from comreg_core.registration.geometry.tracked_nearest import NearestTracker

    NearestTracker(SurfaceCloud(points, normals=normals))(points[None], np.zeros(1, np.int64))
    from comreg_core.surfaces.us_detector import _viterbi  # the bone detector's kernel

    _viterbi(np.zeros((4, 3), dtype=np.float32), 1, 0.5, 1.0)  # the detector's gains
    from comreg_core.surfaces.us_detector import detect_bone_surface  # its filters, percentiles

    frame = np.full((160, 120), 20, dtype=np.uint8)
    frame[80:84] = 250  # a bright echo over a shadow
    detect_bone_surface(frame, (0.1, 0.1))
    from comreg_core.surfaces.us_denoise_incremental import IncrementalDenoise  # live's

    clean_up = IncrementalDenoise()
    for frame_index in range(2):
        clean_up.add(points * 0.1, np.full(12, frame_index), np.ones(12))
        clean_up.cloud(frame_index + 1, frame_index + 1)
    from comreg_core.surfaces.us_denoise import cluster_labels  # the clean-up's kernel

    cluster_labels(points, 1.0, 2)
    from comreg_core.surfaces.us_kernels import compile_us_kernels  # the volume paths'

    compile_us_kernels()
