"""Which frames of a live stream are used (:class:`FrameGate`): the bone is detected only in
frames that can show new bone, and no frame waits longer than a stated age.

- **No new bone** (:class:`FrameSpacing`): a frame whose image moved less than
  ``distance_mm`` (at every corner of the image) *and* turned less than ``angle_deg`` from the
  last frame sent to detection covers the same bone again; it is skipped before detection and
  counted as ``skipped`` (not a loss), as volume reconstruction does with frames closer than
  its voxel. The comparison runs in stream order, in a fixed order of operations (the same
  decision on every CPU).
- **Lag**: a frame that waited too long for a detection worker is dropped (``lag``): when its
  age plus what detection and an update still take (the mean of the last ones, counted up to
  half the limit) passes ``max_age_s``. So, while updates take less than half the limit, no
  frame is older than ``max_age_s`` when an update registers it; when they take longer, the
  frames detected are still registered (older: ``frame_age_s`` says by how much) rather than
  all dropped, and the status line says LATE.

Every frame's fate (``used``, ``skipped``, ``lag``) is kept (:attr:`FrameGate.fates`) with its
pose, for ``frames.csv``; :attr:`FrameGate.counts` counts them by cause. Thread-safe: the
pipeline's thread admits frames while the update loop takes them.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.registration.geometry.metrics import rotation_angles_deg
from comreg_core.transforms import rotate

#: The default spacing of the frames used (mm at the image's corners, deg): module docstring
#: and docs/live.md (why these).
SPACING_MM = 0.5
SPACING_DEG = 0.5
#: The default age limit of a frame when it is used (s).
MAX_AGE_S = 0.5
#: Fates of a frame (and a frame sent to detection).
USED, SKIPPED, LAG, DETECT = "used", "skipped", "lag", "detect"


@dataclass(frozen=True)
class FrameSpacing:
    """The least motion that can show new bone: ``distance_mm`` at any corner of the image, or
    ``angle_deg`` of turn."""

    distance_mm: float = SPACING_MM
    angle_deg: float = SPACING_DEG

    def __post_init__(self) -> None:
        if not (np.isfinite(self.distance_mm) and np.isfinite(self.angle_deg)
                and self.distance_mm >= 0 and self.angle_deg >= 0):
            raise ComRegError(f"A frame spacing of {self.distance_mm:g} mm, "
                              f"{self.angle_deg:g} deg is not two non-negative numbers.",
                              "Give e.g. --frame-spacing 0.5,0.5 (0,0 uses every frame).")

    def moved(self, T_a: np.ndarray, T_b: np.ndarray, corners: np.ndarray
              ) -> tuple[float, float]:
        """``(mm, deg)``: how far the image ``corners`` ``(4, 3)`` (image mm) moved at most, and
        the angle turned, from pose ``T_a`` to ``T_b`` (``(4, 4)`` image -> reference)."""
        a = rotate(corners, T_a[:3, :3]) + T_a[:3, 3]
        b = rotate(corners, T_b[:3, :3]) + T_b[:3, 3]
        d = b - a
        mm = float(np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]).max())
        return mm, float(rotation_angles_deg(T_b[None], T_a)[0])

    def new_bone(self, T_last: np.ndarray, T_new: np.ndarray, corners: np.ndarray) -> bool:
        """Whether a frame at ``T_new`` can show bone the one at ``T_last`` did not."""
        mm, deg = self.moved(T_last, T_new, corners)
        return mm >= self.distance_mm or deg >= self.angle_deg


def image_corners(frame) -> np.ndarray:
    """``(4, 3)`` the corner pixel centres of ``frame``'s image in image mm."""
    H, W = frame.image.shape[:2]
    sx, sy = frame.spacing
    return np.array([[0.0, 0.0, 0.0], [(W - 1) * sx, 0.0, 0.0], [0.0, (H - 1) * sy, 0.0],
                     [(W - 1) * sx, (H - 1) * sy, 0.0]])


@dataclass
class FrameFate:
    """What became of a frame: ``fate`` (used, skipped, lag), decided at ``at_s``
    (``time.monotonic()``), with the frame's ``index``, ``timestamp``, arrival ``received_s``
    and pose ``T_ref_image``."""

    index: int
    timestamp: float
    received_s: float
    T_ref_image: np.ndarray
    fate: str
    at_s: float


