"""MetaImage files (``.mha``, ``.mhd`` + data file; also the header and voxels of PLUS
``.igs.mha`` sequences): header fields, voxel data, 3D grids read and written atomically. ITK
MetaImages are always LPS. Geometry conventions: see :mod:`comreg_core.io.volumes`.
"""

from __future__ import annotations

import itertools
import logging
import re
import zlib
from pathlib import Path

import numpy as np

from comreg_core.errors import ComRegError, CorruptFileError, MissingSpatialMetadataError
from comreg_core.io._files import atomic_output, parse_numbers, require_input_file
from comreg_core.io.image_files import (STORABLE_DTYPE_CODES, format_numbers, grid_axes,
                                        grid_matrix, parse_errors_as_corrupt,
                                        refuse_tracked_sequence, storable_array)

log = logging.getLogger(__name__)

#: numpy dtype code -> MetaImage ElementType, for the types ComReg writes.
METAIMAGE_ELEMENT_TYPES = dict(zip(STORABLE_DTYPE_CODES, (
    "MET_CHAR", "MET_UCHAR", "MET_SHORT", "MET_USHORT", "MET_INT", "MET_UINT", "MET_LONG_LONG",
    "MET_ULONG_LONG", "MET_FLOAT", "MET_DOUBLE")))
#: MetaImage ElementType -> numpy dtype code, for reading. MetaIO's MET_LONG is 4 bytes.
METAIMAGE_DTYPES = {**{v: k for k, v in METAIMAGE_ELEMENT_TYPES.items()},
                    "MET_ASCII_CHAR": "i1", "MET_LONG": "i4", "MET_ULONG": "u4"}


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


def header_field(fields: dict[str, str], *names: str) -> str | None:
    """The value of the first of ``names`` present (case-insensitive), else None."""
    lower = {k.lower(): v for k, v in fields.items()}
    for name in names:
        if name.lower() in lower:
            return lower[name.lower()]
    return None


def header_numbers(path: Path, fields: dict[str, str], names: tuple[str, ...], count: int,
                   dtype=float) -> np.ndarray | None:
    """The ``count`` numbers of the first present field of ``names``, or None if absent."""
    value = header_field(fields, *names)
    if value is None:
        return None
    numbers = parse_numbers(value, count, dtype)
    if numbers is None:
        raise CorruptFileError(path, f"'{names[0]} = {value}' should hold {count} numbers")
    return numbers


def metaimage_dtype(path: Path, fields: dict[str, str]) -> np.dtype:
    """The voxel type of a MetaImage header (``ElementType`` and its byte order)."""
    element_type = (header_field(fields, "ElementType") or "").upper()
    if element_type not in METAIMAGE_DTYPES:
        raise CorruptFileError(path, f"unsupported or missing 'ElementType = {element_type}'")
    msb = header_flag(fields, "BinaryDataByteOrderMSB", "ElementByteOrderMSB")
    return np.dtype(METAIMAGE_DTYPES[element_type]).newbyteorder(">" if msb else "<")


def header_flag(fields: dict[str, str], *names: str) -> bool:
    """True when the first of ``names`` present says "True" or "1" (absent = False)."""
    return (header_field(fields, *names) or "False").strip().lower() in ("true", "1")


