"""A live stream's frames: images paired with their poses, and the probe calibration.

- :class:`Frame`: one B-mode image with its pose (image mm -> tracker reference mm).
- :class:`FrameAssembler`: pairs the IMAGE messages of a stream with their poses (the TRANSFORM
  of the same timestamp, PLUS Server's way), a probe pose through the probe calibration; what
  it cannot pair (an image without a pose, a pose that is no rigid map) becomes a one-line
  note, never an exception.
- :func:`probe_calibration`, :func:`recorded_probe_poses`: the probe calibration of a file, and
  the probe's poses of a recording (what ``comreg replay`` sends as ``ProbeToReference``).

Coordinates: a frame's pixel (row r, column c) lies at ``T_ref_image @ (c sx, r sy, 0, 1)``
(:mod:`comreg_core.io.sweeps`). Their bone points: :mod:`comreg_core.live.points`.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.io._files import file_extension, require_input_file
from comreg_core.io.frame_folders import read_frame_folder_calibration
from comreg_core.io.plus_files import read_plus_calibration
from comreg_core.io.plus_sequences import read_plus_sequence
from comreg_core.io.sweeps import TrackedSweep, frames_to_grey

log = logging.getLogger(__name__)

#: Pixel columns further from a right angle than this (|cos|) make a pose malformed.
MAX_SHEAR_COS = 0.05


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
        self.not_frames = 0  # IMAGEs that are no 2D frame

    def add_image(self, image: np.ndarray, ijk_to_world: np.ndarray, timestamp: float,
                  received_s: float) -> tuple[list[Frame], list[str]]:
        """An IMAGE: ``image`` ``(H, W)``, or as pyigtl unpacks one, ``(K, H, W)`` (one
        component) or ``(K, H, W, C)`` (colour, C <= 4) with one slice (``K = 1``); a volume of
        several slices is no frame. ``ijk_to_world`` its ``(4, 4)`` matrix (pixel -> image mm,
        or the pose itself)."""
        pixels = np.asarray(image)
        if pixels.ndim in (3, 4) and pixels.shape[0] == 1:
            pixels = pixels[0]
        if pixels.ndim == 3 and pixels.shape[-1] <= 4:  # one slice's colour channels
            pixels = frames_to_grey(pixels[None])[0]
        self.images += 1
        index = self.images - 1
        if pixels.ndim != 2 or min(pixels.shape) < 2:
            self.not_frames += 1
            return [], [f"frame {index}: an image of shape {np.shape(image)} is no 2D B-mode "
                        f"frame; skipped ({self.not_frames} so far)"] \
                if _worth_telling(self.not_frames) else []
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
