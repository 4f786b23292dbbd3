"""A live sweep as it grows: frames in, bone points out, and how much of the bone they cover.

- :class:`Frame`: one B-mode image with its pose (image mm -> tracker reference mm).
- :class:`FrameAssembler`: pairs the IMAGE messages of a stream with their poses (the TRANSFORM
  of the same timestamp, PLUS Server's way), a probe pose through the probe calibration; what
  it cannot pair (an image without a pose, a pose that is no rigid map) becomes a one-line
  note, never an exception.
- :class:`SweepPoints`: the bone points of every frame used, found by the B-mode detector with
  the settings of ``comreg extract-us`` (:class:`~comreg_core.surfaces.us_config.
  USExtractionConfig`), and the cloud of all of them denoised together as ``extract-us`` does:
  after the last frame it is exactly ``extract-us``'s cloud of the frames used.
- :func:`covered_length_mm`: the length of bone the points cover along an axis.
- :func:`probe_calibration`, :func:`recorded_probe_poses`: the probe calibration of a file, and
  the probe's poses of a recording (what ``comreg replay`` sends as ``ProbeToReference``).

Coordinates: a frame's pixel (row r, column c) lies at ``T_ref_image @ (c sx, r sy, 0, 1)``
(:mod:`comreg_core.io.sweeps`); points are in the tracker's reference frame, mm.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.io._files import file_extension, require_input_file
from comreg_core.io.frame_folders import read_frame_folder_calibration
from comreg_core.io.plus_files import read_plus_calibration
from comreg_core.io.plus_sequences import read_plus_sequence
from comreg_core.io.sweeps import TrackedSweep, frames_to_grey
from comreg_core.surfaces.us_config import USExtractionConfig
from comreg_core.surfaces.us_denoise import denoise_points
from comreg_core.surfaces.us_detector import detect_bone_surface
from comreg_core.surfaces.us_points import NoBoneFoundError, USSurfacePoints, beam_origins

log = logging.getLogger(__name__)

#: Pixel columns further from a right angle than this (|cos|) make a pose malformed.
MAX_SHEAR_COS = 0.05
#: Neighbouring points along the axis closer than this (mm) belong to one covered stretch (a
#: sweep's frames can be 30 mm apart where the probe moved fast: 95th percentile of the shared
#: fibula recording's frames as served, every 10th of the original).
MERGE_GAP_MM = 40.0
#: A covered stretch needs at least this many points (a stray echo covers nothing).
MIN_STRETCH_POINTS = 20


@dataclass
class Frame:
    """One tracked B-mode frame of a live stream.

    Attributes:
        index: its place in the stream (0, 1, ...: every IMAGE received counts).
        image: ``(H, W)`` pixels, row 0 at the transducer face.
        spacing: ``(2,)`` mm per pixel ``(sx, sy)`` (columns, rows).
        T_ref_image: ``(4, 4)`` image mm -> reference mm.
        timestamp: the sender's time stamp (s).
        received_s: when it arrived (``time.monotonic()``).
    """

    index: int
    image: np.ndarray
    spacing: np.ndarray
    T_ref_image: np.ndarray
    timestamp: float
    received_s: float


def pixel_pose(T_ref_pixel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(spacing (2,), T_ref_image (4, 4))`` of a pixel -> reference map ``(4, 4)`` (columns 0
    and 1: the pixel steps in mm); raises ``ValueError`` when it is not finite or its pixel
    axes are zero or not at right angles."""
    T = np.asarray(T_ref_pixel, dtype=np.float64).reshape(4, 4)
    if not np.isfinite(T).all() or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError("not a finite affine 4x4 matrix")
    sx, sy = np.linalg.norm(T[:3, 0]), np.linalg.norm(T[:3, 1])
    if not (sx > 1e-9 and sy > 1e-9):
        raise ValueError("a pixel axis of length 0")
    if abs(T[:3, 0] @ T[:3, 1]) > MAX_SHEAR_COS * sx * sy:
        raise ValueError("pixel axes not at right angles")
    out = T @ np.diag([1.0 / sx, 1.0 / sy, 1.0, 1.0])
    normal = np.cross(out[:3, 0], out[:3, 1])
    out[:3, 2] = normal / np.linalg.norm(normal)
    return np.array([sx, sy]), out


