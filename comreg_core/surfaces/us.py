"""Ultrasound bone surfaces: a tracked sweep -> bone surface points in the reference frame (mm).

Two sources:

- **Label masks** (:func:`surface_from_masks`): bone pixels of mask frames (or of a label volume
  resampled onto the frames) -> image mm -> reference mm, optionally thinned to the top edge of
  each bone run along the beam (the surface the echo comes from).
- **Raw B-mode** (:func:`detect_bone_surface`): a classical, shadow-aware detector, no trained
  network. Bone reflects almost all the sound: its echo is a bright thin ridge under soft tissue
  with an acoustic shadow below it. Per pixel (at about 0.1 mm) the detector multiplies

  * ``intensity``: smoothed intensity / the frame's reference level (its 99th percentile, at
    least a fifth of its maximum), clipped to 1;
  * ``ridge``: the scale-normalised most negative Hessian eigenvalue (a bright line of any
    direction), saturating at ``ridge_saturation``;
  * ``shadow``: ``1 - mean(intensity below) / mean(row level below)`` over ``shadow_depth_mm``
    starting ``shadow_gap_mm`` under the pixel, where a row's level is its median (by default)
    over the imaged columns: how much darker the scan line is below the pixel than the image
    is at the same depths (depth attenuation cancels out);
  * ``tissue``: ``mean(intensity above) / median tissue intensity`` over ``tissue_depth_mm`` above
    the pixel, clipped to 1, times the echogenic fraction of that window: bone lies under soft
    tissue, while gel, skin folds, vessel walls and wires in a water bath lie under dark regions,

  each raised to its power, into a bone probability (zero outside the imaged columns: black
  margins of scan-converted frames are ignored). A Viterbi dynamic programme over the scan lines
  then picks, per column, either "no bone" or one depth, rewarding probability above
  ``threshold``, penalising depth changes between neighbouring scan lines and each start of a
  bone segment; segments narrower than ``min_segment_mm`` are dropped. Each depth is finally
  moved to the peak of the unclipped ridge response nearby (sub-pixel, by a parabola): the echo
  centre, which lies on the CT surface within 0.1 mm on the real fibula sweep (signed median).

Denoising (:func:`denoise_points`): DBSCAN-like cluster selection (radius in mm), statistical
outlier removal, then optional voxel or farthest-point downsampling.

:func:`compound_sweep` compounds a sweep into a 3D volume (nearest voxel, mean or max) on the grid
PLUS's volume reconstruction uses, to look at it. :func:`extract_us_to_file` is the library side
of ``comreg extract-us``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from scipy import ndimage

from comreg_core.config import ConfigError, load_config, require
from comreg_core.errors import ComRegError, CorruptFileError
from comreg_core.io._files import file_extension, require_input_file
from comreg_core.io.frame_folders import FRAME_IMAGE_EXTENSIONS, read_frame_image
from comreg_core.io.plus_files import frames_to_mf, read_plus_frames
from comreg_core.io.segmentations import read_segmentation
from comreg_core.io.sweeps import TrackedSweep
from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.pointsets import farthest_point_indices

log = logging.getLogger(__name__)

#: ``progress(done, total)``: frames processed so far.
Progress = Callable[[int, int], None]


class NoBoneFoundError(ComRegError):
    """No frame of the sweep shows a bone surface (or every mask is empty)."""


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BoneDetectorConfig:
    """The classical B-mode bone detector (see the module docstring). Lengths in mm.

    The defaults were set on every other frame of the UltraBones100k fibula sweep and checked on
    the others: raw detections within median 0.43 / 90th percentile 1.5 mm of the CT surface on
    the held-out frames, from 89% of them (tests/benchmarks/bench_us_detector.py prints the
    figures for the whole sweep).

    Attributes:
        working_pixel_mm: frames are block-averaged to about this pixel size first (0 = keep).
        smoothing_mm: Gaussian sigma of the intensity term.
        ridge_scale_mm: Gaussian sigma of the Hessian (about half the echo thickness).
        ridge_saturation: scale-normalised ridge strength (/ 99th percentile) counted as 1.
        shadow_gap_mm, shadow_depth_mm: the shadow window starts this far below a pixel and is
            this deep.
        shadow_reference_percentile: percentile over the imaged columns of each row that the
            shadow is compared with (50 = the median: right when the bone shadow covers less
            than half the image width; raise it when the bone fills most of the width).
        tissue_depth_mm: depth of the soft-tissue window above a pixel (ending shadow_gap_mm
            above it).
        tissue_min_fill: fraction of that window that must be echogenic (brighter than a
            quarter of the median tissue intensity) for full credit; 0 = no such check.
        min_depth_mm, max_depth_mm: depth range searched (below the transducer face); None =
            to the bottom.
        intensity_power, ridge_power, shadow_power, tissue_power: exponents of the four terms.
        threshold: probability above which a pixel counts as evidence for bone (0..1).
        max_slope_deg: steepest surface (to the array direction) followed between neighbouring
            scan lines.
        depth_change_penalty: cost per mm of depth change between neighbouring scan lines.
        segment_penalty: cost of starting a bone segment (probability x mm).
        min_segment_mm: bone segments narrower than this (along the array) are dropped.
        subpixel: refine each depth with a parabola through the probability.
    """

    working_pixel_mm: float = 0.1
    smoothing_mm: float = 0.1
    ridge_scale_mm: float = 0.3
    ridge_saturation: float = 0.2
    shadow_gap_mm: float = 1.0
    shadow_depth_mm: float = 10.0
    shadow_reference_percentile: float = 50.0
    tissue_depth_mm: float = 4.0
    tissue_min_fill: float = 0.75
    min_depth_mm: float = 2.0
    max_depth_mm: float | None = None
    intensity_power: float = 1.0
    ridge_power: float = 1.0
    shadow_power: float = 1.0
    tissue_power: float = 2.0
    threshold: float = 0.1
    max_slope_deg: float = 82.0
    depth_change_penalty: float = 0.05
    segment_penalty: float = 0.1
    min_segment_mm: float = 2.0
    subpixel: bool = True

    def __post_init__(self):
        for name in ("working_pixel_mm", "min_depth_mm", "smoothing_mm", "depth_change_penalty",
                     "segment_penalty", "min_segment_mm"):
            require(getattr(self, name) >= 0, f"detector.{name}", "must be >= 0")
        for name in ("ridge_scale_mm", "ridge_saturation", "shadow_depth_mm", "tissue_depth_mm"):
            require(getattr(self, name) > 0, f"detector.{name}", "must be > 0")
        require(self.shadow_gap_mm >= 0, "detector.shadow_gap_mm", "must be >= 0")
        for name in ("intensity_power", "ridge_power", "shadow_power", "tissue_power"):
            require(0 <= getattr(self, name) <= 10, f"detector.{name}", "must lie in [0, 10]")
        require(0 <= self.shadow_reference_percentile <= 100,
                "detector.shadow_reference_percentile", "must lie in [0, 100]")
        require(0 <= self.tissue_min_fill <= 1, "detector.tissue_min_fill", "must lie in [0, 1]")
        require(0 < self.threshold < 1, "detector.threshold", "must lie in (0, 1)")
        require(0 < self.max_slope_deg < 90, "detector.max_slope_deg", "must lie in (0, 90)")
        require(self.max_depth_mm is None or self.max_depth_mm > self.min_depth_mm,
                "detector.max_depth_mm", "must be larger than min_depth_mm")


@dataclass(frozen=True)
class DenoiseConfig:
    """Point-cloud clean-up after extraction. Lengths in mm; 0 switches a step off.

    Attributes:
        cluster_radius_mm: DBSCAN neighbourhood radius (0 = no cluster selection).
        cluster_min_points: neighbours (self included) that make a point a core point.
        min_cluster_fraction: keep clusters with at least this fraction of the largest
            cluster's points (1.0 = the largest cluster only). A sparse sweep (frames several
            mm apart) breaks the bone into several clusters: keep them with a small fraction.
        outlier_neighbors: k of the statistical outlier removal (0 = off).
        outlier_std_ratio: drop points whose mean distance to their k neighbours exceeds the
            mean over all points by this many standard deviations.
        downsample: "none", "voxel" (centroid per voxel of ``voxel_size_mm``) or "fps" (farthest
            points, ``target_points`` of them).
        voxel_size_mm: voxel edge for "voxel".
        target_points: points left by "fps"; with "voxel", an upper bound reached by farthest
            point sampling of the voxel centroids (0 = no bound).
    """

    cluster_radius_mm: float = 5.0
    cluster_min_points: int = 5
    min_cluster_fraction: float = 0.05
    outlier_neighbors: int = 16
    outlier_std_ratio: float = 2.5
    downsample: Literal["none", "voxel", "fps"] = "none"
    voxel_size_mm: float = 0.5
    target_points: int = 0

    def __post_init__(self):
        require(self.cluster_radius_mm >= 0, "denoise.cluster_radius_mm", "must be >= 0")
        require(self.cluster_min_points >= 1, "denoise.cluster_min_points", "must be >= 1")
        require(0 < self.min_cluster_fraction <= 1, "denoise.min_cluster_fraction",
                "must lie in (0, 1]")
        require(self.outlier_neighbors >= 0, "denoise.outlier_neighbors", "must be >= 0")
        require(self.outlier_std_ratio > 0, "denoise.outlier_std_ratio", "must be > 0")
        require(self.voxel_size_mm > 0, "denoise.voxel_size_mm", "must be > 0")
        require(self.target_points >= 0, "denoise.target_points", "must be >= 0")
        require(self.downsample != "fps" or self.target_points > 0, "denoise.target_points",
                "must be > 0 when downsample is 'fps'")


@dataclass(frozen=True)
class USExtractionConfig:
    """Everything ``comreg extract-us`` does (YAML section ``us_extraction``).

    Attributes:
        detector: the B-mode detector (used without masks).
        denoise: the clean-up of the extracted points.
        mask_top_edge: with masks, keep only the top pixel of each bone run along the beam.
        frame_step: use every n-th valid frame.
        reference: PLUS coordinate frame the points are given in.
    """

    detector: BoneDetectorConfig = field(default_factory=BoneDetectorConfig)
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)
    mask_top_edge: bool = True
    frame_step: int = 1
    reference: str = "Reference"

    def __post_init__(self):
        require(self.frame_step >= 1, "frame_step", "must be >= 1")


def load_us_extraction_config(path: str | Path | None = None,
                              overrides: dict | None = None) -> USExtractionConfig:
    """Defaults, updated from a YAML file (bare keys or a ``us_extraction`` section), then from
    ``overrides``."""
    return load_config(USExtractionConfig, path, overrides, section="us_extraction")


# --------------------------------------------------------------------------------------------
# B-mode bone detector
# --------------------------------------------------------------------------------------------


@dataclass
class BoneEvidence:
    """Detector maps of one frame at the working resolution.

    Attributes:
        intensity, ridge, shadow, tissue, probability: ``(h, w)`` in [0, 1].
        ridge_strength: ``(h, w)`` the unclipped ridge term (localises the echo centre where
            intensity and ridge saturate).
        factor: ``(ky, kx)`` block size of the working pixels in frame pixels.
        pixel_mm: ``(py, px)`` working pixel size in mm (depth, lateral).
    """

    intensity: np.ndarray
    ridge: np.ndarray
    shadow: np.ndarray
    tissue: np.ndarray
    probability: np.ndarray
    factor: tuple[int, int]
    pixel_mm: tuple[float, float]
    ridge_strength: np.ndarray | None = None


def _block_mean(frame: np.ndarray, ky: int, kx: int) -> np.ndarray:
    """``(H // ky, W // kx)`` float32 block means."""
    H, W = frame.shape
    h, w = H // ky, W // kx
    a = np.asarray(frame[:h * ky, :w * kx], dtype=np.float32)
    if ky == 1 and kx == 1:
        return a
    return a.reshape(h, ky, w, kx).mean(axis=(1, 3))


def _window_means(cum: np.ndarray, start: np.ndarray, stop: np.ndarray):
    """Means over rows ``[start, stop)`` (clipped) of the array whose row cumsum is ``cum``
    (``(h + 1, ...)``), and the row counts."""
    h = len(cum) - 1
    start = np.clip(start, 0, h)
    stop = np.clip(stop, 0, h)
    count = np.maximum(stop - start, 0)
    total = cum[stop] - cum[start]
    shape = (-1,) + (1,) * (cum.ndim - 1)
    return total / np.maximum(count, 1).reshape(shape), count


def bone_evidence(frame: np.ndarray, spacing, config: BoneDetectorConfig | None = None
                  ) -> BoneEvidence:
    """Per-pixel bone probability of one B-mode frame ``(H, W)`` (row 0 at the transducer) with
    pixel ``spacing`` ``(sx, sy)`` mm; see the module docstring."""
    c = config or BoneDetectorConfig()
    sx, sy = (float(v) for v in spacing)
    frame = np.asarray(frame)
    if frame.ndim != 2:
        raise ValueError(f"a frame must be (H, W), got shape {frame.shape}")
    ky = max(1, int(round(c.working_pixel_mm / sy))) if c.working_pixel_mm > 0 else 1
    kx = max(1, int(round(c.working_pixel_mm / sx))) if c.working_pixel_mm > 0 else 1
    a = _block_mean(frame, ky, kx)
    py, px = sy * ky, sx * kx
    h, w = a.shape
    zeros = np.zeros_like(a)
    if h < 3 or w < 3:
        return BoneEvidence(zeros, zeros, zeros, zeros, zeros, (ky, kx), (py, px))

    intensity = ndimage.gaussian_filter(a, (c.smoothing_mm / py, c.smoothing_mm / px))
    ref = max(float(np.percentile(intensity, 99)), 0.2 * float(intensity.max()))
    if not ref > 0:  # a blank frame
        return BoneEvidence(zeros, zeros, zeros, zeros, zeros, (ky, kx), (py, px))

    sigma = (c.ridge_scale_mm / py, c.ridge_scale_mm / px)
    iyy = ndimage.gaussian_filter(a, sigma, order=(2, 0)) / py ** 2
    ixx = ndimage.gaussian_filter(a, sigma, order=(0, 2)) / px ** 2
    ixy = ndimage.gaussian_filter(a, sigma, order=(1, 1)) / (px * py)
    lam_min = 0.5 * (iyy + ixx) - np.sqrt((0.5 * (iyy - ixx)) ** 2 + ixy ** 2)
    strength = -lam_min * c.ridge_scale_mm ** 2 / (ref * c.ridge_saturation)
    ridge = np.clip(strength, 0.0, 1.0)

    # Field of view: scan-converted frames often have black margins (or a black sector
    # outside the fan); the reference statistics are taken over imaged columns only.
    fov = np.percentile(intensity, 95, axis=0) > 0.05 * ref
    if not fov.any():
        return BoneEvidence(zeros, zeros, zeros, zeros, zeros, (ky, kx), (py, px))
    floor = 0.05 * ref  # a water bath or an empty image is not "tissue"
    rows = np.arange(h)
    gap = max(1, int(round(c.shadow_gap_mm / py)))
    depth = max(1, int(round(c.shadow_depth_mm / py)))
    above_n = max(1, int(round(c.tissue_depth_mm / py)))
    cum = np.vstack([np.zeros((1, w), np.float64), np.cumsum(intensity, axis=0, dtype=np.float64)])
    profile = np.maximum(np.percentile(intensity[:, fov], c.shadow_reference_percentile, axis=1),
                         floor)
    pcum = np.concatenate([[0.0], np.cumsum(profile, dtype=np.float64)])

    below, n_below = _window_means(cum, rows + gap, rows + gap + depth)
    expected, _ = _window_means(pcum, rows + gap, rows + gap + depth)
    shadow = np.clip(1.0 - below / np.maximum(expected, floor)[:, None], 0.0, 1.0)
    shadow[n_below == 0] = 0.0

    first = min(int(c.min_depth_mm / py), h - 1)
    tissue_ref = max(float(np.median(intensity[first:max(first + 1, h // 2)][:, fov])), floor)
    above, n_above = _window_means(cum, rows - gap - above_n, rows - gap)
    tissue = np.clip(above / tissue_ref, 0.0, 1.0)
    if c.tissue_min_fill > 0:  # mostly echogenic, not one bright reflector over water
        echo = np.vstack([np.zeros((1, w)), np.cumsum(intensity > 0.25 * tissue_ref, axis=0)])
        fill, _ = _window_means(echo, rows - gap - above_n, rows - gap)
        tissue *= np.clip(fill / c.tissue_min_fill, 0.0, 1.0)
    tissue[n_above < max(1, above_n // 2)] = 0.0

    norm = np.clip(intensity / ref, 0.0, 1.0)
    probability = ((norm ** c.intensity_power) * (ridge ** c.ridge_power)
                   * (shadow ** c.shadow_power) * (tissue ** c.tissue_power)).astype(np.float32)
    probability[:first] = 0.0
    probability[:, ~fov] = 0.0
    if c.max_depth_mm is not None:
        probability[int(math.ceil(c.max_depth_mm / py)):] = 0.0
    return BoneEvidence(norm.astype(np.float32), ridge.astype(np.float32),
                        shadow.astype(np.float32), tissue.astype(np.float32), probability,
                        (ky, kx), (py, px), strength.astype(np.float32))


def _viterbi(gain: np.ndarray, max_step: int, step_cost: float, switch_cost: float
             ) -> np.ndarray:
    """Best path through the columns of ``gain`` ``(h, w)`` (reward of "bone at row r in column
    c"; "no bone" earns 0). Moving between bone rows r -> r' in neighbouring columns costs
    ``step_cost * |r - r'|`` and is allowed for ``|r - r'| <= max_step``; entering or leaving
    bone costs ``switch_cost``. Returns ``(w,)`` rows, -1 where there is no bone."""
    h, w = gain.shape
    shifts = np.arange(-max_step, max_step + 1)
    source = np.arange(h)[:, None] + shifts[None, :]  # (h, S): candidate previous rows
    inside = (source >= 0) & (source < h)
    source = np.clip(source, 0, h - 1)
    penalty = np.where(inside, step_cost * np.abs(shifts)[None, :], np.inf)
    back = np.empty((w, h), dtype=np.int32)  # previous bone row, or -1 = came from "no bone"
    off_from = np.full(w, -1, dtype=np.int32)  # row the "no bone" state left bone at, or -1
    v_bone = gain[:, 0].astype(np.float64) - switch_cost
    v_off = 0.0
    rows = np.arange(h)
    for col in range(1, w):
        cand = v_bone[source] - penalty
        best = np.argmax(cand, axis=1)
        stay = cand[rows, best]
        enter = v_off - switch_cost
        from_bone = stay >= enter
        back[col] = np.where(from_bone, source[rows, best], -1)
        top = int(np.argmax(v_bone))
        leave = v_bone[top] - switch_cost
        new_off = v_off
        if leave > v_off:
            new_off, off_from[col] = leave, top
        v_bone = np.where(from_bone, stay, enter) + gain[:, col]
        v_off = new_off
    path = np.full(w, -1, dtype=np.int64)
    top = int(np.argmax(v_bone))
    in_bone = v_bone[top] - switch_cost > v_off
    row = top
    for col in range(w - 1, -1, -1):
        if in_bone:
            path[col] = row
            previous = int(back[col, row]) if col > 0 else -1
            if previous < 0:
                in_bone = False
            else:
                row = previous
        elif col > 0 and off_from[col] >= 0:
            in_bone, row = True, int(off_from[col])
    return path


@dataclass
class FrameDetection:
    """Bone surface pixels found in one frame.

    Attributes:
        rows, cols: ``(K,)`` float pixel positions in the full-resolution frame.
        score: ``(K,)`` bone probability there.
    """

    rows: np.ndarray
    cols: np.ndarray
    score: np.ndarray


def detect_bone_surface(frame: np.ndarray, spacing, config: BoneDetectorConfig | None = None
                        ) -> FrameDetection:
    """Bone surface pixels of one B-mode frame ``(H, W)`` (row 0 at the transducer), pixel
    ``spacing`` ``(sx, sy)`` mm; at most one per scan line (column). Empty when no bone is
    seen."""
    c = config or BoneDetectorConfig()
    ev = bone_evidence(frame, spacing, c)
    (ky, kx), (py, px) = ev.factor, ev.pixel_mm
    P = ev.probability
    empty = FrameDetection(np.zeros(0), np.zeros(0), np.zeros(0))
    if not (P > c.threshold).any():
        return empty
    max_step = max(1, int(round(math.tan(math.radians(c.max_slope_deg)) * px / py)))
    gain = (P - c.threshold) * px
    path = _viterbi(gain, max_step, c.depth_change_penalty * py, c.segment_penalty)
    cols = np.flatnonzero(path >= 0)
    if len(cols) == 0:
        return empty
    rows = path[cols]
    segment = np.concatenate([[0], np.cumsum(np.diff(cols) > 1)])
    width = np.bincount(segment) * px
    keep = width[segment] >= max(c.min_segment_mm, 1e-9)
    rows, cols = rows[keep], cols[keep]
    if len(cols) == 0:
        return empty
    score = P[rows, cols].astype(np.float64)
    offset = np.zeros(len(rows))
    if c.subpixel:
        # Locate the echo centre on the unclipped ridge response near the chosen row (the
        # probability saturates on strong echoes), then fit a parabola through its peak.
        R = ev.ridge_strength
        h = P.shape[0]
        reach = max(1, int(round(c.ridge_scale_mm / py)))
        window = np.clip(rows[:, None] + np.arange(-reach, reach + 1)[None, :], 0, h - 1)
        rows = window[np.arange(len(rows)), np.argmax(R[window, cols[:, None]], axis=1)]
        inner = (rows > 0) & (rows < h - 1)
        r, cc = rows[inner], cols[inner]
        up, mid, down = R[r - 1, cc], R[r, cc], R[r + 1, cc]
        curvature = up - 2 * mid + down
        with np.errstate(divide="ignore", invalid="ignore"):
            delta = np.where(curvature < 0, 0.5 * (up - down) / curvature, 0.0)
        offset[inner] = np.clip(np.nan_to_num(delta), -0.5, 0.5)
    full_rows = (rows + offset) * ky + (ky - 1) / 2.0
    full_cols = cols * kx + (kx - 1) / 2.0
    return FrameDetection(full_rows, full_cols.astype(np.float64), score)


# --------------------------------------------------------------------------------------------
# Points of a sweep
# --------------------------------------------------------------------------------------------


@dataclass
class USSurfacePoints:
    """Bone surface points of a sweep, in the sweep's reference frame.

    Attributes:
        points: ``(M, 3)`` mm.
        frame_index: ``(M,)`` index of the sweep frame each point comes from (-1 after
            downsampling merged points).
        score: ``(M,)`` bone probability (1 for masks).
        frames_examined: frames looked at (valid, every ``frame_step``-th).
        frames_with_bone: frames that gave at least one point.
        reference: the coordinate frame of ``points``.
    """

    points: np.ndarray
    frame_index: np.ndarray
    score: np.ndarray
    frames_examined: int
    frames_with_bone: int
    reference: str = "Reference"

    def subset(self, keep) -> "USSurfacePoints":
        keep = np.asarray(keep)
        return USSurfacePoints(self.points[keep], self.frame_index[keep], self.score[keep],
                               self.frames_examined,
                               len(np.unique(self.frame_index[keep][self.frame_index[keep] >= 0])),
                               self.reference)


def _frames_to_use(sweep: TrackedSweep, frame_step: int) -> np.ndarray:
    valid = np.flatnonzero(sweep.valid)
    if len(valid) == 0:
        sweep.only_valid()  # raises NoValidFramesError with the message
    return valid[::frame_step]


def detect_sweep_surface(sweep: TrackedSweep, config: BoneDetectorConfig | None = None, *,
                         frame_step: int = 1, progress: Progress | None = None
                         ) -> USSurfacePoints:
    """Run :func:`detect_bone_surface` on the valid frames of ``sweep`` (every
    ``frame_step``-th) and map the pixels to the reference frame."""
    config = config or BoneDetectorConfig()
    use = _frames_to_use(sweep, frame_step)
    points, frames, scores = [], [], []
    for done, f in enumerate(use, start=1):
        found = detect_bone_surface(sweep.frames[f], sweep.spacing, config)
        if len(found.rows):
            points.append(sweep.pixel_to_reference(np.full(len(found.rows), f), found.rows,
                                                   found.cols))
            frames.append(np.full(len(found.rows), f))
            scores.append(found.score)
        if progress is not None:
            progress(done, len(use))
    return _collect(sweep, points, frames, scores, len(use), "B-mode detector")


def _collect(sweep, points, frames, scores, examined, source) -> USSurfacePoints:
    with_bone = len(points)
    where = f" of '{sweep.path}'" if sweep.path else ""
    if with_bone == 0:
        raise NoBoneFoundError(
            f"No bone surface was found in any of the {examined} frames{where} ({source}).",
            "Check that the frames are B-mode images with the transducer at the top and the bone "
            "echo visible, lower detector.threshold in the config, or pass bone masks.")
    if with_bone < 0.5 * examined:
        log.warning("%s: only %d of %d frames show a bone surface (%s); the others gave no "
                    "points", sweep.path or "sweep", with_bone, examined, source)
    else:
        log.info("%s: bone found in %d of %d frames (%s)", sweep.path or "sweep", with_bone,
                 examined, source)
    return USSurfacePoints(np.concatenate(points), np.concatenate(frames),
                           np.concatenate(scores), examined, with_bone, sweep.reference)


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
    use = _frames_to_use(sweep, frame_step)
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
    return _collect(sweep, points, frames, scores, len(use), "bone masks")


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


# --------------------------------------------------------------------------------------------
# Denoising
# --------------------------------------------------------------------------------------------


def cluster_labels(points: np.ndarray, radius_mm: float, min_points: int = 5) -> np.ndarray:
    """DBSCAN labels ``(N,)`` (-1 = noise) of ``(N, 3)`` points: core points have at least
    ``min_points`` points (self included) within ``radius_mm``; core points closer than the
    radius share a cluster; other points join the cluster of their nearest core point within
    the radius. Clusters are numbered by decreasing size."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels
    tree = cKDTree(points)
    counts = tree.query_ball_point(points, radius_mm, return_length=True)
    core = np.flatnonzero(counts >= min_points)
    if len(core) == 0:
        return labels
    pairs = cKDTree(points[core]).query_pairs(radius_mm, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(core), len(core)))
    _, component = connected_components(graph, directed=False)
    labels[core] = component
    border = np.setdiff1d(np.arange(n), core)
    if len(border):
        d, nearest = cKDTree(points[core]).query(points[border], distance_upper_bound=radius_mm)
        hit = np.isfinite(d)
        labels[border[hit]] = component[nearest[hit]]
    sizes = np.bincount(labels[labels >= 0])
    rank = np.empty_like(sizes)
    rank[np.argsort(-sizes, kind="stable")] = np.arange(len(sizes))
    labels[labels >= 0] = rank[labels[labels >= 0]]
    return labels


def select_clusters(points: np.ndarray, radius_mm: float, min_points: int = 5,
                    min_fraction: float = 1.0) -> np.ndarray:
    """Boolean mask ``(N,)`` of the points in DBSCAN clusters holding at least ``min_fraction``
    of the largest cluster's points (1.0 = largest cluster only)."""
    labels = cluster_labels(points, radius_mm, min_points)
    if (labels < 0).all():
        return np.zeros(len(points), dtype=bool)
    sizes = np.bincount(labels[labels >= 0])
    kept = np.flatnonzero(sizes >= min_fraction * sizes.max())
    return np.isin(labels, kept)


def statistical_outliers(points: np.ndarray, k: int = 16, std_ratio: float = 2.5) -> np.ndarray:
    """Boolean mask ``(N,)`` of inliers: points whose mean distance to their ``k`` nearest
    neighbours is at most mean + ``std_ratio`` * std of that distance over all points (PCL's
    StatisticalOutlierRemoval)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    if len(points) <= k:
        return np.ones(len(points), dtype=bool)
    d, _ = cKDTree(points).query(points, k=k + 1)
    mean = d[:, 1:].mean(axis=1)
    return mean <= mean.mean() + std_ratio * mean.std()


def voxel_downsample(points: np.ndarray, voxel_mm: float) -> np.ndarray:
    """``(M, 3)`` centroids of the points in each occupied cubic voxel of edge ``voxel_mm``,
    in order of first occurrence."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return points.reshape(0, 3)
    keys = np.floor((points - points.min(axis=0)) / voxel_mm).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse)
    sums = np.stack([np.bincount(inverse, weights=points[:, i]) for i in range(3)], axis=1)
    order = np.argsort(first, kind="stable")
    return (sums / counts[:, None])[order]


def denoise_points(surface: USSurfacePoints, config: DenoiseConfig | None = None
                   ) -> USSurfacePoints:
    """Cluster selection, outlier removal, then downsampling of extracted points. Points merged
    by voxel downsampling get ``frame_index`` -1 and the mean score."""
    c = config or DenoiseConfig()
    out = surface
    if c.cluster_radius_mm > 0 and len(out.points):
        keep = select_clusters(out.points, c.cluster_radius_mm, c.cluster_min_points,
                               c.min_cluster_fraction)
        log.info("cluster selection (%.3g mm): kept %d of %d points", c.cluster_radius_mm,
                 int(keep.sum()), len(keep))
        out = out.subset(keep)
    if c.outlier_neighbors > 0 and len(out.points):
        keep = statistical_outliers(out.points, c.outlier_neighbors, c.outlier_std_ratio)
        log.info("outlier removal: kept %d of %d points", int(keep.sum()), len(keep))
        out = out.subset(keep)
    if c.downsample == "voxel" and len(out.points):
        frames_with_bone = out.frames_with_bone
        points = voxel_downsample(out.points, c.voxel_size_mm)
        score = np.full(len(points), float(out.score.mean()))
        out = USSurfacePoints(points, np.full(len(points), -1), score, out.frames_examined,
                              frames_with_bone, out.reference)
    if c.target_points > 0 and len(out.points) > c.target_points:
        merged = bool((out.frame_index < 0).any())
        frames_with_bone = out.frames_with_bone
        out = out.subset(farthest_point_indices(np.asarray(out.points, dtype=np.float64),
                                                c.target_points))
        if merged:
            out.frames_with_bone = frames_with_bone
    if len(out.points) == 0:
        raise NoBoneFoundError("Denoising removed every extracted bone point.",
                               "Loosen the denoise settings (cluster_radius_mm, "
                               "min_cluster_fraction, outlier_std_ratio) in the config.")
    return out


# --------------------------------------------------------------------------------------------
# Whole pipeline and the CLI's library function
# --------------------------------------------------------------------------------------------


@dataclass
class USExtractionResult:
    """What :func:`extract_us_surface` found.

    Attributes:
        points: the final (denoised) :class:`USSurfacePoints`.
        raw: the points before denoising.
        source: "masks" or "detector".
        frames_total, frames_valid: frames in the sweep, and with a valid pose.
        output: the file written by :func:`extract_us_to_file`, if any.
    """

    points: USSurfacePoints
    raw: USSurfacePoints
    source: str
    frames_total: int
    frames_valid: int
    output: Path | None = None

    def summary(self) -> str:
        """One line for the command line."""
        where = f" -> {self.output}" if self.output else ""
        return (f"{len(self.points.points)} bone points ({len(self.raw.points)} before denoising)"
                f" from {self.points.frames_with_bone} of {self.raw.frames_examined} frames "
                f"({self.source}; {self.frames_valid} of {self.frames_total} frames tracked)"
                f"{where}")


def extract_us_surface(sweep: TrackedSweep, config: USExtractionConfig | None = None, *,
                       masks: np.ndarray | None = None, progress: Progress | None = None
                       ) -> USExtractionResult:
    """Bone surface points of ``sweep``: from ``masks`` ``(N, H, W)`` when given, else from the
    B-mode detector; then denoised."""
    config = config or USExtractionConfig()
    if masks is not None:
        raw = surface_from_masks(sweep, masks, top_edge=config.mask_top_edge,
                                 frame_step=config.frame_step)
        source = "masks"
    else:
        raw = detect_sweep_surface(sweep, config.detector, frame_step=config.frame_step,
                                   progress=progress)
        source = "detector"
    return USExtractionResult(denoise_points(raw, config.denoise), raw, source, sweep.n_frames,
                              int(sweep.valid.sum()))


def extract_us_to_file(sweep: str | Path | TrackedSweep, out: str | Path, *,
                       calibration: str | Path | None = None, masks: str | Path | None = None,
                       config: str | Path | USExtractionConfig | None = None,
                       progress: Progress | None = None) -> USExtractionResult:
    """``comreg extract-us SWEEP --out POINTS [--calibration FILE] [--masks DIR] [--config FILE]``:
    read the sweep, extract and denoise its bone surface, write the points (``.ply``, ``.pcd``,
    ``.xyz``, ``.npy``, ... in the sweep's reference frame, tagged LPS) atomically."""
    from comreg_core.io.pointclouds import PointCloud, write_points

    check_us_outputs(out, inputs=[sweep, calibration, masks, config])  # fail before the work
    if not isinstance(config, USExtractionConfig):
        config = load_us_extraction_config(config)
    if not isinstance(sweep, TrackedSweep):
        sweep = read_tracked_sweep(sweep, calibration=calibration, reference=config.reference)
    mask_frames = read_masks(masks, sweep) if masks is not None else None
    result = extract_us_surface(sweep, config, masks=mask_frames, progress=progress)
    result.output = write_points(PointCloud(result.points.points, "LPS"), out)
    log.info("%s", result.summary())
    return result


def check_us_outputs(out: str | Path, compound: str | Path | None = None, *, inputs=()) -> None:
    """Check the outputs of ``comreg extract-us`` before any work: the point cloud ``out`` and
    the optional compounded volume ``compound`` (extensions, places, not an input, distinct)."""
    from comreg_core.errors import OutputPlaceError
    from comreg_core.io._files import check_output_file, require_extension
    from comreg_core.io.pointclouds import POINT_CLOUD_EXTENSIONS
    from comreg_core.io.volumes import VOLUME_WRITE_EXTENSIONS

    inputs = [i for i in inputs if isinstance(i, (str, Path))]
    require_extension(out, "point cloud", POINT_CLOUD_EXTENSIONS)
    check_output_file(out, inputs=inputs, what="output point cloud")
    if compound is not None:
        require_extension(compound, "compounded volume", VOLUME_WRITE_EXTENSIONS)
        check_output_file(compound, inputs=inputs, what="compounded volume")
        if Path(compound).absolute() == Path(out).absolute():
            raise OutputPlaceError(f"--out and --compound are the same file '{out}'.",
                                   "Give them different names.")


# --------------------------------------------------------------------------------------------
# Compounding
# --------------------------------------------------------------------------------------------


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
                   clip_origin=(0, 0), clip_size=None, max_voxels: int = 100_000_000):
    """Compound the valid frames into a 3D :class:`~comreg_core.io.volumes.Volume` (reference
    frame, taken as LPS, axis aligned) on :func:`compounding_grid`: every pixel goes to its
    nearest voxel; a voxel holds the ``"mean"`` or ``"max"`` of its pixels (0 where none).
    Voxels keep the frames' type. Write it with :func:`~comreg_core.io.volumes.write_volume`."""
    from comreg_core.io.volumes import Volume

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
    total = np.zeros(size, dtype=np.float64) if mode == "mean" else None
    count = np.zeros(size, dtype=np.int64) if mode == "mean" else None
    peak = np.zeros(size, dtype=np.float64) if mode == "max" else None
    frames = np.flatnonzero(sweep.valid)
    per_chunk = max(1, 5_000_000 // max(len(rr), 1))  # pixels binned together
    for start in range(0, len(frames), per_chunk):
        flat_parts, value_parts = [], []
        for f in frames[start:start + per_chunk]:
            T = sweep.T_ref_image[f]
            p = local @ T[:3, :2].T + (T[:3, 3] - origin)
            ijk = np.rint(p / spacing_mm).astype(np.int64)
            inside = np.all((ijk >= 0) & (ijk < dims), axis=1)
            flat_parts.append(np.ravel_multi_index(ijk[inside].T, dims, order="F"))
            value_parts.append(sweep.frames[f][rr[inside], cc[inside]].astype(np.float64))
        flat, values = np.concatenate(flat_parts), np.concatenate(value_parts)
        if mode == "mean":
            total += np.bincount(flat, weights=values, minlength=size)
            count += np.bincount(flat, minlength=size)
        else:
            np.maximum.at(peak, flat, values)
    if mode == "mean":
        array = np.where(count > 0, total / np.maximum(count, 1), 0.0)
    else:
        array = peak
    dtype = sweep.frames.dtype
    if dtype.kind in "ui":
        array = np.rint(array)
    array = array.astype(dtype).reshape(tuple(dims), order="F")
    return Volume.from_geometry(array, (spacing_mm,) * 3, origin, np.eye(3), "LPS")
