"""Tracked freehand ultrasound sweeps: 2D B-mode frames with one image-to-reference pose each.

Every reader returns one :class:`TrackedSweep`. Formats:

- PLUS sequence metafiles ``.igs.mha`` / ``.seq.mha`` (zlib-compressed or raw) and their NRRD form
  ``.igs.nrrd`` / ``.seq.nrrd`` (custom fields ``key:=value``), with per-frame ``*ToTracker`` /
  ``*ToReference`` transforms, their status, ``UltrasoundImageOrientation`` and timestamps; the
  image-to-probe calibration comes from the sequence itself or from a PLUS device-set XML
  (``<Transform From="Image" To="Probe" Matrix=...>``). :func:`read_plus_sequence`.
- A frame folder as in UltraBones100k: ``frames/<timestamp>.png``, ``tracking.csv`` (positions
  and Euler angles of the probe), ``calibration.json``. :func:`read_frame_folder`.
- A 3D Slicer volume sequence ``.seq.nrrd`` (a 4D NRRD, list axis first or last, frames sharing
  one geometry). :func:`read_slicer_volume_sequence`.

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

import csv
import json
import logging
import re
import xml.etree.ElementTree as ET
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from comreg_core.errors import ComRegError, CorruptFileError, InputFileNotFoundError
from comreg_core.io._files import file_extension, require_extension, require_input_file

log = logging.getLogger(__name__)

#: Sequence files :func:`read_tracked_sweep` reads (a directory is a frame folder).
SWEEP_EXTENSIONS = [".igs.mha", ".seq.mha", ".igs.nrrd", ".seq.nrrd", ".mha", ".mhd", ".nrrd",
                    ".nhdr"]
#: Image files a frame folder may hold.
FRAME_IMAGE_EXTENSIONS = [".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".pnm"]

_SEQ_FIELD = re.compile(r"^Seq_Frame(\d+)_(.+)$")
_TRANSFORM_NAME = re.compile(r"^([A-Za-z0-9]+)To([A-Za-z0-9]+)$")


class CalibrationMismatchError(ComRegError):
    """The calibration was made for another image size, or maps outside the frames."""


class NoValidFramesError(ComRegError):
    """A sweep has no frame with both an image and a valid pose."""


# --------------------------------------------------------------------------------------------
# The sweep
# --------------------------------------------------------------------------------------------


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
        return self.T_ref_image @ np.diag([self.spacing[0], self.spacing[1], 1.0, 1.0])

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
            out[idx] = local[idx] @ T[:3, :2].T + T[:3, 3]
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


# --------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------


def read_tracked_sweep(path: str | Path, *, calibration: str | Path | None = None,
                       reference: str = "Reference") -> TrackedSweep:
    """Read a tracked sweep from a PLUS sequence file, a 3D Slicer volume sequence, or a frame
    folder (a directory). ``calibration`` is a PLUS device-set XML (sequence files) or a
    ``calibration.json`` (frame folders); ``reference`` names the output coordinate frame of a
    PLUS file.

    Raises:
        InputFileNotFoundError, UnsupportedFormatError, CorruptFileError,
        CalibrationMismatchError, NoValidFramesError, ComRegError (no transform chain).
    """
    path = Path(path)
    if path.is_dir():
        return read_frame_folder(path, calibration=calibration)
    if not path.exists():
        raise InputFileNotFoundError(path, "ultrasound sweep (file or frame folder)")
    ext = require_extension(path, "tracked ultrasound sweep", SWEEP_EXTENSIONS)
    if ext in (".igs.nrrd", ".seq.nrrd", ".nrrd", ".nhdr"):
        fields = _nrrd_header(path)
        if not any(_SEQ_FIELD.match(str(k)) for k in fields):
            if calibration is not None:
                log.warning("%s is a 3D Slicer volume sequence: its geometry is in the file, so "
                            "the calibration '%s' is not used", path, calibration)
            return read_slicer_volume_sequence(path)
    return read_plus_sequence(path, calibration=calibration, reference=reference)


# --------------------------------------------------------------------------------------------
# PLUS device set (calibration) XML
# --------------------------------------------------------------------------------------------


@dataclass
class PlusDeviceSet:
    """What ComReg uses from a PLUS device-set configuration XML.

    Attributes:
        transforms: ``{"ImageToProbe": (4, 4), ...}`` from ``<CoordinateDefinitions>``.
        output_spacing: ``(3,)`` mm of ``<VolumeReconstruction OutputSpacing>``, or None.
        clip_origin, clip_size: ``ClipRectangleOrigin``/``Size`` ``(2,)`` px, or None.
        image_size: ``(W, H)`` px of ``<ScanConversion OutputImageSizePixel>``, or None.
        path: the XML file.
    """

    transforms: dict[str, np.ndarray]
    output_spacing: np.ndarray | None = None
    clip_origin: np.ndarray | None = None
    clip_size: np.ndarray | None = None
    image_size: np.ndarray | None = None
    path: Path | None = None


def read_plus_device_set(path: str | Path) -> PlusDeviceSet:
    """Parse a PLUS device-set XML: every ``<Transform From To Matrix>`` (16 numbers, row
    major), the volume reconstruction spacing and clip rectangle, the scan-converted image size."""
    path = require_input_file(path, "PLUS configuration file")
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise CorruptFileError(path, f"not a readable XML file ({exc})") from None

    def numbers(element, name, count, dtype=float):
        text = element.get(name) if element is not None else None
        if text is None:
            return None
        try:
            values = np.array([dtype(v) for v in text.split()])
        except ValueError:
            values = np.array([])
        if values.size != count:
            raise CorruptFileError(path, f"<{element.tag} {name}=\"{text.strip()[:80]}\"> "
                                         f"should hold {count} numbers")
        return values

    transforms = {}
    for element in root.iter("Transform"):
        source, target = element.get("From"), element.get("To")
        if not source or not target or element.get("Matrix") is None:
            continue
        matrix = numbers(element, "Matrix", 16).reshape(4, 4)
        transforms[f"{source}To{target}"] = matrix
    recon = next(root.iter("VolumeReconstruction"), None)
    scan = next(root.iter("ScanConversion"), None)
    return PlusDeviceSet(
        transforms=transforms,
        output_spacing=numbers(recon, "OutputSpacing", 3),
        clip_origin=numbers(recon, "ClipRectangleOrigin", 2, int),
        clip_size=numbers(recon, "ClipRectangleSize", 2, int),
        image_size=numbers(scan, "OutputImageSizePixel", 2, int),
        path=path)


def read_plus_calibration(path: str | Path, name: str = "ImageToProbe") -> np.ndarray:
    """The ``(4, 4)`` transform ``name`` (default ImageToProbe: pixel -> probe mm) of a PLUS
    device-set XML."""
    device_set = read_plus_device_set(path)
    if name not in device_set.transforms:
        found = ", ".join(sorted(device_set.transforms)) or "none"
        raise ComRegError(f"'{path}' defines no {name} transform (it defines: {found}).",
                          "Pass the PLUS configuration file written by the calibration "
                          "(fCal) for this probe.")
    return device_set.transforms[name]


# --------------------------------------------------------------------------------------------
# PLUS sequence files
# --------------------------------------------------------------------------------------------


def read_plus_sequence(path: str | Path, *, calibration: str | Path | PlusDeviceSet | None = None,
                       reference: str = "Reference", image: str = "Image") -> TrackedSweep:
    """Read a PLUS sequence (``.igs.mha``/``.seq.mha``/``.igs.nrrd``/``.seq.nrrd``).

    Frames are flipped to the MF orientation. The pose of each frame is the chain from ``image``
    to ``reference`` through the per-frame transforms and the static ones of ``calibration`` (a
    device-set XML) -- normally ``inv(ReferenceToTracker) @ ProbeToTracker @ ImageToProbe``.
    Without a ``reference`` frame in the data, "Tracker" is used (with a warning).
    """
    path = Path(path)
    ext = require_extension(path, "PLUS sequence", SWEEP_EXTENSIONS)
    path = require_input_file(path, "ultrasound sequence")
    if ext in (".igs.nrrd", ".seq.nrrd", ".nrrd", ".nhdr"):
        fields, frames = _read_plus_nrrd(path)
    else:
        fields, frames = _read_plus_metaimage(path)
    if not any(_SEQ_FIELD.match(str(key)) for key in fields):
        raise ComRegError(f"'{path}' has no per-frame tracking fields (Seq_FrameXXXX_...): it is "
                          "an image or volume, not a PLUS tracked ultrasound sequence.",
                          "Pass the sequence file recorded by PLUS (.igs.mha, .seq.mha, "
                          ".igs.nrrd), a 3D Slicer volume sequence or a frame folder.")
    n, H, W = frames.shape
    frames = _to_mf(path, fields, frames)
    per_frame = _per_frame_fields(path, fields, n)

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

    names = sorted({key[: -len("Transform")] for rec in per_frame for key in rec
                    if key.endswith("Transform") and _TRANSFORM_NAME.match(key[:-9])})
    chain, reference = _transform_chain(path, image, reference, names, static)
    log.info("%s: %d frames %dx%d, %s = %s", path, n, W, H, f"{image}To{reference}",
             " @ ".join(("inv(%s)" % name if inverse else name) for name, inverse in
                        reversed(chain)))

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
        T = M @ T
        valid &= ok
    image_ok = np.array([(rec.get("ImageStatus") or rec.get("Status") or "OK").strip().upper()
                         == "OK" for rec in per_frame])
    if (~image_ok).any():
        reasons["image status not OK"] = int((~image_ok).sum())
    valid &= image_ok
    valid &= np.isfinite(T).all(axis=(1, 2))
    if (~valid).any():
        detail = ", ".join(f"{count} {reason}" for reason, count in reasons.items())
        log.warning("%s: %d of %d frames have no valid %sTo%s pose (%s) and are left out, as "
                    "PLUS does", path, int((~valid).sum()), n, image, reference, detail)
    if not valid.any():
        raise NoValidFramesError(
            f"None of the {n} frames in '{path}' has a valid {image}To{reference} pose "
            f"({', '.join(f'{c} {r}' for r, c in reasons.items())}).",
            "Check that the probe and the reference marker were visible to the tracker.")

    first = T[np.flatnonzero(valid)[0]]
    scale = np.linalg.norm(first[:3, :3], axis=0)
    if not (1e-4 < scale[0] < 10 and 1e-4 < scale[1] < 10):
        raise CalibrationMismatchError(
            f"The {image}To{reference} chain of '{path}' gives a pixel size of "
            f"{scale[0]:.3g} x {scale[1]:.3g} mm.",
            "The ImageToProbe calibration should map pixels to millimetres (PLUS fCal "
            "output, about 0.05-0.5 mm per pixel); check the configuration file.")
    if not (0.005 < scale[0] < 2 and 0.005 < scale[1] < 2):
        log.warning("%s: unusual pixel size %.3g x %.3g mm; is the calibration in mm per pixel?",
                    path, scale[0], scale[1])
    unscale = np.diag([1 / scale[0], 1 / scale[1], 1 / scale[2] if scale[2] > 0 else 1.0, 1.0])
    T = T @ unscale
    timestamps = np.array([_to_float(rec.get("Timestamp")) for rec in per_frame])
    return TrackedSweep(frames, scale[:2], T, timestamps, valid, reference,
                        [f"Frame{i:04d}" for i in range(n)], path)


def _nrrd_header(path: Path) -> dict:
    import nrrd

    try:
        return nrrd.read_header(str(path))
    except (nrrd.NRRDError, OSError, ValueError, StopIteration, KeyError, IndexError) as exc:
        raise CorruptFileError(path, f"bad NRRD header ({type(exc).__name__}: {exc})") from None


def _read_plus_metaimage(path: Path) -> tuple[dict[str, str], np.ndarray]:
    """Header fields and ``(N, H, W)`` frames of a PLUS ``.mha``/``.mhd`` sequence."""
    from comreg_core.io.volumes import (_MET_DTYPES, _field, _is_true, _read_metaimage_data,
                                        read_metaimage_header)

    fields, offset = read_metaimage_header(path)
    try:
        ndims = int(_field(fields, "NDims") or 0)
        dims = [int(v) for v in (_field(fields, "DimSize") or "").split()]
    except ValueError:
        raise CorruptFileError(path, "'NDims' or 'DimSize' is not a list of integers") from None
    if ndims == 4 and len(dims) == 4 and dims[2] == 1:  # W H 1 N: 2D frames stored as 3D
        dims = [dims[0], dims[1], dims[3]]
    elif ndims == 2 and len(dims) == 2:
        dims = [*dims, 1]
    if len(dims) != 3 or min(dims) < 0:
        raise CorruptFileError(path, f"'DimSize = {_field(fields, 'DimSize')}' does not describe "
                                     "2D frames over time (width height count)")
    element_type = (_field(fields, "ElementType") or "").upper()
    if element_type not in _MET_DTYPES:
        raise CorruptFileError(path, f"unsupported or missing 'ElementType = {element_type}'")
    msb = _is_true(fields, "BinaryDataByteOrderMSB", "ElementByteOrderMSB")
    dtype = np.dtype(_MET_DTYPES[element_type]).newbyteorder(">" if msb else "<")
    channels = int(_field(fields, "ElementNumberOfChannels") or 1)
    W, H, N = dims
    if N == 0 or W == 0 or H == 0:
        raise NoValidFramesError(f"'{path}' holds no image frames (DimSize {W} {H} {N}).",
                                 "Record the sweep with the ultrasound video device enabled.")
    expected = W * H * N * channels * dtype.itemsize
    data = _read_metaimage_data(path, fields, offset, expected)
    frames = np.frombuffer(data, dtype).astype(dtype.newbyteorder("="))
    frames = frames.reshape(N, H, W, channels) if channels > 1 else frames.reshape(N, H, W)
    return fields, _to_grey(frames)


def _read_plus_nrrd(path: Path) -> tuple[dict[str, str], np.ndarray]:
    """Header fields and ``(N, H, W)`` frames of a PLUS ``.igs.nrrd``/``.seq.nrrd``."""
    import nrrd

    from comreg_core.io.volumes import _parsing

    with _parsing(path):
        array, header = nrrd.read(str(path), index_order="F")
    kinds = [str(k).lower() for k in (header.get("kinds") or [])]
    if array.ndim == 2:
        array = array[..., None]
        kinds = kinds + ["list"]
    if array.ndim != 3:
        raise CorruptFileError(path, f"a PLUS NRRD sequence has 3 axes (x, y, frames); this one "
                                     f"has {array.ndim} (kinds {' '.join(kinds)})")
    list_axes = [i for i, k in enumerate(kinds) if k not in ("domain", "space")] or [2]
    frame_axis = list_axes[-1]
    x_axis, y_axis = [i for i in range(3) if i != frame_axis]
    frames = np.moveaxis(array, (frame_axis, y_axis, x_axis), (0, 1, 2))
    fields = {str(k): (v if isinstance(v, str) else " ".join(map(str, np.ravel(v))))
              for k, v in header.items()}
    return fields, np.ascontiguousarray(_to_grey(frames))


def _to_grey(frames: np.ndarray) -> np.ndarray:
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


def _to_mf(path: Path, fields: dict[str, str], frames: np.ndarray) -> np.ndarray:
    """Flip frames from the file's UltrasoundImageOrientation to MF (first letter: marked (M)
    or unmarked (U) side at column 0; second: near (N) or far (F) at the last row)."""
    lower = {k.lower().replace(" ", ""): v for k, v in fields.items()}
    kind = (lower.get("ultrasoundimagetype") or "BRIGHTNESS").strip().upper()
    if kind not in ("BRIGHTNESS", "XX", ""):
        raise ComRegError(f"'{path}' holds {kind} ultrasound data, not B-mode images.",
                          "Record or export B-mode (brightness) frames.")
    orientation = lower.get("ultrasoundimageorientation")
    if orientation is None:
        log.warning("%s has no UltrasoundImageOrientation; assuming MF (transducer at the top "
                    "row, marked side at column 0)", path)
        return frames
    code = orientation.strip().upper()[:2]
    if code in ("MF", "XX"):
        return frames
    if len(code) != 2 or code[0] not in "MU" or code[1] not in "FN":
        raise ComRegError(f"'{path}' has UltrasoundImageOrientation = {orientation}; ComReg "
                          "reads B-mode frames with scan lines in columns (MF, MN, UF, UN).",
                          "Export the sequence from PLUS with an MF orientation.")
    if code[0] == "U":
        frames = frames[:, :, ::-1]
    if code[1] == "N":
        frames = frames[:, ::-1, :]
    return np.ascontiguousarray(frames)


def _per_frame_fields(path: Path, fields: dict[str, str], n: int) -> list[dict[str, str]]:
    """``n`` dicts of each frame's ``Seq_FrameXXXX_*`` fields (suffix -> value)."""
    per_frame: list[dict[str, str]] = [{} for _ in range(n)]
    beyond = set()
    for key, value in fields.items():
        match = _SEQ_FIELD.match(key)
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