def read_metaimage_grid(path: Path) -> tuple[np.ndarray, dict[str, str], np.ndarray]:
    """Read a 3D MetaImage: ``(array (C, I, J, K), fields, ijk_to_space in LPS)``.

    ITK MetaImages are always LPS; 'AnatomicalOrientation' only names the closest axis letters
    of the direction matrix ("RAI" = identity), so it is kept in ``fields`` but not used.
    """
    fields, offset = read_metaimage_header(path)
    refuse_tracked_sequence(path, fields)
    ndims = header_numbers(path, fields, ("NDims",), 1, int)
    if ndims is None or int(ndims[0]) != 3:
        raise ComRegError(f"'{path}' is a {int(ndims[0]) if ndims is not None else '?'}D "
                          "MetaImage; ComReg needs a 3D volume.", "Export the 3D volume.")
    dims = header_numbers(path, fields, ("DimSize",), 3, int)
    if dims is None or (dims < 1).any():
        raise CorruptFileError(path, f"'DimSize = {header_field(fields, 'DimSize')}' is not 3 "
                                     "sizes")
    dtype = metaimage_dtype(path, fields)
    channels = header_numbers(path, fields, ("ElementNumberOfChannels",), 1, int)
    channels = 1 if channels is None else int(channels[0])

    directions = header_numbers(path, fields, ("TransformMatrix", "Rotation", "Orientation"), 9)
    origin = header_numbers(path, fields, ("Offset", "Origin", "Position"), 3)
    spacing = header_numbers(path, fields, ("ElementSpacing", "ElementSize"), 3)
    if directions is None and origin is None and spacing is None:
        raise MissingSpatialMetadataError(path, "no 'ElementSpacing', 'Offset' or "
                                                "'TransformMatrix'")
    # Absent single fields take MetaIO's defaults (identity, origin 0, spacing 1).
    if directions is None or origin is None or spacing is None:
        log.debug("%s: MetaIO defaults for missing geometry fields (directions %s, origin %s, "
                  "spacing %s)", path, directions, origin, spacing)
    directions = np.eye(3) if directions is None else directions.reshape(3, 3)
    spacing = np.ones(3) if spacing is None else spacing
    ijk_to_space = grid_matrix(path, directions * spacing[:, None],
                                np.zeros(3) if origin is None else origin)

    expected = int(np.prod(dims)) * channels * dtype.itemsize
    data = read_metaimage_voxels(path, fields, offset, expected)
    with parse_errors_as_corrupt(path):
        if header_flag(fields, "BinaryData") or header_field(fields, "BinaryData") is None:
            flat = np.frombuffer(data, dtype)
        else:
            flat = np.array(data.decode("latin-1").split(), dtype=dtype)
        array = flat.reshape((channels, *dims), order="F").astype(dtype.newbyteorder("="))
    return array, fields, ijk_to_space


def read_metaimage_voxels(path: Path, fields: dict[str, str], offset: int,
                          expected: int) -> bytes:
    """The (decompressed) voxel bytes of a MetaImage; checks their length is ``expected``
    (a truncated file, or data file of a ``.mhd``, raises :class:`CorruptFileError` naming it)."""
    data_file = header_field(fields, "ElementDataFile") or ""
    compressed = header_flag(fields, "CompressedData")
    source, of = path, ""  # the file holding the voxels, for messages
    with parse_errors_as_corrupt(path):
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
            source, of = data_path, f" (the voxel data of '{path}')"
            data = data_path.read_bytes()
            skip = int(header_field(fields, "HeaderSize") or 0)
            if skip == -1 and not compressed:
                skip = max(len(data) - expected, 0)
            data = data[max(skip, 0):]
        if compressed:
            inflater = zlib.decompressobj(zlib.MAX_WBITS | 32)  # zlib or gzip stream
            raw = inflater.decompress(data) + inflater.flush()
            if not inflater.eof:
                raise CorruptFileError(source, f"the compressed voxel data end early "
                                               f"({len(raw)} of {expected} bytes recovered){of}")
            data = raw
    if len(data) != expected:
        raise CorruptFileError(
            source, f"'DimSize = {header_field(fields, 'DimSize')}' and "
                    f"'{header_field(fields, 'ElementType')}' need {expected} bytes of voxel data "
                    f"but the file holds {len(data)}{of}")
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


def write_metaimage_grid(path: Path, ext: str, array: np.ndarray, ijk_to_space: np.ndarray, *,
                         compress: bool) -> None:
    """Write ``array`` ``(I, J, K)`` on the LPS grid ``ijk_to_space`` ``(4, 4)`` atomically, as
    ``.mha`` (``ext``; inline data) or ``.mhd`` + ``.raw``/``.zraw`` (zlib when ``compress``)."""
    array = storable_array(array, "MetaImage")
    axes, origin = grid_axes(ijk_to_space)
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
        "TransformMatrix": format_numbers(directions),
        "Offset": format_numbers(origin),
        "CenterOfRotation": "0 0 0",
        "AnatomicalOrientation": _orientation_code(directions.T),
        "ElementSpacing": format_numbers(spacing),
        "DimSize": " ".join(str(n) for n in array.shape),
        "ElementType": METAIMAGE_ELEMENT_TYPES[array.dtype.str[1:]],
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
