"""Compiled kernels (numba) of the ultrasound volume paths: a frame's pixels binned into the
compounding grid (:mod:`.us_compounding`), and the resampled slices of a volume found and filled
(:mod:`.us_volume`). Serial, so the numbers do not depend on the thread count; compiled on first
use and cached next to this file."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _voxel(p, n, spacing, dims):
    """The flat (Fortran order) voxel index of point ``p[n]`` (mm from the grid origin), its
    nearest voxel (``rint(p / spacing)``), or -1 outside the grid ``dims``."""
    i = np.rint(p[n, 0] / spacing)
    j = np.rint(p[n, 1] / spacing)
    k = np.rint(p[n, 2] / spacing)
    if not (0 <= i < dims[0] and 0 <= j < dims[1] and 0 <= k < dims[2]):
        return -1
    return int(i) + dims[0] * (int(j) + dims[1] * int(k))


@njit(cache=True)
def bin_sum(p, spacing, dims, frame, rows, cols, total, count):
    """Add pixel ``frame[rows[n], cols[n]]`` (as float64) to ``total`` and 1 to ``count`` (both
    ``(prod(dims),)``) at the nearest voxel of ``p[n]`` ``(N, 3)`` mm; pixels off the grid
    skipped. Pixels in order, so a voxel's sum is that of ``np.bincount``."""
    for n in range(len(rows)):
        v = _voxel(p, n, spacing, dims)
        if v >= 0:
            total[v] += np.float64(frame[rows[n], cols[n]])
            count[v] += 1


@njit(cache=True)
def bin_max(p, spacing, dims, frame, rows, cols, peak):
    """:func:`bin_sum` keeping the largest pixel per voxel in ``peak`` (``np.maximum``: NaN
    wins)."""
    for n in range(len(rows)):
        v = _voxel(p, n, spacing, dims)
        if v >= 0:
            value = np.float64(frame[rows[n], cols[n]])
            if value > peak[v] or value != value:
                peak[v] = value


@njit(cache=True)
def divide_by_count(total, count):
    """``total / count`` in place where ``count > 0`` (elsewhere ``total`` stays 0)."""
    for v in range(len(total)):
        if count[v] > 0:
            total[v] = total[v] / count[v]


@njit(cache=True)
def reach_of(covered):
    """``(reach (I+1, J+1, K+1) bool, blocks (I//8+1, J//8+1, K//8+1) bool)`` of ``covered``
    ``(I, J, K)``: ``reach[a, b, c]`` is set where a voxel of ``covered[a-1:a+1, b-1:b+1,
    c-1:c+1]`` is; ``blocks[a // 8, b // 8, c // 8]`` where ``reach[a, b, c]`` is."""
    I, J, K = covered.shape
    reach = np.zeros((I + 1, J + 1, K + 1), np.bool_)
    blocks = np.zeros((I // 8 + 1, J // 8 + 1, K // 8 + 1), np.bool_)
    for k in range(K):
        for j in range(J):
            for i in range(I):
                if covered[i, j, k]:
                    for a in range(i, i + 2):
                        for b in range(j, j + 2):
                            for c in range(k, k + 2):
                                reach[a, b, c] = True
                                blocks[a // 8, b // 8, c // 8] = True
    return reach, blocks


@njit(cache=True)
def may_exceed_zero(ijk, reach, blocks):
    """Indices ``(m,)`` of the points ``ijk`` ``(n, 3)`` (voxel index coordinates) whose
    linear interpolation can be above 0: ``reach[floor(ijk) + 1]`` is set (:func:`reach_of`:
    a voxel of the 2 x 2 x 2 block from ``floor(ijk)`` is above 0); points farther than one
    voxel outside the volume are left out."""
    found = np.empty(len(ijk), np.int64)
    m = 0
    for n in range(len(ijk)):
        x = np.floor(ijk[n, 0]) + 1
        y = np.floor(ijk[n, 1]) + 1
        z = np.floor(ijk[n, 2]) + 1
        if not (0 <= x < reach.shape[0] and 0 <= y < reach.shape[1]
                and 0 <= z < reach.shape[2]):
            continue
        a, b, c = int(x), int(y), int(z)
        if blocks[a // 8, b // 8, c // 8] and reach[a, b, c]:
            found[m] = n
            m += 1
    return found[:m]


@njit(cache=True)
def fill_slices(values, imaged, slice_mm, max_gap_mm, every):
    """uint8 slices ``(ceil(K / every), H, W)``: every ``every``-th of ``values`` ``(K, H, W)``,
    pixels not ``imaged`` linearly interpolated along the slice axis between the nearest imaged
    ones (gaps up to ``max_gap_mm``, slices ``slice_mm`` apart), the rest set to the slice's
    median imaged or interpolated value (0 if none), rounded and clipped to 0-255."""
    K, H, W = values.shape
    before = np.full((H, W), -1, np.int64)  # the last imaged slice up to k
    after = np.full((H, W), -1, np.int64)  # the next imaged slice from k (-1: not looked for)
    out = np.empty(((K + every - 1) // every, H, W), np.uint8)
    filled = np.empty((H, W), np.float64)
    known = np.empty((H, W), np.bool_)
    for k in range(K):
        for r in range(H):
            for c in range(W):
                if imaged[k, r, c]:
                    before[r, c] = k
        if k % every:
            continue
        n_known = 0
        for r in range(H):
            for c in range(W):
                known[r, c] = True
                if imaged[k, r, c]:
                    filled[r, c] = np.float64(values[k, r, c])
                    n_known += 1
                    continue
                b, a = before[r, c], after[r, c]
                if a < k:
                    a = k + 1
                    while a < K and not imaged[a, r, c]:
                        a += 1
                    after[r, c] = a
                if b >= 0 and a < K and (a - b) * slice_mm <= max_gap_mm:
                    w = (k - b) / (a - b)
                    filled[r, c] = (1 - w) * np.float64(values[b, r, c]) \
                        + w * np.float64(values[a, r, c])
                    n_known += 1
                else:
                    known[r, c] = False
        rest = np.median(filled.ravel()[known.ravel()]) if n_known else 0.0
        for r in range(H):
            for c in range(W):
                x = np.rint(filled[r, c] if known[r, c] else rest)
                out[k // every, r, c] = np.uint8(min(max(x, 0.0), 255.0))
    return out


def compile_us_kernels() -> None:
    """Compile (or load from numba's cache) these kernels on tiny problems, with the types and
    layouts the volume paths give them (uint8 frames; volumes read in Fortran order): the
    set-up script calls it (:func:`~comreg_core.registration.geometry.kernels.compile_kernels`)
    so that the first volume does not wait for the compiler."""
    dims = np.array([2, 2, 2], dtype=np.int64)
    p, pixels = np.zeros((4, 3)), np.zeros(4, dtype=np.int64)
    frame, total, count = np.zeros((2, 2), np.uint8), np.zeros(8), np.zeros(8, np.int32)
    bin_sum(p, 0.5, dims, frame, pixels, pixels, total, count)
    bin_max(p, 0.5, dims, frame, pixels, pixels, total)
    divide_by_count(total, count)
    reach, blocks = reach_of(np.zeros((2, 2, 2), bool, order="F"))
    may_exceed_zero(np.zeros((4, 3)), reach, blocks)
    fill_slices(np.zeros((2, 2, 2), np.float32), np.zeros((2, 2, 2), bool), 0.5, 2.0, 1)
