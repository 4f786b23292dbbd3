"""Volumes and label maps: NRRD (``.nrrd``, ``.nhdr``, ``.seg.nrrd``) and MetaImage (``.mha``, ``.mhd``).

Geometry is kept as one ``(4, 4)`` matrix ``ijk_to_space`` mapping voxel indices ``(i, j, k)`` (the
array's axes in order, i.e. NRRD/ITK axis order with i fastest on disk) to patient millimetres in
``space`` ("LPS" or "RAS"): ``[x, y, z, 1] = ijk_to_space @ [i, j, k, 1]``. Voxel centres sit at
integer indices (NRRD "cell" centering is converted on read).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import re
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import nrrd
import numpy as np

from comreg_core.errors import (
    ComRegError,
    CorruptFileError,
    EmptyMaskError,
    InputFileNotFoundError,
    LabelNotFoundError,
    MissingSpatialMetadataError,
)
from comreg_core.io._files import atomic_output, require_extension, require_input_file
from comreg_core.transforms import check_space, space_change


@dataclass
class Volume:
    """A scalar image on a regular grid placed in patient millimetres.

    Attributes:
        array: ``(I, J, K)`` voxel values, indexed ``array[i, j, k]``.
        ijk_to_space: ``(4, 4)`` voxel index -> ``space`` mm.
        space: "LPS" or "RAS".
        path: the file it was read from, if any.
    """

    array: np.ndarray
    ijk_to_space: np.ndarray
    space: str = "LPS"
    path: Path | None = None

    def __post_init__(self) -> None:
        self.space = check_space(self.space)
        self.ijk_to_space = np.asarray(self.ijk_to_space, dtype=np.float64)

    @classmethod
    def from_geometry(
        cls,
        array: np.ndarray,
        spacing=(1.0, 1.0, 1.0),
        origin=(0.0, 0.0, 0.0),
        directions=np.eye(3),
        space: str = "LPS",
    ) -> "Volume":
        """Build from spacing ``(3,)`` mm, origin ``(3,)`` mm (centre of voxel 0,0,0) and a
        ``(3, 3)`` direction matrix whose columns are the unit i, j, k axes."""
        M = np.eye(4)
        M[:3, :3] = np.asarray(directions, dtype=np.float64) * np.asarray(spacing, dtype=np.float64)
        M[:3, 3] = origin
        return cls(np.asarray(array), M, space)

    @property
    def spacing(self) -> np.ndarray:
        """``(3,)`` voxel size in mm along i, j, k."""
        return np.linalg.norm(self.ijk_to_space[:3, :3], axis=0)

    @property
    def origin(self) -> np.ndarray:
        """``(3,)`` position in mm of the centre of voxel (0, 0, 0)."""
        return self.ijk_to_space[:3, 3].copy()

    @property
    def directions(self) -> np.ndarray:
        """``(3, 3)`` unit column vectors of the i, j, k axes in ``space``."""
        return self.ijk_to_space[:3, :3] / self.spacing

    def in_space(self, space: str) -> "Volume":
        """The same volume with its geometry expressed in ``space`` (voxels unchanged)."""
        space = check_space(space)
        return replace(self, ijk_to_space=space_change(self.space, space) @ self.ijk_to_space,
                       space=space)


@dataclass
class Segment:
    """One segment of a segmentation: where it lives (layer, label value) and how it is called."""

    name: str
    label_value: int
    layer: int = 0
    id: str = ""
    color: tuple[float, float, float] = (0.9, 0.85, 0.7)

    def __post_init__(self) -> None:
        self.id = self.id or self.name


@dataclass
class Segmentation:
    """A multi-segment label map (3D Slicer ``.seg.nrrd`` or a plain label map).

    Attributes:
        layers: ``(L, I, J, K)`` integer label values; segments may share a layer (different
            label values) or overlap (different layers).
        ijk_to_space: ``(4, 4)`` voxel index -> ``space`` mm, shared by all layers.
        space: "LPS" or "RAS".
        segments: the named segments, in file order.
        path: the file it was read from, if any.
    """

    layers: np.ndarray
    ijk_to_space: np.ndarray
    space: str = "LPS"
    segments: list[Segment] = field(default_factory=list)
    path: Path | None = None

    def __post_init__(self) -> None:
        self.space = check_space(self.space)
        self.ijk_to_space = np.asarray(self.ijk_to_space, dtype=np.float64)
        if self.layers.ndim == 3:
            self.layers = self.layers[np.newaxis]

    @classmethod
    def from_labelmap(cls, volume: Volume) -> "Segmentation":
        """One segment per non-zero label value of an integer label map, named "Label <v>"."""
        labels = np.asarray(volume.array)
        values = [int(v) for v in np.unique(labels) if v != 0]
        segments = [Segment(name=f"Label {v}", label_value=v, id=f"Label_{v}") for v in values]
        return cls(labels[np.newaxis], volume.ijk_to_space, volume.space, segments, volume.path)

    def find_segment(self, *, name: str | None = None, label: int | None = None) -> Segment:
        """The segment with this name (or id), or with this label value in a single-layer map.

        With neither given, the only segment; raises :class:`LabelNotFoundError` when there is no
        match or the choice is ambiguous.
        """
        where = f" in '{self.path}'" if self.path else ""
        listing = ", ".join(f"'{s.name}' (label {s.label_value}, layer {s.layer})"
                            for s in self.segments) or "none"
        if name is not None:
            for seg in self.segments:
                if name in (seg.name, seg.id):
                    return seg
            raise LabelNotFoundError(f"There is no segment named '{name}'{where}.",
                                     f"Segments present: {listing}.")
        if label is not None:
            matches = [s for s in self.segments if s.label_value == int(label)]
            if len(matches) == 1:
                return matches[0]
            if not matches:
                raise LabelNotFoundError(f"No segment has label value {label}{where}.",
                                         f"Segments present: {listing}.")
            raise LabelNotFoundError(
                f"Label value {label} is used by {len(matches)} segments in different layers{where}.",
                "Choose the segment by name instead (--segment NAME).")
        if len(self.segments) == 1:
            return self.segments[0]
        if not self.segments:
            raise EmptyMaskError(f"The segmentation{where} contains no labelled voxels.",
                                 "Check that the right file was exported.")
        raise LabelNotFoundError(
            f"The segmentation{where} has {len(self.segments)} segments; which one is the bone?",
            f"Choose one with --segment NAME or --label N. Segments present: {listing}.")

    def mask(self, segment: Segment) -> np.ndarray:
        """``(I, J, K)`` boolean mask of ``segment``; raises :class:`EmptyMaskError` if empty."""
        mask = self.layers[segment.layer] == segment.label_value
        if not mask.any():
            raise EmptyMaskError(
                f"Segment '{segment.name}' (label {segment.label_value}) has no voxels.",
                "Pick a segment that is painted, or fix the segmentation.")
        return mask

    def geometry(self, array: np.ndarray) -> Volume:
        """A :class:`Volume` holding ``array`` ``(I, J, K)`` on this segmentation's grid."""
        return Volume(array, self.ijk_to_space.copy(), self.space, self.path)