def _to_float(text) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return float("nan")


# --------------------------------------------------------------------------------------------
# Frame folder (UltraBones100k layout)
# --------------------------------------------------------------------------------------------


@dataclass
class FrameFolderTracking:
    """The poses of a frame folder, from ``tracking.csv`` + ``calibration.json``.

    Attributes:
        names: ``N`` frame names (the ``timestamp`` column as written: the image file stems).
        timestamps_ms: ``(N,)`` the ``timestamp`` column (ms).
        T_ref_image: ``(N, 4, 4)`` image mm -> CT/reference mm (pixel centre ``(c, r)`` at
            ``(c * sx, r * sy, 0)``); rigid.
        spacing: ``(2,)`` ``(sx, sy)`` mm per pixel.
        image_size: ``(W, H)`` px the calibration was made for.
        valid: ``(N,)`` bool, False for rows with non-finite numbers.
    """

    names: list[str]
    timestamps_ms: np.ndarray
    T_ref_image: np.ndarray
    spacing: np.ndarray
    image_size: tuple[int, int]
    valid: np.ndarray


def _euler_pose(translation, euler_xyz_deg) -> np.ndarray:
    """``(..., 4, 4)`` from translations ``(..., 3)`` mm and scipy 'xyz' Euler angles in
    degrees (extrinsic x, then y, then z: ``R = Rz @ Ry @ Rx``)."""
    from scipy.spatial.transform import Rotation

    translation = np.asarray(translation, dtype=np.float64)
    euler = np.asarray(euler_xyz_deg, dtype=np.float64)
    shape = translation.shape[:-1]
    T = np.zeros((*shape, 4, 4))
    T[..., 3, 3] = 1.0
    flat_e = euler.reshape(-1, 3)
    R = np.full((len(flat_e), 3, 3), np.nan)
    good = np.isfinite(flat_e).all(axis=1)
    if good.any():
        R[good] = Rotation.from_euler("xyz", flat_e[good], degrees=True).as_matrix()
    T[..., :3, :3] = R.reshape(*shape, 3, 3)
    T[..., :3, 3] = translation
    return T


