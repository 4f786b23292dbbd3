"""PLUS sequences -> :class:`TrackedSweep`: the frames of a ``.igs.mha``/``.seq.mha``/
``.igs.nrrd``/``.seq.nrrd`` file flipped to MF, and each frame's image-to-reference pose composed
from its per-frame ``*ToTracker``/``*ToReference`` transforms (and their status) and the static
ones of a device set, as PLUS composes them::

    ImageToReference = inv(ReferenceToTracker) @ ProbeToTracker @ ImageToProbe

Frame and pose conventions: see :mod:`comreg_core.io.sweeps`.
"""

from __future__ import annotations

import logging
import re
from collections import deque
from pathlib import Path

import numpy as np

from comreg_core.transforms import matmul
from comreg_core.errors import ComRegError, CorruptFileError
from comreg_core.io._files import file_extension, require_extension, require_input_file
from comreg_core.io.plus_files import (PLUS_FRAME_FIELD, PlusDeviceSet, frames_to_mf,
                                       has_plus_frame_fields, read_plus_device_set,
                                       read_plus_frames)
from comreg_core.io.sweeps import (SWEEP_EXTENSIONS, CalibrationMismatchError, NoValidFramesError,
                                   TrackedSweep, parse_float)

log = logging.getLogger(__name__)

_TRANSFORM_NAME = re.compile(r"^([A-Za-z0-9]+)To([A-Za-z0-9]+)$")


def read_plus_sequence(path: str | Path, *, calibration: str | Path | PlusDeviceSet | None = None,
                       reference: str = "Reference", image: str = "Image") -> TrackedSweep:
    """Read a PLUS sequence (``.igs.mha``/``.seq.mha``/``.igs.nrrd``/``.seq.nrrd``).

    Frames are flipped to the MF orientation. The pose of each frame is the chain from ``image``
    to ``reference`` through the per-frame transforms and the static ones of ``calibration`` (a
    device-set XML) -- normally ``inv(ReferenceToTracker) @ ProbeToTracker @ ImageToProbe``.
    Without a ``reference`` frame in the data, "Tracker" is used (with a warning).
    """
    path = Path(path)
    require_extension(path, "PLUS sequence", SWEEP_EXTENSIONS)
    path = require_input_file(path, "ultrasound sequence")
    fields, frames = _read_tracked_frames(path)
    n, H, W = frames.shape
    frames = frames_to_mf(path, fields, frames)
    per_frame = _per_frame_fields(path, fields, n)
    static = _static_transforms(calibration, W, H)
    names = sorted({key[: -len("Transform")] for rec in per_frame for key in rec
                    if key.endswith("Transform") and _TRANSFORM_NAME.match(key[:-9])})
    chain, reference = _transform_chain(path, image, reference, names, static)
    log.info("%s: %d frames %dx%d, %s = %s", path, n, W, H, f"{image}To{reference}",
             " @ ".join(("inv(%s)" % name if inverse else name) for name, inverse in
                        reversed(chain)))
    T, valid = _compose_poses(path, per_frame, chain, names, static, f"{image}To{reference}")
    T, spacing = _pixel_units(path, T, valid, f"{image}To{reference}")
    timestamps = np.array([parse_float(rec.get("Timestamp")) for rec in per_frame])
    return TrackedSweep(frames, spacing, T, timestamps, valid, reference,
                        [f"Frame{i:04d}" for i in range(n)], path)


def _read_tracked_frames(path: Path) -> tuple[dict[str, str], np.ndarray]:
    """The header fields and the ``(N, H, W)`` frames of a PLUS sequence, as stored; raises
    :class:`ComRegError` for an image without per-frame tracking fields."""
    fields, frames = read_plus_frames(path)
    if not has_plus_frame_fields(fields):
        raise ComRegError(f"'{path}' has no per-frame tracking fields (Seq_FrameXXXX_...): it is "
                          "an image or volume, not a PLUS tracked ultrasound sequence.",
                          "Pass the sequence file recorded by PLUS (.igs.mha, .seq.mha, "
                          ".igs.nrrd), a 3D Slicer volume sequence or a frame folder.")
    return fields, frames


def _static_transforms(calibration: str | Path | PlusDeviceSet | None, W: int, H: int
                       ) -> dict[str, np.ndarray]:
    """The static ``(4, 4)`` transforms of ``calibration`` (a device-set XML or a read one) by
    name, checked against ``W x H`` px frames; empty without one."""
    device_set = None
    if isinstance(calibration, PlusDeviceSet):
        device_set = calibration
    elif calibration is not None:
        if file_extension(calibration) == ".json":
            raise ComRegError(f"'{calibration}' is a frame-folder calibration (JSON); a PLUS "
                              "sequence needs its PLUS configuration XML.",
                              "Pass the PlusDeviceSet_*.xml file with the ImageToProbe "
                              "transform.")
        device_set = read_plus_device_set(calibration)
    static = dict(device_set.transforms) if device_set else {}
    if device_set is not None:
        _check_device_set_fits(device_set, W, H)
    return static


