"""Bone surface points of a tracked ultrasound sweep (:class:`USSurfacePoints`, mm, in the sweep's
reference frame): the result the B-mode detector and the label masks both produce, and what they
share to produce it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.io.sweeps import TrackedSweep

log = logging.getLogger(__name__)



class NoBoneFoundError(ComRegError):
    """No frame of the sweep shows a bone surface (or every mask is empty)."""


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
        """The points selected by ``keep`` (boolean mask or indices), frames recounted."""
        keep = np.asarray(keep)
        return USSurfacePoints(self.points[keep], self.frame_index[keep], self.score[keep],
                               self.frames_examined,
                               len(np.unique(self.frame_index[keep][self.frame_index[keep] >= 0])),
                               self.reference)


def frames_to_use(sweep: TrackedSweep, frame_step: int) -> np.ndarray:
    """Indices of the valid frames of ``sweep``, every ``frame_step``-th; raises
    :class:`~comreg_core.io.sweeps.NoValidFramesError` when there are none."""
    valid = np.flatnonzero(sweep.valid)
    if len(valid) == 0:
        sweep.only_valid()  # raises NoValidFramesError with the message
    return valid[::frame_step]


def collect_surface_points(sweep: TrackedSweep, points: list, frames: list, scores: list,
                           examined: int, source: str) -> USSurfacePoints:
    """One :class:`USSurfacePoints` from per-frame lists (``(K, 3)`` mm points, ``(K,)`` frame
    indices, ``(K,)`` scores) of the frames with bone, out of ``examined`` frames; raises
    :class:`NoBoneFoundError` when no frame gave points, warns when fewer than half did.
    ``source`` names the method in messages."""
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


def beam_origins(points: np.ndarray, T_ref_image: np.ndarray) -> np.ndarray:
    """``(M, 3)`` where the ultrasound beam of each echo started: the point moved back along its
    image's beam axis (image y, into the tissue) to the transducer face (image y = 0). ``points``
    ``(M, 3)`` mm and ``T_ref_image`` ``(M, 4, 4)`` (each point's frame pose, image mm -> the
    points' frame) in the same frame. A tracked sweep knows this for every point; the pose
    search uses it to rule out poses the probe could not have seen."""
    beam = T_ref_image[:, :3, 1]
    beam = beam / np.linalg.norm(beam, axis=1, keepdims=True)
    depth = np.einsum("mi,mi->m", points - T_ref_image[:, :3, 3], beam)
    return points - depth[:, None] * beam
