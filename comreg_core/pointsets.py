"""Point sets as numpy arrays: farthest point sampling, the one implementation of it.

Numpy only (and ``fpsample``, a dependency, when it can be imported): no torch, nothing of
ComReg above this module, so ``surfaces`` and ``model`` both use it. Points are ``(N, 3)`` in
any unit; indices are int64.
"""

from __future__ import annotations

import math

import numpy as np

try:  # a declared dependency; a bare 3D Slicer Python may lack it until pip_install
    import fpsample
except ImportError:
    fpsample = None


def fps_bucket_height(n_points: int) -> int:
    """Bucket height for fpsample's bucket FPS on ``n_points`` points: ``2 ** height`` points
    per KD-tree leaf, from 1 (small clouds) to 9 (large ones, fpsample's recommendation), and
    never more leaves' worth than there are points."""
    height = int(min(9, max(1, round(math.log2(n_points)) - 5)))
    while 2 ** height > n_points:
        height -= 1
    return height


def farthest_point_indices(points: np.ndarray, n: int, start: int = 0) -> np.ndarray:
    """Indices ``(min(n, N),)`` int64 of exact farthest point sampling of ``(N, 3)`` points.

    float32 and float64 points keep the type the caller gives them (the two can pick different
    points on near ties); other types are read as float64. For ``n >= N`` all
    indices in order. With ``fpsample`` its bucket FPS runs, which applies ``start`` after an
    internal KD reordering: the first sample is another, fixed point and the rest is exact FPS
    from it. Without ``fpsample`` a numpy loop starts at ``start``.
    """
    points = np.asarray(points)
    if points.dtype not in (np.float32, np.float64):
        points = points.astype(np.float64)
    N = len(points)
    if n >= N:
        return np.arange(N)
    if fpsample is not None and N >= 2:
        return np.asarray(fpsample.bucket_fps_kdline_sampling(
            points, n, fps_bucket_height(N), start_idx=start), dtype=np.int64)
    chosen = np.empty(n, dtype=np.int64)
    chosen[0] = start
    dist = np.sum((points - points[start]) ** 2, axis=1)
    for i in range(1, n):
        chosen[i] = int(np.argmax(dist))
        np.minimum(dist, np.sum((points - points[chosen[i]]) ** 2, axis=1), out=dist)
    return chosen