def _compose_poses(path: Path, per_frame: list[dict[str, str]], chain: list[tuple[str, bool]],
                   names: list[str], static: dict[str, np.ndarray], pose: str
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's ``(N, 4, 4)`` ``pose`` (pixels -> reference, still scaled by the pixel size)
    along ``chain``, and ``(N,)`` whether it is valid: every per-frame transform of the chain
    OK, the image status OK and the product finite. Logs the frames left out; raises
    :class:`NoValidFramesError` when none is valid."""
    n = len(per_frame)
    T = np.repeat(np.eye(4)[None], n, axis=0)
    valid = np.ones(n, dtype=bool)
    reasons: dict[str, int] = {}
    for name, inverse in chain:
        if name not in names:  # a static (calibration) transform; per-frame ones win, as in PLUS
            M = np.repeat(static[name][None], n, axis=0)
            ok = np.ones(n, dtype=bool)
        else:
            M, ok, why = _frame_transforms(path, per_frame, name)
            for reason, count in why.items():
                reasons[reason] = reasons.get(reason, 0) + count
        if inverse:
            M = _safe_inverse(M)
        T = matmul(M, T)
        valid &= ok
    image_ok = np.array([(rec.get("ImageStatus") or rec.get("Status") or "OK").strip().upper()
                         == "OK" for rec in per_frame])
    if (~image_ok).any():
        reasons["image status not OK"] = int((~image_ok).sum())
    valid &= image_ok
    valid &= np.isfinite(T).all(axis=(1, 2))
    if (~valid).any():
        detail = ", ".join(f"{count} {reason}" for reason, count in reasons.items())
        log.warning("%s: %d of %d frames have no valid %s pose (%s) and are left out, as "
                    "PLUS does", path, int((~valid).sum()), n, pose, detail)
    if not valid.any():
        raise NoValidFramesError(
            f"None of the {n} frames in '{path}' has a valid {pose} pose "
            f"({', '.join(f'{c} {r}' for r, c in reasons.items())}).",
            "Check that the probe and the reference marker were visible to the tracker.")
    return T, valid


def _pixel_units(path: Path, T: np.ndarray, valid: np.ndarray, pose: str
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``T`` ``(N, 4, 4)`` with the pixel size divided out of its columns, and the ``(2,)`` pixel
    size (mm, along x then y) read from the first valid frame's pose; raises
    :class:`CalibrationMismatchError` for a size no calibration in mm gives."""
    first = T[np.flatnonzero(valid)[0]]
    scale = np.linalg.norm(first[:3, :3], axis=0)
    if not (1e-4 < scale[0] < 10 and 1e-4 < scale[1] < 10):
        raise CalibrationMismatchError(
            f"The {pose} chain of '{path}' gives a pixel size of "
            f"{scale[0]:.3g} x {scale[1]:.3g} mm.",
            "The ImageToProbe calibration should map pixels to millimetres (PLUS fCal "
            "output, about 0.05-0.5 mm per pixel); check the configuration file.")
    if not (0.005 < scale[0] < 2 and 0.005 < scale[1] < 2):
        log.warning("%s: unusual pixel size %.3g x %.3g mm; is the calibration in mm per pixel?",
                    path, scale[0], scale[1])
    unscale = np.diag([1 / scale[0], 1 / scale[1], 1 / scale[2] if scale[2] > 0 else 1.0, 1.0])
    return matmul(T, unscale), scale[:2]


def _per_frame_fields(path: Path, fields: dict[str, str], n: int) -> list[dict[str, str]]:
    """``n`` dicts of each frame's ``Seq_FrameXXXX_*`` fields (suffix -> value)."""
    per_frame: list[dict[str, str]] = [{} for _ in range(n)]
    beyond = set()
    for key, value in fields.items():
        match = PLUS_FRAME_FIELD.match(key)
        if not match:
            continue
        index = int(match[1])
        if index >= n:
            beyond.add(index)
            continue
        per_frame[index][match[2]] = str(value).strip()
    if beyond:
        raise CorruptFileError(
            path, f"the header describes frames up to Seq_Frame{max(beyond):04d} but the image "
                  f"data hold only {n} frames (inconsistent frame counts)")
    empty = [i for i, rec in enumerate(per_frame) if not rec]
    if empty:
        log.warning("%s: %d of %d frames have no Seq_Frame fields (no tracking data), first "
                    "Seq_Frame%04d", path, len(empty), n, empty[0])
    return per_frame


def _frame_transforms(path: Path, per_frame: list[dict[str, str]], name: str
                      ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """``(N, 4, 4)`` values of per-frame transform ``name``, ``(N,)`` validity, reasons."""
    n = len(per_frame)
    M = np.full((n, 4, 4), np.nan)
    ok = np.zeros(n, dtype=bool)
    reasons = {f"{name} missing": 0, f"{name} INVALID": 0, f"{name} not finite": 0}
    for i, rec in enumerate(per_frame):
        text = rec.get(f"{name}Transform")
        if text is None:
            reasons[f"{name} missing"] += 1
            continue
        try:
            values = np.array([float(v) for v in text.split()])
        except ValueError:
            values = np.array([])
        if values.size not in (12, 16):
            raise CorruptFileError(path, f"Seq_Frame{i:04d}_{name}Transform should hold 16 "
                                         f"numbers: {text[:80]!r}")
        M[i] = np.vstack([values.reshape(-1, 4)[:3], [0, 0, 0, 1]])
        status = rec.get(f"{name}TransformStatus", "OK").strip().upper()
        if status != "OK":
            reasons[f"{name} INVALID"] += 1
        elif not np.isfinite(M[i]).all() or abs(np.linalg.det(M[i, :3, :3])) < 1e-12:
            reasons[f"{name} not finite"] += 1
        else:
            ok[i] = True
    return M, ok, {k: v for k, v in reasons.items() if v}


def _safe_inverse(M: np.ndarray) -> np.ndarray:
    """Inverse of each finite, invertible ``(4, 4)`` in ``(N, 4, 4)``; NaN elsewhere."""
    out = np.full_like(M, np.nan)
    good = np.isfinite(M).all(axis=(1, 2))
    good[good] = np.abs(np.linalg.det(M[good, :3, :3])) > 1e-12
    out[good] = np.linalg.inv(M[good])
    return out


def _transform_chain(path: Path, source: str, target: str, frame_names: list[str],
                     static: dict[str, np.ndarray]) -> tuple[list[tuple[str, bool]], str]:
    """Shortest chain of transforms from ``source`` to ``target`` frame: a list of
    ``(name, inverse)`` applied first to last. Falls back to target "Tracker"."""
    edges: dict[str, list[tuple[str, str, bool]]] = {}
    for name in [*frame_names, *static]:
        match = _TRANSFORM_NAME.match(name)
        if not match:
            continue
        a, b = match[1], match[2]
        edges.setdefault(a, []).append((b, name, False))
        edges.setdefault(b, []).append((a, name, True))

    def search(goal: str):
        previous: dict[str, tuple[str, str, bool] | None] = {source: None}
        queue = deque([source])
        while queue:
            node = queue.popleft()
            if node == goal:
                chain = []
                while previous[node] is not None:
                    parent, name, inverse = previous[node]
                    chain.append((name, inverse))
                    node = parent
                return chain[::-1]
            for nxt, name, inverse in edges.get(node, []):
                if nxt not in previous:
                    previous[nxt] = (node, name, inverse)
                    queue.append(nxt)
        return None

    chain = search(target)
    if chain is None and target != "Tracker":
        chain = search("Tracker")
        if chain is not None:
            log.warning("%s: no %s coordinate frame is reachable; the sweep is placed in the "
                        "Tracker frame instead", path, target)
            target = "Tracker"
    if chain is None:
        available = ", ".join(sorted({*frame_names, *static})) or "none"
        hint = ("Pass the PLUS configuration file (PlusDeviceSet_*.xml) holding the "
                f"{source}ToProbe calibration with --calibration."
                if f"{source}ToProbe" not in static else
                "The per-frame transforms do not connect the probe to that frame.")
        raise ComRegError(f"Cannot compose {source}To{target} for '{path}': the transforms "
                          f"available are {available}.", hint)
    if not chain:
        raise ComRegError(f"'{path}': the image and the reference frame are the same ('{target}').",
                          "Choose another reference frame.")
    return chain, target


def _check_device_set_fits(device_set: PlusDeviceSet, W: int, H: int) -> None:
    """Raise :class:`CalibrationMismatchError` if the device set was made for other images."""
    where = f"'{device_set.path}'" if device_set.path else "the PLUS configuration"
    if device_set.image_size is not None and tuple(device_set.image_size) != (W, H):
        raise CalibrationMismatchError(
            f"{where} is for {device_set.image_size[0]} x {device_set.image_size[1]} px images "
            f"but the frames are {W} x {H} px.",
            "Use the configuration (calibration) recorded with this probe and imaging depth.")
    if device_set.clip_origin is not None and device_set.clip_size is not None:
        c0, r0 = device_set.clip_origin
        if c0 < 0 or r0 < 0 or c0 >= W or r0 >= H:
            raise CalibrationMismatchError(
                f"{where} clips the frames at pixel ({c0}, {r0}), outside the {W} x {H} px "
                "images.", "Use the configuration recorded with this probe and imaging depth.")
