"""Compiled (numba) image filters of the B-mode detector, bit for bit scipy's.

:func:`gaussian_filter` is ``scipy.ndimage.gaussian_filter(image, sigma, order)`` on a
``float32`` 2D image in its default ``reflect`` mode, with the same bits: the same kernel
(scipy's own ``_gaussian_kernel1d``), the same sums in the same order in float64 (scipy's
symmetric and antisymmetric paths of ``correlate1d``: the centre tap, then the pairs of taps
from the outermost in), rounded to float32 after each axis as scipy stores it. It takes about a
third of scipy's time on a fibula frame (405 x 475 working pixels), which keeps detection
ahead of a 40 frames/s stream (issue 49). Other dtypes or kernels scipy treats as neither
symmetric nor antisymmetric go to scipy itself.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy import ndimage
from scipy.ndimage._filters import _gaussian_kernel1d

#: scipy's tolerance when it decides that a kernel is symmetric or antisymmetric.
_SYMMETRY_TOLERANCE = np.finfo(np.float64).eps


def _correlation_weights(sigma: float, order: int, truncate: float = 4.0
                         ) -> tuple[np.ndarray, int]:
    """The weights ``correlate1d`` gets from ``gaussian_filter1d`` and their symmetry: 1
    (symmetric), -1 (antisymmetric) or 0 (neither: scipy's general path)."""
    radius = int(truncate * float(sigma) + 0.5)
    weights = np.ascontiguousarray(_gaussian_kernel1d(sigma, order, radius)[::-1])
    left, right = weights[:radius][::-1], weights[radius + 1:]
    if np.all(np.abs(right - left) <= _SYMMETRY_TOLERANCE):
        return weights, 1
    if np.all(np.abs(right + left) <= _SYMMETRY_TOLERANCE):
        return weights, -1
    return weights, 0


@njit(cache=True)
def _reflect(index, n):
    """scipy's ``reflect`` extension (d c b a | a b c d | d c b a) of index ``index`` on a line
    of ``n`` samples."""
    period = 2 * n
    index %= period
    return index if index < n else period - 1 - index


@njit(cache=True)
def _along_rows(image, weights, sign):
    """Correlate each column of ``image`` ``(h, w)`` float32 with ``weights`` (axis 0)."""
    h, w = image.shape
    radius = len(weights) // 2
    out = np.empty((h, w), np.float32)
    total = np.empty(w)
    for i in range(h):
        centre = weights[radius]
        for c in range(w):
            total[c] = np.float64(image[i, c]) * centre
        for jj in range(-radius, 0):
            a, b, tap = _reflect(i + jj, h), _reflect(i - jj, h), weights[radius + jj]
            if sign > 0:
                for c in range(w):
                    total[c] += (np.float64(image[a, c]) + np.float64(image[b, c])) * tap
            else:
                for c in range(w):
                    total[c] += (np.float64(image[a, c]) - np.float64(image[b, c])) * tap
        for c in range(w):
            out[i, c] = np.float32(total[c])
    return out


@njit(cache=True)
def _along_columns(image, weights, sign):
    """Correlate each row of ``image`` ``(h, w)`` float32 with ``weights`` (axis 1)."""
    h, w = image.shape
    radius = len(weights) // 2
    out = np.empty((h, w), np.float32)
    line = np.empty(w + 2 * radius, np.float32)  # the row with its reflected ends
    total = np.empty(w)
    for i in range(h):
        row = image[i]
        line[radius:radius + w] = row
        for k in range(radius):
            line[k] = row[_reflect(k - radius, w)]
            line[w + radius + k] = row[_reflect(w + k, w)]
        centre = weights[radius]
        for c in range(w):
            total[c] = np.float64(line[c + radius]) * centre
        for jj in range(-radius, 0):
            tap = weights[radius + jj]
            left, right = line[radius + jj:radius + jj + w], line[radius - jj:radius - jj + w]
            if sign > 0:
                for c in range(w):
                    total[c] += (np.float64(left[c]) + np.float64(right[c])) * tap
            else:
                for c in range(w):
                    total[c] += (np.float64(left[c]) - np.float64(right[c])) * tap
        for c in range(w):
            out[i, c] = np.float32(total[c])
    return out


def gaussian_filter(image: np.ndarray, sigma: tuple[float, float],
                    order: tuple[int, int] = (0, 0)) -> np.ndarray:
    """``scipy.ndimage.gaussian_filter(image, sigma, order)`` of a 2D ``image`` ``(h, w)``
    (``sigma`` in pixels per axis), bit for bit (module docstring); ``(h, w)`` of
    ``image``'s dtype."""
    image = np.asarray(image)
    rows_w, rows_sign = _correlation_weights(sigma[0], order[0])
    cols_w, cols_sign = _correlation_weights(sigma[1], order[1])
    if (image.dtype != np.float32 or image.ndim != 2 or min(sigma) <= 1e-15
            or rows_sign == 0 or cols_sign == 0):
        return ndimage.gaussian_filter(image, sigma, order=order)
    image = np.ascontiguousarray(image)
    return _along_columns(_along_rows(image, rows_w, rows_sign), cols_w, cols_sign)


@njit(cache=True)
def _window(r, offset_start, offset_stop, h):
    """Rows ``[r + offset_start, r + offset_stop)`` clipped to ``[0, h]``: (start, stop, count)."""
    start = min(max(r + offset_start, 0), h)
    stop = min(max(r + offset_stop, 0), h)
    return start, stop, max(stop - start, 0)


@njit(cache=True)
def shadow_and_tissue(intensity, expected, gap, depth, above_n, tissue_ref, echo_level,
                      min_fill, min_above):
    """The detector's shadow and tissue terms (:func:`~comreg_core.surfaces.us_detector.
    bone_evidence`), ``(h, w)`` float64 each, from ``intensity`` ``(h, w)`` float32 and each
    row's ``expected`` level below it ``(h,)`` (floored): window means over rows by running
    float64 sums down each column (numpy's ``cumsum`` order, so numpy's bits). Shadow: ``1 -
    mean(intensity over [r + gap, r + gap + depth)) / expected[r]``; tissue: ``mean(intensity
    over [r - gap - above_n, r - gap)) / tissue_ref`` times the window's share of pixels
    brighter than ``echo_level`` over ``min_fill`` (when ``min_fill`` > 0), 0 where that window
    has fewer than ``min_above`` rows; both clipped to [0, 1]."""
    h, w = intensity.shape
    total = np.zeros((h + 1, w))
    bright = np.zeros((h + 1, w), np.int32)
    for r in range(h):
        for c in range(w):
            total[r + 1, c] = total[r, c] + np.float64(intensity[r, c])
            bright[r + 1, c] = bright[r, c] + (intensity[r, c] > echo_level)
    shadow = np.zeros((h, w))
    tissue = np.zeros((h, w))
    for r in range(h):
        start, stop, count = _window(r, gap, gap + depth, h)
        if count > 0:
            high, low, level = total[stop], total[start], expected[r]
            for c in range(w):
                value = 1.0 - ((high[c] - low[c]) / count) / level
                shadow[r, c] = min(max(value, 0.0), 1.0)
        start, stop, count = _window(r, -gap - above_n, -gap, h)
        if count >= min_above:
            high, low = total[stop], total[start]
            for c in range(w):
                tissue[r, c] = min(max(((high[c] - low[c]) / count) / tissue_ref, 0.0), 1.0)
            if min_fill > 0:
                on, off = bright[stop], bright[start]
                for c in range(w):
                    fill = np.float64(on[c] - off[c]) / count
                    tissue[r, c] *= min(max(fill / min_fill, 0.0), 1.0)
    return shadow, tissue


@njit(cache=True)
def _power(x, exponent):
    """``x ** exponent`` for the exponents 1 and 2, as numpy computes them (exact)."""
    return x if exponent == 1 else x * x


@njit(cache=True)
def _probability_kernel(norm, ridge, shadow, tissue, powers):
    h, w = norm.shape
    out = np.empty((h, w), np.float32)
    for r in range(h):
        for c in range(w):
            image_terms = _power(norm[r, c], powers[0]) * _power(ridge[r, c], powers[1])
            out[r, c] = np.float32(np.float64(image_terms) * _power(shadow[r, c], powers[2])
                                   * _power(tissue[r, c], powers[3]))
    return out


def bone_probability(norm: np.ndarray, ridge: np.ndarray, shadow: np.ndarray,
                     tissue: np.ndarray, powers) -> np.ndarray:
    """``((norm ** p0) * (ridge ** p1) * (shadow ** p2) * (tissue ** p3)).astype(float32)``
    with numpy's bits: ``norm``, ``ridge`` ``(h, w)`` float32, ``shadow``, ``tissue`` ``(h, w)``
    float64, ``powers`` the four exponents; compiled when every exponent is 1 or 2 (the
    defaults), numpy's own expression otherwise."""
    if all(p in (1.0, 2.0) for p in powers):
        return _probability_kernel(norm, ridge, shadow, tissue,
                                   np.array([int(p) for p in powers], np.int64))
    return ((norm ** powers[0]) * (ridge ** powers[1]) * (shadow ** powers[2])
            * (tissue ** powers[3])).astype(np.float32)
