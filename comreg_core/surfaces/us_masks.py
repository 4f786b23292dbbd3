"""Bone surface points from label masks: bone pixels of mask frames (or of a label volume
resampled onto the frames) -> image mm -> reference mm, optionally thinned to the top edge of each
bone run along the beam (the surface the echo comes from).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from comreg_core.errors import ComRegError, CorruptFileError
from comreg_core.io._files import file_extension, require_input_file
from comreg_core.io.frame_folders import FRAME_IMAGE_EXTENSIONS, read_frame_image
from comreg_core.io.plus_files import frames_to_mf, read_plus_frames
from comreg_core.io.segmentations import read_segmentation
from comreg_core.io.sweeps import TrackedSweep
from comreg_core.surfaces.us_points import USSurfacePoints, collect_surface_points, frames_to_use

log = logging.getLogger(__name__)


def surface_from_masks(sweep: TrackedSweep, masks: np.ndarray, *, top_edge: bool = True,
                       frame_step: int = 1) -> USSurfacePoints:
    """Bone points from label masks ``(N, H, W)`` (non-zero = bone) aligned with the sweep's
    frames: every bone pixel, or with ``top_edge`` the first pixel of each run of bone pixels
    along each scan line (column), mapped to the reference frame."""
    masks = np.asarray(masks)
    if masks.shape != sweep.frames.shape:
        raise ComRegError(f"The masks have shape {masks.shape} (frames, rows, columns) but the "
                          f"sweep's frames are {sweep.frames.shape}.",
                          "Give one mask per frame, of the frame's size (inconsistent frame "
                          "counts or sizes).")
    use = frames_to_use(sweep, frame_step)
    points, frames, scores = [], [], []
    for f in use:
        m = masks[f] != 0
        if top_edge:
            m = m & ~np.vstack([np.zeros((1, m.shape[1]), bool), m[:-1]])
        rows, cols = np.nonzero(m)
        if len(rows) == 0:
            continue
        points.append(sweep.pixel_to_reference(np.full(len(rows), f), rows, cols))
        frames.append(np.full(len(rows), f))
        scores.append(np.ones(len(rows)))
    return collect_surface_points(sweep, points, frames, scores, len(use), "bone masks")


def read_masks(path: str | Path, sweep: TrackedSweep) -> np.ndarray:
    """Bone masks ``(N, H, W)`` bool for ``sweep``'s frames from:

    - a folder of images named like the frames (``<frame name>.png``), or exactly one image per
      frame (taken in sorted order);
    - ``.npy`` ``(N, H, W)``;
    - a mask sequence (``.igs.mha``, ``.seq.nrrd``, ...) or a frame stack volume
      (``.nrrd``/``.mha`` with ``W x H x N`` voxels), one frame per sweep frame;
    - any other label volume (``.nrrd``, ``.mha``, ``.seg.nrrd``) placed in the sweep's
      reference frame, sampled at each frame's pixels (nearest voxel, LPS).
    """
    path = Path(path)
    N, H, W = sweep.frames.shape
    if path.is_dir():
        files = {p.stem: p for p in sorted(path.iterdir())
                 if p.is_file() and p.suffix.lower() in FRAME_IMAGE_EXTENSIONS}
        if all(name in files for name in sweep.frame_names):
            chosen = [files[name] for name in sweep.frame_names]
        elif len(files) == N:
            log.info("%s: mask names do not match the frame names; taking the %d masks in "
                     "sorted order", path, N)
            chosen = [files[k] for k in sorted(files)]
        else:
            missing = [name for name in sweep.frame_names if name not in files]
            raise ComRegError(
                f"'{path}' holds {len(files)} mask images for {N} frames and lacks masks for "
                f"{len(missing)} frames (first: '{missing[0]}').",
                "Name each mask like its frame (e.g. 162005.png) or give one mask per frame.")
        masks = np.stack([read_frame_image(p) for p in chosen]) if chosen else np.zeros((0,))
        return _check_masks(path, masks, sweep)
    path = require_input_file(path, "mask file")
    ext = file_extension(path)
    if ext == ".npy":
        try:
            masks = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise CorruptFileError(path, f"not a valid .npy array ({exc})") from None
        return _check_masks(path, masks, sweep)
    if ext in (".igs.mha", ".seq.mha", ".igs.nrrd", ".seq.nrrd"):
        fields, masks = read_plus_frames(path)
        return _check_masks(path, frames_to_mf(path, fields, masks), sweep)
    seg = read_segmentation(path)
    labels = seg.layers.max(axis=0) if len(seg.layers) else seg.layers
    if labels.shape == (W, H, N):
        return _check_masks(path, np.transpose(labels, (2, 1, 0)), sweep)
    return _sample_label_volume(labels, seg.geometry(labels).in_space("LPS").ijk_to_space, sweep)


def _check_masks(path: Path, masks: np.ndarray, sweep: TrackedSweep) -> np.ndarray:
    masks = np.asarray(masks)
    if masks.shape != sweep.frames.shape:
        raise ComRegError(
            f"The masks in '{path}' have shape {masks.shape} (frames, rows, columns) but the "
            f"sweep has {sweep.frames.shape}.",
            "Give one mask per frame, of the frame's size (inconsistent frame counts).")
    return masks != 0


def _sample_label_volume(labels: np.ndarray, ijk_to_space: np.ndarray, sweep: TrackedSweep
                         ) -> np.ndarray:
    """``(N, H, W)`` bool: the label volume's value at every pixel centre of every frame."""
    N, H, W = sweep.frames.shape
    space_to_ijk = np.linalg.inv(ijk_to_space)
    rr, cc = np.mgrid[0:H, 0:W]
    pixel = np.stack([cc.ravel(), rr.ravel(), np.zeros(H * W), np.ones(H * W)])
    masks = np.zeros((N, H, W), dtype=bool)
    for f in np.flatnonzero(sweep.valid):
        ijk = (space_to_ijk @ sweep.T_ref_pixel[f] @ pixel)[:3]
        idx = np.rint(ijk).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < np.array(labels.shape)[:, None]), axis=0)
        values = np.zeros(H * W, dtype=bool)
        values[inside] = labels[idx[0, inside], idx[1, inside], idx[2, inside]] != 0
        masks[f] = values.reshape(H, W)
    if not masks.any():
        log.warning("the label volume does not overlap any frame of the sweep; is it in the "
                    "sweep's reference frame?")
    return masks