def read_frame_folder_tracking(tracking_csv: str | Path, calibration_json: str | Path
                               ) -> FrameFolderTracking:
    """Poses of a frame folder (the one reader of the UltraBones100k tracking chain)::

        p_ref = T_ref_probe(frame) @ T_probe_image @ diag(sx, sy, 1, 1) @ [c + 0.5, r + 0.5, 0, 1]

    (``calibration.json`` counts pixel centres at ``c + 0.5``; ComReg's image frame puts them at
    ``c``, hence a half-pixel shift folded into ``T_ref_image``.) Rows with non-finite values are
    kept as invalid frames, with a warning.
    """
    tracking_csv = require_input_file(tracking_csv, "tracking file")
    calibration_json = require_input_file(calibration_json, "calibration file")
    try:
        cal = json.loads(calibration_json.read_text(encoding="utf-8"))
        sx, sy = (float(v) for v in cal["pixel_spacing_mm"])
        cols, rows = (int(v) for v in cal["image_size_px"])
        T_probe_image = _euler_pose(cal["image_to_probe"]["translation_mm"],
                                    cal["image_to_probe"]["euler_xyz_deg"])
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CorruptFileError(calibration_json, f"missing or bad calibration entry ({exc})") \
            from None
    if not (sx > 0 and sy > 0 and np.isfinite([sx, sy]).all() and cols > 0 and rows > 0
            and np.isfinite(T_probe_image).all()):
        raise CorruptFileError(calibration_json, "pixel spacing, image size and image_to_probe "
                                                 "must be positive, finite numbers")
    try:
        with open(tracking_csv, newline="", encoding="utf-8") as f:
            table = list(csv.DictReader(f))
        names = [r["timestamp"].strip() for r in table]
        stamps = np.array([_to_float(r["timestamp"]) for r in table])
        xyz = np.array([[_to_float(r[k]) for k in ("x", "y", "z")] for r in table])
        euler = np.array([[_to_float(r[k]) for k in ("euler_x", "euler_y", "euler_z")]
                          for r in table])
        factors = np.array([_to_float(r.get("space_factor", sx)) for r in table])
    except (KeyError, TypeError, AttributeError, csv.Error, UnicodeDecodeError) as exc:
        raise CorruptFileError(tracking_csv, f"missing or bad tracking column ({exc}); expected "
                                             "timestamp,x,y,z,euler_x,euler_y,euler_z") from None
    if len(stamps) == 0:
        raise CorruptFileError(tracking_csv, "it has no frames")
    valid = np.isfinite(xyz).all(axis=1) & np.isfinite(euler).all(axis=1)
    if (~valid).any():
        log.warning("%s: %d of %d rows have missing or non-numeric pose values; those frames "
                    "are left out", tracking_csv, int((~valid).sum()), len(valid))
    off = np.isfinite(factors) & (np.abs(factors - sx) > 0.01 * sx)
    if off.any():
        log.warning("%s: %d rows give a space_factor (mm per pixel) other than the calibration's "
                    "%.5g mm; the calibration is used", tracking_csv, int(off.sum()), sx)
    T_ref_probe = _euler_pose(np.nan_to_num(xyz), np.nan_to_num(euler))
    half = np.eye(4)
    half[:2, 3] = 0.5 * sx, 0.5 * sy
    T = T_ref_probe @ T_probe_image @ half
    T[~valid] = np.nan
    return FrameFolderTracking(names, stamps, T, np.array([sx, sy]), (cols, rows), valid)


