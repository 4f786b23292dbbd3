"""Compounding a tracked sweep into a 3D volume (nearest voxel, mean or max) on the grid PLUS's
volume reconstruction uses, to look at it.
"""

from __future__ import annotations

import numpy as np

from comreg_core.config import ConfigError
from comreg_core.errors import ComRegError
from comreg_core.io.sweeps import TrackedSweep
from comreg_core.io.volumes import Volume
from comreg_core.surfaces.us_kernels import bin_max, bin_sum, divide_by_count


def compounding_grid(sweep: TrackedSweep, spacing_mm=0.5, clip_origin=(0, 0), clip_size=None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """PLUS's output grid for the valid frames: ``origin`` ``(3,)`` mm = the minimum of all
    (clipped) frame corners, ``dims`` ``(3,)`` = ``int((max - min) / spacing) + 1``."""
    spacing = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,))
    corners = sweep.frame_corners(clip_origin, clip_size)[sweep.valid].reshape(-1, 3)
    if len(corners) == 0:
        sweep.only_valid()
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    return lo, ((hi - lo) / spacing).astype(np.int64) + 1


def compound_sweep(sweep: TrackedSweep, spacing_mm: float = 0.5, mode: str = "mean", *,
                   clip_origin=(0, 0), clip_size=None, max_voxels: int = 100_000_000
                   ) -> Volume:
    """Compound the valid frames into a 3D :class:`~comreg_core.io.volumes.Volume` (reference
    frame, taken as LPS, axis aligned) on :func:`compounding_grid`: every pixel goes to its
    nearest voxel; a voxel holds the ``"mean"`` or ``"max"`` of its pixels (0 where none).
    Voxels keep the frames' type. Write it with :func:`~comreg_core.io.volumes.write_volume`."""
    if mode not in ("mean", "max"):
        raise ConfigError(f"Compounding mode '{mode}' is unknown.", "Use 'mean' or 'max'.")
    if not spacing_mm > 0:
        raise ConfigError(f"Compounding spacing {spacing_mm} mm must be positive.", "")
    origin, dims = compounding_grid(sweep, spacing_mm, clip_origin, clip_size)
    if int(np.prod(dims)) > max_voxels:
        raise ComRegError(f"A {spacing_mm} mm grid over this sweep needs "
                          f"{' x '.join(map(str, dims))} voxels.", "Choose a larger spacing.")
    H, W = sweep.image_shape
    c0, r0 = (max(0, int(v)) for v in clip_origin)
    c1, r1 = W - 1, H - 1
    if clip_size is not None and min(clip_size) > 0:
        c1, r1 = min(c1, c0 + int(clip_size[0])), min(r1, r0 + int(clip_size[1]))
    rr, cc = np.mgrid[r0:r1 + 1, c0:c1 + 1]
    rr, cc = rr.ravel(), cc.ravel()
    local = np.column_stack([cc * sweep.spacing[0], rr * sweep.spacing[1]])
    size = int(np.prod(dims))
    frames, dtype = np.flatnonzero(sweep.valid), sweep.frames.dtype
    total = np.zeros(size, dtype=np.float64)  # the sums, then the means; or the maxima
    count = np.zeros(size, dtype=np.int32 if len(rr) * len(frames) < 2**31 else np.int64) \
        if mode == "mean" else None
    # small integer pixels sum exactly in any order; other pixels are summed in order per chunk
    # of frames, then added to the total
    exact = mode == "max" or (dtype.kind in "biu" and dtype.itemsize <= 2)
    per_chunk = max(1, 5_000_000 // max(len(rr), 1))
    p = np.empty((len(rr), 3))  # the pixels' positions (mm from the origin) in one frame
    for start in range(0, len(frames), per_chunk):
        part = total if exact else np.zeros(size, dtype=np.float64)
        for f in frames[start:start + per_chunk]:
            T = sweep.T_ref_image[f]
            np.matmul(local, T[:3, :2].T, out=p)
            p += T[:3, 3] - origin
            if mode == "mean":
                bin_sum(p, float(spacing_mm), dims, sweep.frames[f], rr, cc, part, count)
            else:
                bin_max(p, float(spacing_mm), dims, sweep.frames[f], rr, cc, part)
        if part is not total:
            total += part
    if mode == "mean":
        divide_by_count(total, count)
    array = total
    if dtype.kind in "ui":
        array = np.rint(array, out=array)
    array = array.astype(dtype).reshape(tuple(dims), order="F")
    return Volume.from_geometry(array, (spacing_mm,) * 3, origin, np.eye(3), "LPS")