# --------------------------------------------------------------------------------------------
# Readers and writers
# --------------------------------------------------------------------------------------------

log = logging.getLogger(__name__)

#: Extensions :func:`read_volume` accepts; :func:`write_volume` writes all but ``.nhdr``.
VOLUME_READ_EXTENSIONS = [".nrrd", ".nhdr", ".mha", ".mhd"]
VOLUME_WRITE_EXTENSIONS = [".nrrd", ".mha", ".mhd"]
#: Extensions :func:`read_segmentation` accepts (Slicer segmentations or plain label maps).
SEGMENTATION_READ_EXTENSIONS = [".seg.nrrd", *VOLUME_READ_EXTENSIONS]
SEGMENTATION_WRITE_EXTENSIONS = [".seg.nrrd", ".nrrd"]

# numpy dtype code -> MetaImage ElementType (what we write); bool is stored as uint8.
_MET_TYPES = {"i1": "MET_CHAR", "u1": "MET_UCHAR", "i2": "MET_SHORT", "u2": "MET_USHORT",
              "i4": "MET_INT", "u4": "MET_UINT", "i8": "MET_LONG_LONG", "u8": "MET_ULONG_LONG",
              "f4": "MET_FLOAT", "f8": "MET_DOUBLE"}
# MetaImage ElementType -> numpy dtype code (what we read). MetaIO's MET_LONG is 4 bytes.
_MET_DTYPES = {**{v: k for k, v in _MET_TYPES.items()}, "MET_ASCII_CHAR": "i1",
               "MET_LONG": "i4", "MET_ULONG": "u4"}