@dataclass
class _Pending:
    image: np.ndarray
    ijk_to_world: np.ndarray
    timestamp: float
    received_s: float
    index: int


class FrameAssembler:
    """Pairs images and poses of a stream into :class:`Frame` objects.

    Args:
        pose_device: the TRANSFORM device giving each frame's pose (``ImageToReference``; a
            probe pose such as ``ProbeToReference`` with ``T_probe_pixel``).
        T_probe_pixel: ``(4, 4)`` the probe calibration (pixel -> probe mm), or None: the pose
            is then the image's and the IMAGE's own matrix maps its pixels to image mm.
        match_s: an image and a pose at most this far apart in time (s) belong together.
        wait_s: how long an image waits for its pose (wall clock, s).

    :meth:`add_image` / :meth:`add_pose` / :meth:`expire` return ``(frames, notes)``: the
    frames now complete, and one-line notes on what was skipped.
    """

    def __init__(self, pose_device: str, T_probe_pixel: np.ndarray | None = None, *,
                 match_s: float = 0.02, wait_s: float = 0.5):
        self.pose_device = pose_device
        self.T_probe_pixel = None if T_probe_pixel is None else np.asarray(T_probe_pixel, float)
        self.match_s, self.wait_s = match_s, wait_s
        self._poses: deque = deque(maxlen=256)  # (timestamp, (4, 4))
        self._pending: deque[_Pending] = deque()
        self.images = 0
        self.without_pose = 0
        self.bad_poses = 0

    def add_image(self, image: np.ndarray, ijk_to_world: np.ndarray, timestamp: float,
                  received_s: float) -> tuple[list[Frame], list[str]]:
        """An IMAGE: ``image`` ``(H, W)``, ``(1, H, W)`` or with colour channels last;
        ``ijk_to_world`` its ``(4, 4)`` matrix (pixel -> image mm, or the pose itself)."""
        pixels = np.asarray(image)
        while pixels.ndim > 2 and pixels.shape[0] == 1:
            pixels = pixels[0]
        if pixels.ndim == 3:
            pixels = frames_to_grey(pixels[None])[0]
        self.images += 1
        index = self.images - 1
        if pixels.ndim != 2 or min(pixels.shape) < 2:
            return [], [f"frame {index}: an image of shape {np.shape(image)} is no 2D B-mode "
                        "frame; skipped"]
        self._pending.append(_Pending(pixels, np.asarray(ijk_to_world, float), float(timestamp),
                                      received_s, index))
        return self._resolve(received_s)

    def add_pose(self, device: str, matrix: np.ndarray, timestamp: float, received_s: float
                 ) -> tuple[list[Frame], list[str]]:
        """A TRANSFORM ``device``; other devices than :attr:`pose_device` are ignored."""
        if device != self.pose_device:
            return [], []
        matrix = np.asarray(matrix, dtype=np.float64)
        if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
            self.bad_poses += 1
            return [], [f"a {device} pose that is not a finite 4x4 matrix; ignored"] \
                if _worth_telling(self.bad_poses) else []
        self._poses.append((float(timestamp), matrix))
        return self._resolve(received_s)

    def expire(self, now_s: float) -> tuple[list[Frame], list[str]]:
        """Give up on images that waited longer than ``wait_s`` for their pose."""
        return self._resolve(now_s)

    def _resolve(self, now_s: float) -> tuple[list[Frame], list[str]]:
        frames, notes = [], []
        while self._pending:
            item = self._pending[0]
            pose = self._pose_for(item.timestamp)
            newer = any(t > item.timestamp + self.match_s for t, _ in self._poses)
            if pose is None and not newer and now_s - item.received_s < self.wait_s:
                break  # its pose may still come
            self._pending.popleft()
            if pose is None:
                self.without_pose += 1
                if _worth_telling(self.without_pose):
                    notes.append(f"frame {item.index}: an image without a {self.pose_device} "
                                 f"pose within {1000 * self.match_s:g} ms; skipped "
                                 f"({self.without_pose} so far)")
                continue
            try:
                frames.append(self._frame(item, pose))
            except ValueError as exc:
                self.bad_poses += 1
                if _worth_telling(self.bad_poses):
                    notes.append(f"frame {item.index}: its {self.pose_device} pose is unusable "
                                 f"({exc}); skipped ({self.bad_poses} so far)")
        return frames, notes

    def _pose_for(self, timestamp: float) -> np.ndarray | None:
        best, gap = None, self.match_s
        for t, matrix in self._poses:
            if abs(t - timestamp) <= gap:
                best, gap = matrix, abs(t - timestamp)
        return best

    def _frame(self, item: _Pending, pose: np.ndarray) -> Frame:
        if self.T_probe_pixel is not None:  # pose = probe; the calibration maps pixels
            T_ref_pixel = pose @ self.T_probe_pixel
        else:
            T_ref_pixel = pose @ item.ijk_to_world
        spacing, T_ref_image = pixel_pose(T_ref_pixel)
        return Frame(item.index, item.image, spacing, T_ref_image, item.timestamp,
                     item.received_s)


