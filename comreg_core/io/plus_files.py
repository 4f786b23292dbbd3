"""PLUS files, the parts a reader needs before composing poses: the device-set configuration XML
(static transforms such as the ImageToProbe calibration, clip rectangle, image size) and the
header fields and 2D frames of a sequence file (``.igs.mha``/``.seq.mha`` MetaImage form,
``.igs.nrrd``/``.seq.nrrd`` NRRD form, custom fields ``key:=value``). Frame conventions: see
:mod:`comreg_core.io.sweeps`; the poses: :mod:`comreg_core.io.plus_sequences`.
"""

from __future__ import annotations

import logging
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import nrrd
import numpy as np

from comreg_core.errors import ComRegError, CorruptFileError
from comreg_core.io._files import file_extension, parse_numbers, require_input_file
from comreg_core.io.image_files import parse_errors_as_corrupt
from comreg_core.io.metaimage_files import (header_field, metaimage_dtype,
                                            read_metaimage_header, read_metaimage_voxels)
from comreg_core.io.sweeps import NoValidFramesError, frames_to_grey

log = logging.getLogger(__name__)

#: A per-frame field of a PLUS sequence, ``Seq_Frame<index>_<name>`` (groups: index, name).
PLUS_FRAME_FIELD = re.compile(r"^Seq_Frame(\d+)_(.+)$")


def has_plus_frame_fields(fields) -> bool:
    """True when header ``fields`` (their keys) hold PLUS per-frame (tracking) fields."""
    return any(PLUS_FRAME_FIELD.match(str(key)) for key in fields)


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
        values = parse_numbers(text, count, dtype)
        if values is None:
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


def read_plus_frames(path: Path) -> tuple[dict[str, str], np.ndarray]:
    """Header fields and ``(N, H, W)`` frames, as stored, of a PLUS sequence file: the NRRD form
    for ``.nrrd``/``.nhdr`` names, else the MetaImage form."""
    if file_extension(path).endswith((".nrrd", ".nhdr")):
        return read_plus_nrrd_frames(path)
    return read_plus_metaimage_frames(path)


def read_plus_metaimage_frames(path: Path) -> tuple[dict[str, str], np.ndarray]:
    """Header fields and ``(N, H, W)`` frames of a PLUS ``.mha``/``.mhd`` sequence."""
    fields, offset = read_metaimage_header(path)
    try:
        ndims = int(header_field(fields, "NDims") or 0)
        dims = [int(v) for v in (header_field(fields, "DimSize") or "").split()]
    except ValueError:
        raise CorruptFileError(path, "'NDims' or 'DimSize' is not a list of integers") from None
    if ndims == 4 and len(dims) == 4 and dims[2] == 1:  # W H 1 N: 2D frames stored as 3D
        dims = [dims[0], dims[1], dims[3]]
    elif ndims == 2 and len(dims) == 2:
        dims = [*dims, 1]
    if len(dims) != 3 or min(dims) < 0:
        raise CorruptFileError(path, f"'DimSize = {header_field(fields, 'DimSize')}' does not "
                                     "describe 2D frames over time (width height count)")
    dtype = metaimage_dtype(path, fields)
    channels = int(header_field(fields, "ElementNumberOfChannels") or 1)
    W, H, N = dims
    if N == 0 or W == 0 or H == 0:
        raise NoValidFramesError(f"'{path}' holds no image frames (DimSize {W} {H} {N}).",
                                 "Record the sweep with the ultrasound video device enabled.")
    expected = W * H * N * channels * dtype.itemsize
    data = read_metaimage_voxels(path, fields, offset, expected)
    frames = np.frombuffer(data, dtype).astype(dtype.newbyteorder("="))
    frames = frames.reshape(N, H, W, channels) if channels > 1 else frames.reshape(N, H, W)
    return fields, frames_to_grey(frames)


def read_plus_nrrd_frames(path: Path) -> tuple[dict[str, str], np.ndarray]:
    """Header fields and ``(N, H, W)`` frames of a PLUS ``.igs.nrrd``/``.seq.nrrd``."""
    with parse_errors_as_corrupt(path):
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
    return fields, np.ascontiguousarray(frames_to_grey(frames))


def frames_to_mf(path: Path, fields: dict[str, str], frames: np.ndarray) -> np.ndarray:
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