_NRRD_SPACE_NAMES = {"LPS": "left-posterior-superior", "RAS": "right-anterior-superior"}
_SEGMENT_KEY = re.compile(r"^Segment(\d+)_(\w+)$")


# ---- shared helpers -------------------------------------------------------------------------


def _grid_matrix(path: Path, axes: np.ndarray, origin) -> np.ndarray:
    """``(4, 4)`` ijk -> space from ``axes`` ``(3, 3)`` (row n = mm step of one voxel along axis
    n, the layout of both NRRD 'space directions' and MetaImage 'TransformMatrix' x spacing) and
    ``origin`` ``(3,)`` mm (centre of voxel 0, 0, 0)."""
    axes = np.asarray(axes, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    if axes.shape != (3, 3) or origin.shape != (3,):
        raise CorruptFileError(path, f"the grid geometry has axes of shape {axes.shape} and an "
                                     f"origin of shape {origin.shape}, expected (3, 3) and (3,)")
    if not (np.isfinite(axes).all() and np.isfinite(origin).all()):
        raise CorruptFileError(path, "the voxel spacing, directions or origin are not finite")
    if abs(np.linalg.det(axes)) < 1e-12 * max(1.0, np.abs(axes).max() ** 3):
        raise CorruptFileError(path, "the voxel axes are degenerate (zero spacing or parallel "
                                     f"directions): {axes.tolist()}")
    M = np.eye(4)
    M[:3, :3] = axes.T
    M[:3, 3] = origin
    return M


def _grid_axes(ijk_to_space: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`_grid_matrix`: ``(axes (3, 3), origin (3,))`` of a ``(4, 4)`` matrix."""
    return ijk_to_space[:3, :3].T.copy(), ijk_to_space[:3, 3].copy()


def _storable(array: np.ndarray, fmt: str) -> np.ndarray:
    """``array`` as little-endian with a type every reader knows (bool -> uint8)."""
    array = np.asarray(array)
    if array.dtype == np.bool_:
        array = array.astype(np.uint8)
    code = array.dtype.str[1:]
    if code not in _MET_TYPES:
        raise TypeError(f"Cannot write voxels of type {array.dtype} to {fmt}; "
                        f"use one of {sorted(_MET_TYPES)}.")
    return array.astype(array.dtype.newbyteorder("<"), copy=False)


@contextlib.contextmanager
def _parsing(path: Path) -> Iterator[None]:
    """Turn low-level parse failures (pynrrd, zlib, numpy, bad numbers) into
    :class:`CorruptFileError` naming ``path`` and the original detail."""
    try:
        yield
    except ComRegError:
        raise
    except FileNotFoundError as exc:
        raise InputFileNotFoundError(exc.filename or path, "data file named by the header") from exc
    except StopIteration as exc:  # pynrrd on an empty or header-only file
        raise CorruptFileError(path, "the file ends inside its header") from exc
    except (nrrd.NRRDError, zlib.error, OSError, EOFError, ValueError, KeyError, IndexError,
            TypeError) as exc:
        raise CorruptFileError(path, f"{type(exc).__name__}: {str(exc).rstrip('.')}") from exc


def _refuse_sequence(path: Path, keys) -> None:
    """Raise if header ``keys`` are those of a PLUS tracked-ultrasound sequence (a stack of 2D
    frames with per-frame poses, whose third axis is time, not space)."""
    if any(str(key).startswith("Seq_Frame") for key in keys):
        raise ComRegError(f"'{path}' is a tracked ultrasound sequence (2D frames over time), "
                          "not a 3D volume.",
                          "Reconstruct a volume from it first, or read it as an ultrasound "
                          "sequence.")


def _as_volume_array(path: Path, array: np.ndarray, list_kind: str, is_segmentation: bool):
    """A ``(I, J, K)`` array from a 3D array or a 4D one with a single non-spatial component."""
    if array.ndim == 3:
        return array
    if array.shape[0] == 1:
        return array[0]
    if is_segmentation:
        hint = ("It is a 3D Slicer segmentation with several layers; read it as a segmentation "
                "(read_segmentation), not as a volume.")
    else:
        hint = "Export one 3D scalar volume (a single component, frame or channel) instead."
    raise ComRegError(f"'{path}' holds {array.shape[0]} values per voxel (a non-spatial "
                      f"'{list_kind}' axis), not a single 3D scalar volume.", hint)


# ---- NRRD -----------------------------------------------------------------------------------


def _read_nrrd(path: Path) -> tuple[np.ndarray, dict, np.ndarray, str, str]:
    """Read a NRRD file with full 3D geometry.

    Returns ``(array, header, ijk_to_space, space, list_kind)``: ``array`` is ``(I, J, K)``, or
    ``(L, I, J, K)`` when the file has one non-spatial axis (moved first, of kind ``list_kind``).
    NRRD's 'space origin' is the centre of the first sample whatever the axis centering
    ('cell' or 'node'), which is already our convention, so centering needs no shift.
    """
    with _parsing(path):
        array, header = nrrd.read(str(path), index_order="F")
    _refuse_sequence(path, header)
    required = ("space", "space directions", "space origin")
    missing = [name for name in required if name not in header]
    if missing == ["space"] and "space dimension" in header:
        raise ComRegError(
            f"'{path}' gives its geometry in an unnamed space ('space dimension' without "
            "'space'), so ComReg cannot tell whether it is LPS or RAS.",
            "Save it from 3D Slicer or ITK, which write 'space: left-posterior-superior'.")
    if missing:
        raise MissingSpatialMetadataError(path, "no " + ", ".join(f"'{m}'" for m in missing))
    try:
        space = check_space(header["space"])
    except ComRegError:
        raise ComRegError(
            f"'{path}' is in the NRRD space '{header['space']}'; ComReg reads only patient "
            "spaces LPS (left-posterior-superior) and RAS (right-anterior-superior).",
            "Resample or save the volume in patient coordinates (e.g. from 3D Slicer).") from None
    with _parsing(path):
        directions = np.asarray(header["space directions"], dtype=np.float64)
        origin = np.asarray(header["space origin"], dtype=np.float64)
    if directions.ndim != 2 or directions.shape != (array.ndim, 3):
        raise CorruptFileError(path, f"'space directions' has shape {directions.shape} for a "
                                     f"{array.ndim}D array in 3D space")
    kinds = header.get("kinds") or ["domain"] * array.ndim
    spatial = [ax for ax in range(array.ndim) if not np.isnan(directions[ax]).any()]
    other = [ax for ax in range(array.ndim) if ax not in spatial]
    if len(spatial) != 3 or len(other) > 1:
        raise ComRegError(
            f"'{path}' has {len(spatial)} spatial and {len(other)} non-spatial axes "
            f"(kinds {' '.join(kinds)}); ComReg needs a 3D volume, optionally with one "
            "list of layers.", "Export a plain 3D volume or a 3D Slicer segmentation.")
    ijk_to_space = _grid_matrix(path, directions[spatial], origin)
    list_kind = ""
    if other:
        list_kind = kinds[other[0]] if other[0] < len(kinds) else "none"
        array = np.moveaxis(array, other[0], 0)
    return array, header, ijk_to_space, space, list_kind


def _write_nrrd(path: Path, array: np.ndarray, ijk_to_space: np.ndarray, space: str, *,
                compress: bool, extra: dict | None = None) -> None:
    """Write ``array`` ``(I, J, K)`` or ``(L, I, J, K)`` (a leading list axis) atomically."""
    array = _storable(array, "NRRD")
    axes, origin = _grid_axes(ijk_to_space)
    n_list = array.ndim - 3
    header = {
        "dimension": array.ndim,
        "space": _NRRD_SPACE_NAMES[check_space(space)],
        "space directions": np.vstack([np.full((n_list, 3), np.nan), axes]),
        "kinds": ["list"] * n_list + ["domain"] * 3,
        "endian": "little",
        "encoding": "gzip" if compress else "raw",
        "space origin": origin,
        **(extra or {}),
    }
    with atomic_output(path) as tmp:
        nrrd.write(str(tmp), array, header, index_order="F", compression_level=6)


# ---- MetaImage --------------------------------------------------------------------------------


def read_metaimage_header(path: str | Path) -> tuple[dict[str, str], int]:
    """Parse a MetaImage (``.mha``/``.mhd``, also PLUS ``.igs.mha``) header.

    Returns ``(fields, data_offset)``: every ``Key = Value`` line as strings in file order
    (unknown custom fields kept verbatim, values stripped) up to and including
    ``ElementDataFile``, and the byte offset where the data that follow it start.
    """
    path = require_input_file(path)
    fields: dict[str, str] = {}
    with open(path, "rb") as fh:
        for line_no in itertools.count(1):
            raw = fh.readline(65536)
            if not raw:
                raise CorruptFileError(path, "the MetaImage header has no 'ElementDataFile' line "
                                             "(the file is empty, truncated or not a MetaImage)")
            text = raw.decode("latin-1").rstrip("\r\n")
            if not text.strip():
                continue
            key, sep, value = text.partition("=")
            key = key.strip()
            if not sep or not re.fullmatch(r"[A-Za-z_][\w.\-]*", key) \
                    or not value.replace("\t", " ").isprintable():
                raise CorruptFileError(path, f"header line {line_no} is not 'Key = Value': "
                                             f"{text[:60]!r}")
            fields[key] = value.strip()
            if key.lower() == "elementdatafile":
                return fields, fh.tell()
    raise AssertionError("unreachable")


def _field(fields: dict[str, str], *names: str) -> str | None:
    """The value of the first of ``names`` present (case-insensitive), else None."""
    lower = {k.lower(): v for k, v in fields.items()}
    for name in names:
        if name.lower() in lower:
            return lower[name.lower()]
    return None


def _numbers(path: Path, fields: dict[str, str], names: tuple[str, ...], count: int,
             dtype=float) -> np.ndarray | None:
    """The ``count`` numbers of the first present field of ``names``, or None if absent."""
    value = _field(fields, *names)
    if value is None:
        return None
    try:
        numbers = np.array([dtype(v) for v in value.split()])
    except ValueError:
        numbers = np.array([])
    if numbers.size != count:
        raise CorruptFileError(path, f"'{names[0]} = {value}' should hold {count} numbers")
    return numbers


def _is_true(fields: dict[str, str], *names: str) -> bool:
    return (_field(fields, *names) or "False").strip().lower() in ("true", "1")


def _read_metaimage(path: Path) -> tuple[np.ndarray, dict[str, str], np.ndarray]:
    """Read a 3D MetaImage: ``(array (C, I, J, K), fields, ijk_to_space in LPS)``.

    ITK MetaImages are always LPS; 'AnatomicalOrientation' only names the closest axis letters
    of the direction matrix ("RAI" = identity), so it is kept in ``fields`` but not used.
    """
    fields, offset = read_metaimage_header(path)
    _refuse_sequence(path, fields)
    ndims = _numbers(path, fields, ("NDims",), 1, int)
    if ndims is None or int(ndims[0]) != 3:
        raise ComRegError(f"'{path}' is a {int(ndims[0]) if ndims is not None else '?'}D "
                          "MetaImage; ComReg needs a 3D volume.", "Export the 3D volume.")
    dims = _numbers(path, fields, ("DimSize",), 3, int)
    if dims is None or (dims < 1).any():
        raise CorruptFileError(path, f"'DimSize = {_field(fields, 'DimSize')}' is not 3 sizes")
    element_type = (_field(fields, "ElementType") or "").upper()
    if element_type not in _MET_DTYPES:
        raise CorruptFileError(path, f"unsupported or missing 'ElementType = {element_type}'")
    msb = _is_true(fields, "BinaryDataByteOrderMSB", "ElementByteOrderMSB")
    dtype = np.dtype(_MET_DTYPES[element_type]).newbyteorder(">" if msb else "<")
    channels = _numbers(path, fields, ("ElementNumberOfChannels",), 1, int)
    channels = 1 if channels is None else int(channels[0])

    directions = _numbers(path, fields, ("TransformMatrix", "Rotation", "Orientation"), 9)
    origin = _numbers(path, fields, ("Offset", "Origin", "Position"), 3)
    spacing = _numbers(path, fields, ("ElementSpacing", "ElementSize"), 3)
    if directions is None and origin is None and spacing is None:
        raise MissingSpatialMetadataError(path, "no 'ElementSpacing', 'Offset' or "
                                                "'TransformMatrix'")
    # Absent single fields take MetaIO's defaults (identity, origin 0, spacing 1).
    if directions is None or origin is None or spacing is None:
        log.debug("%s: MetaIO defaults for missing geometry fields (directions %s, origin %s, "
                  "spacing %s)", path, directions, origin, spacing)
    directions = np.eye(3) if directions is None else directions.reshape(3, 3)
    spacing = np.ones(3) if spacing is None else spacing
    ijk_to_space = _grid_matrix(path, directions * spacing[:, None],
                                np.zeros(3) if origin is None else origin)

    expected = int(np.prod(dims)) * channels * dtype.itemsize
    data = _read_metaimage_data(path, fields, offset, expected)
    with _parsing(path):
        if _is_true(fields, "BinaryData") or _field(fields, "BinaryData") is None:
            flat = np.frombuffer(data, dtype)
        else:
            flat = np.array(data.decode("latin-1").split(), dtype=dtype)
        array = flat.reshape((channels, *dims), order="F").astype(dtype.newbyteorder("="))
    return array, fields, ijk_to_space


def _read_metaimage_data(path: Path, fields: dict[str, str], offset: int, expected: int) -> bytes:
    """The (decompressed) voxel bytes of a MetaImage; checks their length is ``expected``."""
    data_file = _field(fields, "ElementDataFile") or ""
    compressed = _is_true(fields, "CompressedData")
    with _parsing(path):
        if data_file.upper() == "LOCAL":
            with open(path, "rb") as fh:
                fh.seek(offset)
                data = fh.read()
        else:
            if data_file.upper() == "LIST" or len(data_file.split()) != 1:
                raise ComRegError(f"'{path}' stores its voxels in several files "
                                  f"('ElementDataFile = {data_file}').",
                                  "Save the volume as a single .mha file.")
            data_path = require_input_file(path.parent / data_file, "MetaImage data file")
            data = data_path.read_bytes()
            skip = int(_field(fields, "HeaderSize") or 0)
            if skip == -1 and not compressed:
                skip = max(len(data) - expected, 0)
            data = data[max(skip, 0):]
        if compressed:
            inflater = zlib.decompressobj(zlib.MAX_WBITS | 32)  # zlib or gzip stream
            raw = inflater.decompress(data) + inflater.flush()
            if not inflater.eof:
                raise CorruptFileError(path, f"the compressed voxel data end early "
                                             f"({len(raw)} of {expected} bytes recovered)")
            data = raw
    if len(data) != expected:
        raise CorruptFileError(
            path, f"'DimSize = {_field(fields, 'DimSize')}' and '{_field(fields, 'ElementType')}'"
                  f" need {expected} bytes of voxel data but the file holds {len(data)}")
    return data


def _orientation_code(directions: np.ndarray) -> str:
    """ITK's 'AnatomicalOrientation' letters for ``(3, 3)`` LPS column directions ("RAI" for
    the identity: each letter is the side an axis comes *from*)."""
    letters = ("RL", "AP", "IS")
    code = ""
    for column in directions.T:
        c = int(np.argmax(np.abs(column)))
        code += letters[c][0 if column[c] > 0 else 1]
    return code


def _format_numbers(values) -> str:
    """Space-separated shortest round-trip text of floats (``repr``)."""
    return " ".join(repr(float(v)) for v in np.ravel(values))


def _write_metaimage(volume: "Volume", path: Path, ext: str, compress: bool) -> None:
    """Write ``volume`` as ``.mha`` (inline data) or ``.mhd`` + ``.raw``/``.zraw``, in LPS."""
    lps = volume.in_space("LPS")
    array = _storable(lps.array, "MetaImage")
    axes, origin = _grid_axes(lps.ijk_to_space)
    spacing = np.linalg.norm(axes, axis=1)
    directions = axes / spacing[:, None]  # rows = unit axis vectors, MetaImage's TransformMatrix
    data = array.tobytes(order="F")
    if compress:
        data = zlib.compress(data, 6)
    data_name = "LOCAL" if ext == ".mha" else path.name[: -len(ext)] + (".zraw" if compress
                                                                         else ".raw")
    fields = {
        "ObjectType": "Image",
        "NDims": "3",
        "BinaryData": "True",
        "BinaryDataByteOrderMSB": "False",
        "CompressedData": str(compress),
        **({"CompressedDataSize": str(len(data))} if compress else {}),
        "TransformMatrix": _format_numbers(directions),
        "Offset": _format_numbers(origin),
        "CenterOfRotation": "0 0 0",
        "AnatomicalOrientation": _orientation_code(directions.T),
        "ElementSpacing": _format_numbers(spacing),
        "DimSize": " ".join(str(n) for n in array.shape),
        "ElementType": _MET_TYPES[array.dtype.str[1:]],
        "ElementDataFile": data_name,
    }
    header = "".join(f"{k} = {v}\n" for k, v in fields.items()).encode("ascii")
    if ext == ".mha":
        with atomic_output(path) as tmp:
            tmp.write_bytes(header + data)
        return
    with atomic_output(path.with_name(data_name)) as tmp_data, atomic_output(path) as tmp_header:
        tmp_data.write_bytes(data)
        tmp_header.write_bytes(header)


# ---- public API -------------------------------------------------------------------------------


def read_volume(path: str | Path) -> Volume:
    """Read a 3D scalar volume from ``.nrrd``/``.nhdr`` (LPS or RAS, kept as stored) or
    ``.mha``/``.mhd`` (always LPS). Voxels keep their file type; ``array`` is ``(I, J, K)``."""
    ext = require_extension(path, "volume", VOLUME_READ_EXTENSIONS)
    path = require_input_file(path, "volume file")
    if ext in (".nrrd", ".nhdr"):
        array, header, ijk_to_space, space, list_kind = _read_nrrd(path)
        is_seg = any(_SEGMENT_KEY.match(key) for key in header)
        return Volume(_as_volume_array(path, array, list_kind, is_seg), ijk_to_space, space, path)
    array, _, ijk_to_space = _read_metaimage(path)
    return Volume(_as_volume_array(path, array, "channels", False), ijk_to_space, "LPS", path)


def write_volume(volume: Volume, path: str | Path, *, compress: bool = True) -> Path:
    """Write ``volume`` to ``.nrrd`` (gzip or raw encoding, in the volume's space) or
    ``.mha``/``.mhd`` (zlib-compressed or raw, converted to LPS). Atomic; returns the path."""
    ext = require_extension(path, "volume", VOLUME_WRITE_EXTENSIONS)
    path = Path(path)
    if np.ndim(volume.array) != 3:
        raise ValueError(f"A volume array must be (I, J, K), got shape {np.shape(volume.array)}.")
    if ext == ".nrrd":
        _write_nrrd(path, volume.array, volume.ijk_to_space, volume.space, compress=compress)
    else:
        _write_metaimage(volume, path, ext, compress)
    return path


def read_segmentation(path: str | Path) -> Segmentation:
    """Read a 3D Slicer ``.seg.nrrd`` (3D, or 4D with a leading list of layers) or a plain
    integer label map (``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd``; one segment per label value).

    Slicer files without ``Segment{i}_Layer``/``_LabelValue`` fields are the legacy layout
    (segment i in layer i, label value 1) when there is one layer per segment, else segment i is
    label value i+1 in layer 0. A ``.seg.nrrd`` without any ``Segment{i}_*`` field is read as a
    label map: one segment per non-zero value (and layer).
    """
    ext = require_extension(path, "segmentation", SEGMENTATION_READ_EXTENSIONS)
    path = require_input_file(path, "segmentation file")
    if ext in (".seg.nrrd", ".nrrd", ".nhdr"):
        array, header, ijk_to_space, space, list_kind = _read_nrrd(path)
        if any(_SEGMENT_KEY.match(key) for key in header):
            _require_labels(path, array)
            layers = array if array.ndim == 4 else array[np.newaxis]
            with _parsing(path):
                segments = _slicer_segments(header, len(layers))
            return Segmentation(layers, ijk_to_space, space, segments, path)
        if ext == ".seg.nrrd" and array.ndim == 4:  # layers without segment fields
            _require_labels(path, array)
            segments = [Segment(f"Layer {layer} label {int(v)}", int(v), layer,
                                f"Layer_{layer}_Label_{int(v)}")
                        for layer in range(len(array)) for v in np.unique(array[layer]) if v]
            return Segmentation(array, ijk_to_space, space, segments, path)
        # a .seg.nrrd without Slicer's segment fields is a plain label map: a segment per value
        volume = Volume(_as_volume_array(path, array, list_kind, False), ijk_to_space, space,
                        path)
    else:
        volume = read_volume(path)
    _require_labels(path, volume.array)
    return Segmentation.from_labelmap(volume)


def write_segmentation(seg: Segmentation, path: str | Path, *, compress: bool = True) -> Path:
    """Write ``seg`` as a 3D Slicer ``.seg.nrrd``: 3D for one layer, else 4D with a leading
    list axis, with Slicer's ``Segment{i}_*`` fields. Atomic; returns the path."""
    require_extension(path, "segmentation", SEGMENTATION_WRITE_EXTENSIONS)
    path = Path(path)
    layers = np.asarray(seg.layers)
    if layers.ndim != 4:
        raise ValueError(f"Segmentation layers must be (L, I, J, K), got shape {layers.shape}.")
    if layers.dtype.kind not in "biu":
        raise TypeError(f"Segmentation layers must be integers, got {layers.dtype}.")
    layers = layers.astype(_smallest_label_type(layers), copy=False)
    extra: dict[str, str] = {}
    for i, segment in enumerate(seg.segments):
        for text in (segment.name, segment.id):
            if not text.isascii() or not text.isprintable():
                raise ComRegError(f"Segment name or id {text!r} has characters a NRRD header "
                                  "cannot hold.", "Use printable ASCII names.")
        extra.update({
            f"Segment{i}_Color": _format_numbers(segment.color),
            f"Segment{i}_ColorAutoGenerated": "0",
            f"Segment{i}_Extent": _extent(layers[segment.layer] == segment.label_value),
            f"Segment{i}_ID": segment.id,
            f"Segment{i}_LabelValue": str(int(segment.label_value)),
            f"Segment{i}_Layer": str(int(segment.layer)),
            f"Segment{i}_Name": segment.name,
            f"Segment{i}_NameAutoGenerated": "0",
            f"Segment{i}_Tags": "",
        })
    extra.update({
        "Segmentation_ContainedRepresentationNames": "Binary labelmap|",
        "Segmentation_MasterRepresentation": "Binary labelmap",
        "Segmentation_ReferenceImageExtentOffset": "0 0 0",
    })
    data = layers[0] if len(layers) == 1 else layers
    _write_nrrd(path, data, seg.ijk_to_space, seg.space, compress=compress, extra=extra)
    return path


# ---- segmentation helpers ---------------------------------------------------------------------


def _require_labels(path: Path, array: np.ndarray) -> None:
    """Raise unless ``array`` looks like a label map (integers, none negative)."""
    hint = "This looks like an intensity CT, not a label map; segment the bone first."
    if array.dtype.kind not in "biu":
        raise ComRegError(f"'{path}' has {array.dtype} voxels, not integer labels.", hint)
    if array.dtype.kind == "i" and array.size and array.min() < 0:
        raise ComRegError(f"'{path}' has negative voxel values (down to {array.min()}), which "
                          "a label map never has.", hint)


def _slicer_segments(header: dict, n_layers: int) -> list[Segment]:
    """The segments described by Slicer's ``Segment{i}_*`` header fields, in index order."""
    per_index: dict[int, dict[str, str]] = {}
    for key, value in header.items():
        match = _SEGMENT_KEY.match(key)
        if match:
            per_index.setdefault(int(match[1]), {})[match[2]] = str(value).strip()
    legacy = len(per_index) > 1 and n_layers == len(per_index)
    segments = []
    for n, (i, meta) in enumerate(sorted(per_index.items())):
        layer = int(meta.get("Layer", n if legacy else 0))
        label = int(meta.get("LabelValue", 1 if legacy else n + 1))
        color = tuple(float(c) for c in meta.get("Color", "").split()) or None
        segments.append(Segment(
            name=meta.get("Name") or meta.get("ID") or f"Segment_{i}", label_value=label,
            layer=layer, id=meta.get("ID", ""),
            **({"color": color} if color and len(color) == 3 else {})))
    return segments


def _extent(mask: np.ndarray) -> str:
    """Slicer's "i0 i1 j0 j1 k0 k1" bounding box of a ``(I, J, K)`` mask ("0 -1 ..." if empty)."""
    if not mask.any():
        return "0 -1 0 -1 0 -1"
    bounds = []
    for axis in range(3):
        hits = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
        bounds += [int(hits[0]), int(hits[-1])]
    return " ".join(str(b) for b in bounds)


def _smallest_label_type(layers: np.ndarray) -> np.dtype:
    """The smallest unsigned type holding all labels (Slicer does the same), else int32/64."""
    if layers.size == 0:
        return np.dtype(np.uint8)
    low, high = int(layers.min()), int(layers.max())
    for dtype in (np.uint8, np.uint16, np.uint32) if low >= 0 else (np.int8, np.int16, np.int32):
        info = np.iinfo(dtype)
        if info.min <= low and high <= info.max:
            return np.dtype(dtype)
    return np.dtype(np.int64)