def _worth_telling(count: int) -> bool:
    """Whether the ``count``-th repeat of a problem gets its line: the first three, then every
    hundredth (a stream without poses must not bury the status lines)."""
    return count <= 3 or count % 100 == 0


@dataclass
class _FrameRecord:
    index: int
    timestamp: float
    received_s: float
    T_ref_image: np.ndarray
    raw_points: int


@dataclass
class SweepPoints:
    """Bone points of the frames used so far (module docstring).

    Attributes:
        config: the extraction settings (``comreg extract-us``'s; its detector and denoising).
        records: one per frame used: stream index, time stamp, arrival, pose, raw points.
    """

    config: USExtractionConfig = field(default_factory=USExtractionConfig)
    records: list[_FrameRecord] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._points: list[np.ndarray] = []
        self._frames: list[np.ndarray] = []
        self._scores: list[np.ndarray] = []
        self._poses: dict[int, np.ndarray] = {}
        self._cloud: USSurfacePoints | None = None
        self._dirty = False

    def add(self, frame: Frame) -> int:
        """Detect the bone in ``frame`` and keep its points; returns how many it gave."""
        found = detect_bone_surface(frame.image, frame.spacing, self.config.detector)
        one = TrackedSweep(frame.image[None], frame.spacing, frame.T_ref_image[None],
                           [frame.timestamp], [True])
        n = len(found.rows)
        if n:
            self._points.append(one.pixel_to_reference(np.zeros(n, int), found.rows,
                                                       found.cols))
            self._frames.append(np.full(n, frame.index, dtype=np.int64))
            self._scores.append(found.score)
            self._dirty = True
        self._poses[frame.index] = frame.T_ref_image
        self.records.append(_FrameRecord(frame.index, frame.timestamp, frame.received_s,
                                         frame.T_ref_image, n))
        return n

    @property
    def frames_used(self) -> int:
        return len(self.records)

    @property
    def frames_with_bone(self) -> int:
        return len(self._points)

    def cloud(self) -> USSurfacePoints | None:
        """All points so far in frame order, denoised together (as ``extract-us``), or None
        when there are none or the clean-up keeps none. Cached until a frame adds points."""
        if self._dirty:  # in frame order, whatever order the frames were detected in
            frames = np.concatenate(self._frames)
            order = np.argsort(frames, kind="stable")
            raw = USSurfacePoints(np.concatenate(self._points)[order], frames[order],
                                  np.concatenate(self._scores)[order], self.frames_used,
                                  self.frames_with_bone)
            try:
                self._cloud = denoise_points(raw, self.config.denoise)
            except NoBoneFoundError:
                self._cloud = None
            self._dirty = False
        return self._cloud

    def beam_origins(self, cloud: USSurfacePoints) -> np.ndarray | None:
        """``(N, 3)`` the beam origin of each point of ``cloud`` (None after a down-sampling
        that merged points)."""
        if (cloud.frame_index < 0).any():
            return None
        poses = np.stack([self._poses[int(i)] for i in cloud.frame_index])
        return beam_origins(cloud.points, poses)


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


