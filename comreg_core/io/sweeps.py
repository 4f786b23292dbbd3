"""The tracked freehand ultrasound sweep every reader returns (:class:`TrackedSweep`), with the
errors and small helpers those readers share.

Conventions. ``frames[n]`` is ``(H, W)`` with row 0 at the transducer face and columns along the
array (PLUS's "MF" orientation; other orientations are flipped to it on read, as PLUS does). The
*image* frame is in mm: the centre of pixel (row r, column c) is at ``(c * sx, r * sy, 0)``, so
``T_ref_pixel = T_ref_image @ diag(sx, sy, 1, 1)`` maps pixel indices, the quantity PLUS's
ImageToProbe calibration maps. PLUS composes, and so do we::

    ImageToReference = inv(ReferenceToTracker) @ ProbeToTracker @ ImageToProbe

Frames whose transforms on that chain are INVALID (or missing, or whose image is INVALID) keep
their pixels but are flagged ``valid = False``; everything downstream uses valid frames only, as
PLUS's volume reconstruction does. A calibration may carry scale and a little shear, so
``T_ref_image`` is affine (rigid for the frame-folder format).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from comreg_core.transforms import matmul
from comreg_core.errors import ComRegError

#: Sequence files :func:`comreg_core.io.tracked_us.read_tracked_sweep` reads (a directory is a
#: frame folder).
SWEEP_EXTENSIONS = [".igs.mha", ".seq.mha", ".igs.nrrd", ".seq.nrrd", ".mha", ".mhd", ".nrrd",
                    ".nhdr"]


class CalibrationMismatchError(ComRegError):
    """The calibration was made for another image size, or maps outside the frames."""


class NoValidFramesError(ComRegError):
    """A sweep has no frame with both an image and a valid pose."""


@dataclass
class TrackedSweep:
    """A tracked freehand 2D ultrasound sweep.

    Attributes:
        frames: ``(N, H, W)`` pixel values (uint8 for B-mode), row 0 at the transducer face.
        spacing: ``(2,)`` pixel size in mm: ``(sx, sy)`` along columns (array) and rows (depth).
        T_ref_image: ``(N, 4, 4)`` image mm -> reference mm per frame (NaN where no pose).
        timestamps: ``(N,)`` seconds (NaN where unknown).
        valid: ``(N,)`` bool, True where the frame has an image and a valid pose.
        reference: name of the reference coordinate frame ("Reference", "Tracker", "CT", ...).
        frame_names: ``N`` labels (file stems or "Frame0007"), for messages and mask matching.
        path: the file or folder it was read from, if any.
    """

    frames: np.ndarray
    spacing: np.ndarray
    T_ref_image: np.ndarray
    timestamps: np.ndarray
    valid: np.ndarray
    reference: str = "Reference"
    frame_names: list[str] = field(default_factory=list)
    path: Path | None = None

    def __post_init__(self) -> None:
        self.frames = np.asarray(self.frames)
        if self.frames.ndim != 3:
            raise ValueError(f"frames must be (N, H, W), got shape {self.frames.shape}")
        n = len(self.frames)
        self.spacing = np.asarray(self.spacing, dtype=np.float64).reshape(2)
        self.T_ref_image = np.asarray(self.T_ref_image, dtype=np.float64).reshape(n, 4, 4)
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(n)
        self.valid = np.asarray(self.valid, dtype=bool).reshape(n)
        if not self.frame_names:
            self.frame_names = [f"Frame{i:04d}" for i in range(n)]
        if len(self.frame_names) != n:
            raise ValueError(f"{len(self.frame_names)} frame names for {n} frames")
        self.valid &= np.isfinite(self.T_ref_image).all(axis=(1, 2))

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def image_shape(self) -> tuple[int, int]:
        """``(H, W)`` of one frame in pixels."""
        return int(self.frames.shape[1]), int(self.frames.shape[2])

    @property
    def T_ref_pixel(self) -> np.ndarray:
        """``(N, 4, 4)`` pixel index ``(col, row, 0, 1)`` -> reference mm (its third column is
        the unit plane normal)."""
        return matmul(self.T_ref_image, np.diag([self.spacing[0], self.spacing[1], 1.0, 1.0]))

    def pixel_to_reference(self, frame_index, rows, cols) -> np.ndarray:
        """Reference mm ``(M, 3)`` of pixel positions ``rows``/``cols`` ``(M,)`` (float allowed,
        pixel centres at integers) in frames ``frame_index`` ``(M,)``."""
        frame_index = np.asarray(frame_index, dtype=np.int64).reshape(-1)
        local = np.column_stack([np.asarray(cols, dtype=np.float64).reshape(-1) * self.spacing[0],
                                 np.asarray(rows, dtype=np.float64).reshape(-1) * self.spacing[1]])
        out = np.empty((len(frame_index), 3))
        order = np.argsort(frame_index, kind="stable")
        frames, starts = np.unique(frame_index[order], return_index=True)
        for f, idx in zip(frames, np.split(order, starts[1:])):
            T = self.T_ref_image[f]
            out[idx] = (local[idx, 0:1] * T[:3, 0] + local[idx, 1:2] * T[:3, 1]) + T[:3, 3]
        return out

    def frame_corners(self, clip_origin=(0, 0), clip_size=None) -> np.ndarray:
        """``(N, 4, 3)`` reference mm of the four corner pixel centres of each frame, or of the
        clip rectangle (origin ``(col, row)``, size ``(cols, rows)`` px, PLUS's convention:
        corners at ``origin`` and ``min(origin + size, last index)``)."""
        H, W = self.image_shape
        c0, r0 = (max(0, int(v)) for v in clip_origin)
        c1, r1 = W - 1, H - 1
        if clip_size is not None and min(clip_size) > 0:
            c1, r1 = min(c1, c0 + int(clip_size[0])), min(r1, r0 + int(clip_size[1]))
        cols = np.array([c0, c0, c1, c1], dtype=np.float64)
        rows = np.array([r0, r1, r0, r1], dtype=np.float64)
        n = self.n_frames
        pts = self.pixel_to_reference(np.repeat(np.arange(n), 4), np.tile(rows, n),
                                      np.tile(cols, n))
        return pts.reshape(n, 4, 3)

    def select(self, indices) -> "TrackedSweep":
        """The sweep restricted to frames ``indices`` (an index array or boolean mask)."""
        idx = np.arange(self.n_frames)[np.asarray(indices)]
        return replace(self, frames=self.frames[idx], T_ref_image=self.T_ref_image[idx],
                       timestamps=self.timestamps[idx], valid=self.valid[idx],
                       frame_names=[self.frame_names[i] for i in idx])

    def only_valid(self) -> "TrackedSweep":
        """The valid frames only; raises :class:`NoValidFramesError` if there are none."""
        if not self.valid.any():
            where = f" in '{self.path}'" if self.path else ""
            raise NoValidFramesError(
                f"None of the {self.n_frames} frames{where} has a valid tracking pose.",
                "Check that the probe and reference were visible to the tracker, and that the "
                "calibration file belongs to this recording.")
        return self.select(self.valid)


def frames_to_grey(frames: np.ndarray) -> np.ndarray:
    """``(N, H, W)`` from ``(N, H, W[, C])``: one channel as is, RGB(A) as luminance."""
    if frames.ndim == 3:
        return frames
    if frames.shape[-1] == 1:
        return frames[..., 0]
    rgb = frames[..., :3].astype(np.float32)
    if np.array_equal(frames[..., 0], frames[..., 1]) and np.array_equal(frames[..., 0],
                                                                         frames[..., 2]):
        return frames[..., 0]
    grey = rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    return grey.round().astype(frames.dtype) if frames.dtype.kind in "ui" else grey


def parse_float(text) -> float:
    """``float(text)``, or NaN when ``text`` is None or not a number."""
    try:
        return float(text)
    except (TypeError, ValueError):
        return float("nan")
