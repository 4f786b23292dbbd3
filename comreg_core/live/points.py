"""A live sweep's bone points as it grows, and how much of the bone they cover.

- :func:`detect_frame`: the bone points of one frame (:class:`Detection`), found by the B-mode
  detector with the settings of ``comreg extract-us``; a pure function of the frame, so a
  detection worker's answer is the update loop's own (:mod:`comreg_core.live.detection`).
- :class:`SweepPoints`: the points of every frame used, and the cloud of all of them cleaned
  up together as ``extract-us`` does, kept up to date frame by frame
  (:class:`~comreg_core.surfaces.us_denoise_incremental.IncrementalDenoise`): after any frames,
  in any order, it is exactly ``extract-us``'s cloud of those frames.
- :func:`covered_length_mm`: the length of bone the points cover along an axis.

Coordinates: points are in the tracker's reference frame, mm (:mod:`comreg_core.live.stream`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from comreg_core.io.sweeps import TrackedSweep
from comreg_core.surfaces.us_config import USExtractionConfig
from comreg_core.surfaces.us_denoise_incremental import IncrementalDenoise
from comreg_core.surfaces.us_detector import detect_bone_surface
from comreg_core.surfaces.us_points import NoBoneFoundError, USSurfacePoints, beam_origins

#: Neighbouring points along the axis closer than this (mm) belong to one covered stretch (a
#: sweep's frames can be 30 mm apart where the probe moved fast: 95th percentile of the shared
#: fibula recording's frames as served, every 10th of the original).
MERGE_GAP_MM = 40.0
#: A covered stretch needs at least this many points (a stray echo covers nothing).
MIN_STRETCH_POINTS = 20


@dataclass
class Detection:
    """The bone points of one frame (no image).

    Attributes:
        index, timestamp, received_s, T_ref_image: the frame's
            (:class:`~comreg_core.live.stream.Frame`).
        points: ``(n, 3)`` reference mm; scores: ``(n,)`` the detector's.
        detect_s: how long the detection took (s).
    """

    index: int
    timestamp: float
    received_s: float
    T_ref_image: np.ndarray
    points: np.ndarray
    scores: np.ndarray
    detect_s: float = 0.0


def detect_frame(frame, config: USExtractionConfig | None = None) -> Detection:
    """The bone points of ``frame`` (a :class:`~comreg_core.live.stream.Frame`), as ``comreg
    extract-us`` finds them in a frame of a recording (``config``: its settings)."""
    config = config or USExtractionConfig()
    start = time.perf_counter()
    found = detect_bone_surface(frame.image, frame.spacing, config.detector)
    n = len(found.rows)
    points = np.zeros((0, 3))
    if n:
        one = TrackedSweep(frame.image[None], frame.spacing, frame.T_ref_image[None],
                           [frame.timestamp], [True])
        points = one.pixel_to_reference(np.zeros(n, int), found.rows, found.cols)
    return Detection(frame.index, frame.timestamp, frame.received_s,
                     np.asarray(frame.T_ref_image, np.float64), points,
                     np.asarray(found.score, np.float64).reshape(-1),
                     time.perf_counter() - start)


@dataclass
class FrameRecord:
    """A frame used: stream ``index``, ``timestamp``, arrival ``received_s``, pose
    ``T_ref_image``, ``raw_points`` found, and ``used_s``: when an update took it (NaN: at the
    stop)."""

    index: int
    timestamp: float
    received_s: float
    T_ref_image: np.ndarray
    raw_points: int
    used_s: float = math.nan


class SweepPoints:
    """Bone points of the frames used so far (module docstring).

    Args:
        config: the extraction settings (``comreg extract-us``'s; its detector and clean-up).

    Attributes:
        records: one :class:`FrameRecord` per frame used, in the order they were added.
    """

    def __init__(self, config: USExtractionConfig | None = None):
        self.config = config or USExtractionConfig()
        self.records: list[FrameRecord] = []
        self._denoise = IncrementalDenoise(self.config.denoise)
        self._with_bone = 0
        self._poses: dict[int, np.ndarray] = {}
        self._pose_table: tuple[np.ndarray, np.ndarray] | None = None
        self._cloud: USSurfacePoints | None = None
        self._dirty = False

    def add(self, frame, used_s: float = math.nan) -> int:
        """Detect the bone in ``frame`` and keep its points; returns how many it gave."""
        return self.add_detection(detect_frame(frame, self.config), used_s)

    def add_detection(self, found: Detection, used_s: float = math.nan) -> int:
        """Keep the points of a frame's :class:`Detection` (taken by an update at ``used_s``,
        ``time.monotonic()``); returns how many there are."""
        n = len(found.points)
        if n:
            self._denoise.add(found.points, np.full(n, found.index, np.int64), found.scores)
            self._with_bone += 1
            self._dirty = True
        self._poses[found.index] = found.T_ref_image
        self._pose_table = None
        self.records.append(FrameRecord(found.index, found.timestamp, found.received_s,
                                        found.T_ref_image, n, used_s))
        return n

    @property
    def frames_used(self) -> int:
        return len(self.records)

    @property
    def frames_with_bone(self) -> int:
        return self._with_bone

    def cloud(self) -> USSurfacePoints | None:
        """All points so far in frame order, cleaned up together (as ``extract-us``), or None
        when there are none or the clean-up keeps none. Cached until a frame adds points."""
        if self._dirty:
            try:
                self._cloud = self._denoise.cloud(self.frames_used, self.frames_with_bone)
            except NoBoneFoundError:
                self._cloud = None
            self._dirty = False
        return self._cloud

    def beam_origins(self, cloud: USSurfacePoints) -> np.ndarray | None:
        """``(N, 3)`` the beam origin of each point of ``cloud`` (None after a down-sampling
        that merged points)."""
        if (cloud.frame_index < 0).any():
            return None
        if self._pose_table is None:
            keys = np.array(sorted(self._poses), dtype=np.int64)
            self._pose_table = keys, np.stack([self._poses[int(k)] for k in keys])
        keys, poses = self._pose_table
        return beam_origins(cloud.points, poses[np.searchsorted(keys, cloud.frame_index)])


def covered_length_mm(along: np.ndarray, merge_gap_mm: float = MERGE_GAP_MM,
                      min_points: int = MIN_STRETCH_POINTS) -> float:
    """The length (mm) of the union of the stretches that positions ``along`` ``(N,)`` (mm on
    one axis) cover: sorted positions closer than ``merge_gap_mm`` form one stretch; stretches
    of fewer than ``min_points`` points count 0."""
    s = np.sort(np.asarray(along, dtype=np.float64))
    if len(s) == 0:
        return 0.0
    breaks = np.flatnonzero(np.diff(s) > merge_gap_mm)
    starts = np.concatenate([[0], breaks + 1])
    stops = np.concatenate([breaks, [len(s) - 1]])
    keep = (stops - starts + 1) >= min_points
    return float(np.sum(s[stops[keep]] - s[starts[keep]]))
