"""The classical B-mode bone detector: a tracked sweep's raw frames -> bone surface points, no
trained network.

Bone reflects almost all the sound: its echo is a bright thin ridge under soft tissue with an
acoustic shadow below it. Per pixel (at about 0.1 mm) the detector (:func:`bone_evidence`)
multiplies

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
(:func:`detect_bone_surface`) then picks, per column, either "no bone" or one depth, rewarding
probability above ``threshold``, penalising depth changes between neighbouring scan lines and
each start of a bone segment; segments narrower than ``min_segment_mm`` are dropped. Each depth
is finally moved to the peak of the unclipped ridge response nearby (sub-pixel, by a parabola):
the echo centre, which lies on the CT surface within 0.1 mm on the real fibula sweep (signed
median). :func:`detect_sweep_surface` runs it on every frame of a sweep. Settings:
:class:`~comreg_core.surfaces.us_config.BoneDetectorConfig`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from comreg_core.progress import Progress
from comreg_core.io.sweeps import TrackedSweep
from comreg_core.surfaces.us_config import BoneDetectorConfig
from comreg_core.surfaces.us_filters import bone_probability, gaussian_filter, shadow_and_tissue
from comreg_core.surfaces.us_percentiles import median, percentile
from comreg_core.surfaces.us_points import (USSurfacePoints, collect_surface_points,
                                            frames_to_use)


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
    """``(H // ky, W // kx)`` float32 block means. A B-mode (uint8) frame's blocks are summed
    exactly in integers, then divided as ``numpy.mean`` divides its float32 sum (exact too): the
    same bits as ``mean(axis=(1, 3))``, in a fifth of its time."""
    H, W = frame.shape
    h, w = H // ky, W // kx
    if ky == 1 and kx == 1:
        return np.asarray(frame[:h, :w], dtype=np.float32)
    if frame.dtype != np.uint8:
        a = np.asarray(frame[:h * ky, :w * kx], dtype=np.float32)
        return a.reshape(h, ky, w, kx).mean(axis=(1, 3))
    total = np.zeros((h, w), np.uint32)
    for i in range(ky):
        for j in range(kx):
            total += frame[i:h * ky:ky, j:w * kx:kx]
    mean = total.astype(np.float32)
    return np.true_divide(mean, np.intp(ky * kx), out=mean, casting="unsafe")


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

    intensity = gaussian_filter(a, (c.smoothing_mm / py, c.smoothing_mm / px))
    ref = max(float(percentile(intensity, 99)), 0.2 * float(intensity.max()))
    if not ref > 0:  # a blank frame
        return BoneEvidence(zeros, zeros, zeros, zeros, zeros, (ky, kx), (py, px))

    sigma = (c.ridge_scale_mm / py, c.ridge_scale_mm / px)
    iyy = gaussian_filter(a, sigma, (2, 0)) / py ** 2
    ixx = gaussian_filter(a, sigma, (0, 2)) / px ** 2
    ixy = gaussian_filter(a, sigma, (1, 1)) / (px * py)
    lam_min = 0.5 * (iyy + ixx) - np.sqrt((0.5 * (iyy - ixx)) ** 2 + ixy ** 2)
    strength = -lam_min * c.ridge_scale_mm ** 2 / (ref * c.ridge_saturation)
    ridge = np.clip(strength, 0.0, 1.0)

    # Field of view: scan-converted frames often have black margins (or a black sector
    # outside the fan); the reference statistics are taken over imaged columns only.
    fov = percentile(intensity, 95, axis=0) > 0.05 * ref
    if not fov.any():
        return BoneEvidence(zeros, zeros, zeros, zeros, zeros, (ky, kx), (py, px))
    floor = 0.05 * ref  # a water bath or an empty image is not "tissue"
    rows = np.arange(h)
    gap = max(1, int(round(c.shadow_gap_mm / py)))
    depth = max(1, int(round(c.shadow_depth_mm / py)))
    above_n = max(1, int(round(c.tissue_depth_mm / py)))
    profile = np.maximum(percentile(intensity, c.shadow_reference_percentile, axis=1,
                                    columns=fov), floor)
    pcum = np.concatenate([[0.0], np.cumsum(profile, dtype=np.float64)])
    expected, _ = _window_means(pcum, rows + gap, rows + gap + depth)
    first = min(int(c.min_depth_mm / py), h - 1)
    tissue_ref = max(float(median(intensity[first:max(first + 1, h // 2)][:, fov])), floor)
    shadow, tissue = shadow_and_tissue(
        intensity, np.maximum(expected, floor), gap, depth, above_n, tissue_ref,
        np.float32(0.25 * tissue_ref), float(c.tissue_min_fill), max(1, above_n // 2))

    norm = np.clip(intensity / ref, 0.0, 1.0)
    probability = bone_probability(norm, ridge, shadow, tissue, (
        c.intensity_power, c.ridge_power, c.shadow_power, c.tissue_power))
    probability[:first] = 0.0
    probability[:, ~fov] = 0.0
    if c.max_depth_mm is not None:
        probability[int(math.ceil(c.max_depth_mm / py)):] = 0.0
    return BoneEvidence(norm.astype(np.float32, copy=False), ridge.astype(np.float32, copy=False),
                        shadow.astype(np.float32), tissue.astype(np.float32), probability,
                        (ky, kx), (py, px), strength.astype(np.float32, copy=False))


def _viterbi(gain: np.ndarray, max_step: int, step_cost: float, switch_cost: float
             ) -> np.ndarray:
    """Best path through the columns of ``gain`` ``(h, w)`` (reward of "bone at row r in column
    c"; "no bone" earns 0). Moving between bone rows r -> r' in neighbouring columns costs
    ``step_cost * |r - r'|`` and is allowed for ``|r - r'| <= max_step``; entering or leaving
    bone costs ``switch_cost``. Returns ``(w,)`` rows, -1 where there is no bone. Compiled
    (numba): a fibula frame's path (405 x 475 working pixels) in ~1 ms."""
    gain = np.asarray(gain)
    if gain.dtype not in (np.float32, np.float64):
        gain = gain.astype(np.float64)
    return _viterbi_kernel(gain, int(max_step), float(step_cost), float(switch_cost))


@njit(cache=True)
def _viterbi_kernel(gain, max_step, step_cost, switch_cost):
    """:func:`_viterbi`: ``gain`` ``(h, w)`` float32 or float64. Ties go to the first
    candidate (the smallest previous row; numpy's ``argmax``). Each column's best predecessors are found one
    shift at a time over all rows (branch-free, so the compiler vectorises it), the candidates
    of a row still compared in order of their row: the same path as row by row."""
    h, w = gain.shape
    columns = np.empty((w, h))  # one scan line per row, float64
    for r in range(h):
        for c in range(w):
            columns[c, r] = gain[r, c]
    penalty = np.empty(max_step + 1)
    for k in range(max_step + 1):
        penalty[k] = step_cost * k
    back = np.empty((w, h), dtype=np.int32)  # previous bone row, or -1 = came from "no bone"
    off_from = np.full(w, -1, dtype=np.int32)  # row the "no bone" state left bone at, or -1
    v_bone = columns[0] - switch_cost
    new_bone = np.empty(h)
    best = np.empty(h)
    best_row = np.empty(h, dtype=np.int32)
    v_off = 0.0
    for col in range(1, w):
        enter = v_off - switch_cost
        for r in range(h):
            best[r] = -np.inf
            best_row[r] = min(max(r - max_step, 0), h - 1)
        for shift in range(-max_step, max_step + 1):
            cost = penalty[abs(shift)]
            lo, hi = max(0, -shift), min(h, h - shift)
            sources, bests, rows = v_bone[lo + shift:hi + shift], best[lo:hi], best_row[lo:hi]
            for i in range(hi - lo):  # non-negative indices: no wrap-around checks
                candidate = sources[i] - cost
                better = candidate > bests[i]
                bests[i] = candidate if better else bests[i]
                rows[i] = lo + shift + i if better else rows[i]
        here = columns[col]
        for r in range(h):
            from_bone = best[r] >= enter
            back[col, r] = best_row[r] if from_bone else -1
            new_bone[r] = (best[r] if from_bone else enter) + here[r]
        top = np.argmax(v_bone)
        leave = v_bone[top] - switch_cost
        if leave > v_off:
            v_off, off_from[col] = leave, top
        v_bone[:] = new_bone
    path = np.full(w, -1, dtype=np.int64)
    top = np.argmax(v_bone)
    in_bone = v_bone[top] - switch_cost > v_off
    row = top
    for col in range(w - 1, -1, -1):
        if in_bone:
            path[col] = row
            previous = back[col, row] if col > 0 else -1
            if previous < 0:
                in_bone = False
            else:
                row = previous
        elif col > 0 and off_from[col] >= 0:
            in_bone, row = True, off_from[col]
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


def warm_up_frame() -> np.ndarray:
    """A small synthetic B-mode frame ``(120, 80)`` uint8 at 0.1 mm (tissue speckle, a bright
    echo at 8 mm, its shadow below) on which :func:`detect_bone_surface` finds bone: running it
    compiles (or loads from numba's cache) every kernel of the detector."""
    rng = np.random.default_rng(0)
    frame = rng.integers(40, 90, size=(120, 80)).astype(np.uint8)
    frame[:5] = 0  # the gel
    frame[78:82] = 230  # the echo
    frame[82:] //= 8  # its shadow
    return frame


def detect_sweep_surface(sweep: TrackedSweep, config: BoneDetectorConfig | None = None, *,
                         frame_step: int = 1, progress: Progress | None = None
                         ) -> USSurfacePoints:
    """Run :func:`detect_bone_surface` on the valid frames of ``sweep`` (every
    ``frame_step``-th) and map the pixels to the reference frame."""
    config = config or BoneDetectorConfig()
    use = frames_to_use(sweep, frame_step)
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
    return collect_surface_points(sweep, points, frames, scores, len(use), "B-mode detector")