def read_frame_folder(folder: str | Path, *, calibration: str | Path | None = None,
                      tracking: str | Path | None = None, frames_dir: str | Path | None = None
                      ) -> TrackedSweep:
    """Read a frame folder: images ``frames/<name>.png`` (or beside the CSV), ``tracking.csv``
    and ``calibration.json``; ``<name>`` is the ``timestamp`` column.

    Frames with a tracking row but no image, or an image but no row, are left out with a
    warning; images of another size than the calibration's raise
    :class:`CalibrationMismatchError`.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileNotFoundError(folder, "frame folder")
    if calibration is not None and file_extension(calibration) != ".json":
        raise ComRegError(f"A frame folder needs its calibration as JSON (calibration.json), not "
                          f"'{calibration}'.", "Pass the calibration.json of the recording "
                          "(image_to_probe and pixel_spacing_mm, see the data README).")
    track = read_frame_folder_tracking(tracking or folder / "tracking.csv",
                                       calibration or folder / "calibration.json")
    image_dir = Path(frames_dir) if frames_dir else (folder / "frames" if (folder / "frames")
                                                     .is_dir() else folder)
    files = {p.stem: p for p in sorted(image_dir.iterdir())
             if p.is_file() and p.suffix.lower() in FRAME_IMAGE_EXTENSIONS}
    present = [i for i, name in enumerate(track.names) if name in files]
    missing = [name for name in track.names if name not in files]
    if missing:
        log.warning("%s: %d of %d tracked frames have no image in %s (first: %s); they are "
                    "left out", folder, len(missing), len(track.names), image_dir, missing[0])
    extra = sorted(set(files) - set(track.names))
    if extra:
        log.warning("%s: %d images have no tracking row (first: %s); they are left out", folder,
                    len(extra), files[extra[0]].name)
    if not present:
        raise NoValidFramesError(
            f"No image in '{image_dir}' matches a row of the tracking file (images are named "
            "by the 'timestamp' column, e.g. 162005.png).",
            "Check that the frames and tracking.csv come from the same recording.")
    frames = []
    W, H = track.image_size
    for i in present:
        image = read_frame_image(files[track.names[i]])
        if image.shape != (H, W):
            raise CalibrationMismatchError(
                f"Frame '{files[track.names[i]]}' is {image.shape[1]} x {image.shape[0]} px but "
                f"the calibration is for {W} x {H} px images.",
                "Use the calibration made for this probe and imaging depth, or export the "
                "frames uncropped.")
        frames.append(image)
    idx = np.array(present)
    return TrackedSweep(np.stack(frames), track.spacing, track.T_ref_image[idx],
                        track.timestamps_ms[idx] / 1000.0, track.valid[idx], "CT",
                        [track.names[i] for i in present], folder)


def read_frame_image(path: str | Path) -> np.ndarray:
    """One 2D image file (PNG, JPEG, BMP, TIFF, PNM) as ``(H, W)``, row 0 at the top; colour
    images become luminance."""
    import vtk
    from vtk.util import numpy_support

    path = require_input_file(path, "frame image")
    reader = vtk.vtkImageReader2Factory.CreateImageReader2(str(path))
    if reader is None:
        raise CorruptFileError(path, "not an image VTK can read (PNG, JPEG, BMP, TIFF, PNM)")
    reader.SetFileName(str(path))
    reader.Update()
    image = reader.GetOutput()
    scalars = image.GetPointData().GetScalars() if image else None
    nx, ny, nz = image.GetDimensions() if image else (0, 0, 0)
    if scalars is None or nx * ny == 0:
        raise CorruptFileError(path, "the image holds no pixels")
    if nz != 1:
        raise CorruptFileError(path, f"a 2D frame was expected, found {nx} x {ny} x {nz}")
    pixels = numpy_support.vtk_to_numpy(scalars).reshape(ny, nx, -1)[::-1]
    return np.ascontiguousarray(_to_grey(pixels[None])[0])


# --------------------------------------------------------------------------------------------
# 3D Slicer volume sequence
# --------------------------------------------------------------------------------------------


def read_slicer_volume_sequence(path: str | Path) -> TrackedSweep:
    """Read a 3D Slicer volume sequence ``.seq.nrrd``: a 4D NRRD of 2D frames (one spatial axis
    of size 1) with a list axis first or last. All frames share the file's geometry (a volume
    sequence has no per-frame pose), converted to LPS; ``axis N index values`` give timestamps.
    """
    import nrrd

    from comreg_core.io.volumes import _parsing
    from comreg_core.transforms import check_space, space_change

    path = require_input_file(path, "volume sequence")
    with _parsing(path):
        array, header = nrrd.read(str(path), index_order="F")
    if array.ndim != 4:
        raise CorruptFileError(path, f"a volume sequence has 4 axes (3 spatial + frames); this "
                                     f"one has {array.ndim}")
    directions = np.asarray(header.get("space directions"), dtype=np.float64)
    if directions.shape != (4, 3) or "space origin" not in header or "space" not in header:
        raise CorruptFileError(path, "a volume sequence needs 'space', 'space origin' and "
                                     "'space directions' for its 3 spatial axes")
    spatial = [i for i in range(4) if np.isfinite(directions[i]).all()]
    if len(spatial) != 3:
        raise CorruptFileError(path, f"expected 3 spatial axes and one list axis, found "
                                     f"{len(spatial)} spatial ones")
    frame_axis = next(i for i in range(4) if i not in spatial)
    flat = [i for i in spatial if array.shape[i] == 1]
    if not flat:
        raise ComRegError(f"'{path}' is a sequence of 3D volumes "
                          f"({' x '.join(str(array.shape[i]) for i in spatial)}), not of 2D "
                          "ultrasound frames.", "Export the 2D image sequence instead.")
    normal_axis = flat[-1]
    x_axis, y_axis = [i for i in spatial if i != normal_axis]
    frames = np.moveaxis(array, (frame_axis, y_axis, x_axis, normal_axis), (0, 1, 2, 3))[..., 0]
    space = check_space(str(header["space"]))
    to_lps = space_change(space, "LPS")
    T_pixel = np.eye(4)
    T_pixel[:3, 0] = directions[x_axis]
    T_pixel[:3, 1] = directions[y_axis]
    normal = directions[normal_axis]
    T_pixel[:3, 2] = normal / max(np.linalg.norm(normal), 1e-12)
    T_pixel[:3, 3] = np.asarray(header["space origin"], dtype=np.float64)
    T_pixel = to_lps @ T_pixel
    spacing = np.linalg.norm(T_pixel[:3, :2], axis=0)
    T_image = T_pixel @ np.diag([1 / spacing[0], 1 / spacing[1], 1.0, 1.0])
    n = frames.shape[0]
    stamps = np.full(n, np.nan)
    for key, value in header.items():
        if re.fullmatch(rf"axis {frame_axis} index values", str(key)):
            values = [_to_float(v) for v in str(value).split()]
            if len(values) == n:
                stamps = np.array(values)
    log.warning("%s is a 3D Slicer volume sequence: all %d frames share one geometry (it holds "
                "no per-frame tracking); for a freehand sweep use the PLUS recording", path, n)
    return TrackedSweep(np.ascontiguousarray(_to_grey(frames)), spacing,
                        np.repeat(T_image[None], n, axis=0), stamps, np.ones(n, dtype=bool),
                        space, [f"Frame{i:04d}" for i in range(n)], path)