class FrameGate:
    """Decides which frames are detected and used (module docstring).

    Args:
        spacing: the :class:`FrameSpacing` of the frames used; None: every frame.
        max_age_s: the age limit (s) of a frame when used (kept by dropping frames that
            waited too long for detection); None: no limit (frames wait).
    """

    def __init__(self, spacing: FrameSpacing | None = FrameSpacing(),
                 max_age_s: float | None = None):
        if max_age_s is not None and not max_age_s > 0:
            raise ComRegError(f"A frame age limit of {max_age_s:g} s is not a positive number.",
                              "Give e.g. --max-frame-age 0.5 (inf: frames wait, none is "
                              "dropped).")
        self.spacing = spacing
        self.max_age_s = max_age_s
        self.fates: list[FrameFate] = []
        self.counts = {SKIPPED: 0, LAG: 0}
        self._lock = threading.Lock()
        self._last: np.ndarray | None = None  # the pose of the last frame sent to detection
        self._detect_s: deque[float] = deque(maxlen=8)
        self._update_s: deque[float] = deque(maxlen=8)
        self.update_every_s = 0.0  # the least time between two updates (s)

    def admit(self, frame, now_s: float) -> bool:
        """Whether ``frame`` (next in stream order) goes to detection now; if not, it is
        recorded as skipped (no new bone) or dropped for lag."""
        return self.decide(frame, now_s, True) == DETECT

    def decide(self, frame, now_s: float, can_detect: bool) -> str | None:
        """The fate of ``frame`` (next in stream order): :data:`SKIPPED` or :data:`LAG`
        (recorded), :data:`DETECT` (when ``can_detect``: it is the new reference), or None: it
        shows new bone and is not too old, but must wait for a free worker (the frames after
        it wait for its fate: it may become the reference)."""
        with self._lock:
            if self.spacing is not None and self._last is not None and \
                    not self.spacing.new_bone(self._last, frame.T_ref_image,
                                              image_corners(frame)):
                self._record(frame, SKIPPED, now_s)
                return SKIPPED
            if self.max_age_s is not None and \
                    now_s - frame.received_s + self._reserve() > self.max_age_s:
                self._record(frame, LAG, now_s)
                return LAG
            if not can_detect:
                return None
            self._last = np.asarray(frame.T_ref_image, np.float64)
            return DETECT

    def used(self, found, now_s: float) -> None:
        """Record that an update (or the stop, ``now_s`` NaN) took the detected frame."""
        with self._lock:
            self.fates.append(FrameFate(found.index, found.timestamp, found.received_s,
                                        found.T_ref_image, USED, now_s))

    def timed(self, detect_s: float | None = None, update_s: float | None = None) -> None:
        """Note how long a detection and an update took (s): what a frame still has to wait."""
        with self._lock:
            if detect_s is not None:
                self._detect_s.append(float(detect_s))
            if update_s is not None:
                self._update_s.append(float(update_s))

    def _reserve(self) -> float:
        """The time a frame sent to detection now still waits before an update takes it (s):
        the mean detection of late, and the mean update of late or the time between updates
        (:attr:`update_every_s`) if longer; at most half the age limit."""
        mean = (lambda d: sum(d) / len(d) if d else 0.0)
        wait = mean(self._detect_s) + max(mean(self._update_s), self.update_every_s)
        return min(wait, 0.5 * self.max_age_s)

    def _record(self, frame, fate: str, now_s: float) -> None:
        self.counts[fate] += 1
        self.fates.append(FrameFate(frame.index, frame.timestamp, frame.received_s,
                                    np.asarray(frame.T_ref_image, np.float64), fate, now_s))


class Backlog:
    """Frames waiting for an update that detects them itself (the 3D Slicer module's: frames
    given to :meth:`~comreg_core.live.session.LiveSession.update`): :meth:`take` gives at most
    ``limit`` of them (evenly spread, the newest among them, :func:`coalesce`), the rest wait;
    beyond ``max_frames`` the oldest are dropped (:attr:`dropped`), with a note."""

    def __init__(self, max_frames: int = 300):
        self.max_frames = int(max_frames)
        self.frames: list = []
        self.dropped = 0

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, frames) -> list[str]:
        """Queue ``frames`` (in order); returns the notes of frames dropped."""
        self.frames.extend(frames)
        excess = len(self.frames) - self.max_frames
        if excess <= 0:
            return []
        self.dropped += excess
        note = (f"LAGGING: {excess} frames waited too long and were dropped (frames "
                f"{self.frames[0].index}-{self.frames[excess - 1].index}; {self.dropped} so far)")
        del self.frames[:excess]
        return [note]

    def take(self, limit: int | None = None) -> list:
        """At most ``limit`` of the frames waiting (all: None); the others keep waiting."""
        use = coalesce(self.frames, len(self.frames) if limit is None else limit)
        chosen = {id(frame) for frame in use}
        self.frames = [frame for frame in self.frames if id(frame) not in chosen]
        return use


def coalesce(frames: list, limit: int) -> list:
    """At most ``limit`` of ``frames`` (in order), evenly spread and always with the newest:
    what one update detects when frames come faster than the updates (the update loop that
    detects its own frames: the 3D Slicer module)."""
    if len(frames) <= limit:
        return list(frames)
    if limit < 1:
        raise ComRegError("At least one frame per update must be used.", "")
    picks = np.unique(np.round(np.linspace(len(frames) - 1, 0, limit)).astype(int))
    return [frames[i] for i in sorted(picks)]