def coalesce(frames: list[Frame], limit: int) -> list[Frame]:
    """At most ``limit`` of ``frames`` (in order), evenly spread and always with the newest:
    what one update detects when the stream is faster than the updates."""
    if len(frames) <= limit:
        return list(frames)
    if limit < 1:
        raise ComRegError("At least one frame per update must be used.", "")
    picks = np.unique(np.round(np.linspace(len(frames) - 1, 0, limit)).astype(int))
    return [frames[i] for i in sorted(picks)]


def probe_calibration(path) -> np.ndarray:
    """The probe calibration ``T_probe_pixel`` ``(4, 4)`` (pixel index -> probe mm) in a file
    ``comreg extract-us --probe-calibration`` takes: a PLUS device-set XML (its ``ImageToProbe``) or
    a frame folder's ``calibration.json`` (``image_to_probe``, ``pixel_spacing_mm``; pixel
    centres at ``c + 0.5``, as :func:`~comreg_core.io.frame_folders.read_frame_folder_tracking`
    reads it)."""
    path = require_input_file(path, "probe calibration")
    if file_extension(path) != ".json":
        return read_plus_calibration(path)
    cal = read_frame_folder_calibration(path)
    sx, sy = cal.spacing
    half = np.eye(4)
    half[:2, 3] = 0.5 * sx, 0.5 * sy
    return cal.T_probe_image @ half @ np.diag([sx, sy, 1.0, 1.0])


def probe_poses(T_ref_pixel: np.ndarray, T_probe_pixel: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` the probe's poses ``T_ref_probe`` (probe mm -> reference mm) of frames whose
    pixel -> reference maps are ``T_ref_pixel`` ``(N, 4, 4)`` (a unit normal as third column,
    as :attr:`~comreg_core.io.sweeps.TrackedSweep.T_ref_pixel` has it), given the probe
    calibration ``T_probe_pixel`` ``(4, 4)`` (pixel -> probe mm): ``T_ref_probe @
    T_probe_pixel`` maps each pixel as ``T_ref_pixel`` does (PLUS's ImageToReference =
    ProbeToReference @ ImageToProbe). NaN where ``T_ref_pixel`` is. Raises :class:`ComRegError`
    when the calibration cannot be inverted."""
    C = np.asarray(T_probe_pixel, dtype=np.float64).reshape(4, 4)
    if not (np.isfinite(C).all() and abs(np.linalg.det(C)) > 1e-12):
        raise ComRegError("The probe calibration (ImageToProbe) cannot be inverted, so the "
                          "probe's poses cannot be derived from it.",
                          "Pass the calibration made for this recording.")
    normal = np.diag([1.0, 1.0, np.linalg.norm(C[:3, 2]), 1.0])  # ours is a unit normal
    return np.asarray(T_ref_pixel, dtype=np.float64) @ normal @ np.linalg.inv(C)


def recorded_probe_poses(sweep: TrackedSweep, calibration=None
                         ) -> tuple[np.ndarray | None, str]:
    """The probe's poses of a recorded ``sweep`` (read from ``sweep.path``) and where they came
    from: ``((N, 4, 4) T_ref_probe, NaN where unknown, text)``, or ``(None, why not)``.

    From the probe calibration when there is one (``calibration``, as ``comreg extract-us``
    takes it, or a frame folder's own ``calibration.json``: :func:`probe_poses`); else from a
    PLUS sequence's own per-frame transforms (its ProbeToReference chain); else None (a 3D
    Slicer volume sequence, or a PLUS sequence giving only the image's poses)."""
    path = sweep.path
    if calibration is None and path is not None and path.is_dir():
        calibration = path / "calibration.json"
    if calibration is not None:
        T = probe_poses(sweep.T_ref_pixel, probe_calibration(calibration))
        return T, f"derived from the probe calibration '{calibration}'"
    if path is not None and path.is_file():
        try:
            probe = read_plus_sequence(path, reference=sweep.reference, image="Probe")
        except ComRegError:
            probe = None
        if probe is not None and probe.n_frames == sweep.n_frames:
            T = np.where(probe.valid[:, None, None], probe.T_ref_image, np.nan)
            return T, f"the recording's ProbeTo{probe.reference} transforms"
    return None, ("the recording gives no probe pose and there is no probe calibration to "
                  "derive it from (--probe-calibration)")
