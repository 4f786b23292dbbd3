"""Point clouds: XYZ (ASCII), PLY, PCD (ASCII, binary, binary_compressed) and NPY.

Coordinates are patient millimetres. ComReg writes a ``SPACE=LPS``/``SPACE=RAS`` comment into XYZ,
PLY and PCD files (as 3D Slicer does for models); files without it, and NPY files, are taken as
LPS.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from comreg_core.errors import CorruptFileError, InvalidGeometryError
from comreg_core.io._files import (atomic_output, require_extension, require_input_file,
                                   require_near_origin)
from comreg_core.transforms import apply_transform, as_points, check_space, space_change

POINT_CLOUD_EXTENSIONS = [".xyz", ".txt", ".csv", ".ply", ".pcd", ".npy"]
_SPACE_COMMENT = re.compile(r"SPACE=(RAS|LPS)", re.IGNORECASE)


@dataclass
class PointCloud:
    """Points in patient millimetres.

    Attributes:
        points: ``(N, 3)`` float64 coordinates in mm (N >= 1, all finite).
        space: "LPS" or "RAS".
        path: the file it was read from, if any.
        beam_origins: ``(N, 3)`` mm, where each point's ultrasound beam started (the probe's
            element, same space), or None. Kept by PLY files (vertex properties ``beam_x``,
            ``beam_y``, ``beam_z``); other formats hold the points only.
    """

    points: np.ndarray
    space: str = "LPS"
    path: Path | None = None
    beam_origins: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.space = check_space(self.space)
        where = f" in '{self.path}'" if self.path else ""
        self.points = as_points(self.points, f"points{where}")
        require_near_origin(self.points, f"points{where}")
        if len(self.points) == 0:
            raise InvalidGeometryError(f"The point cloud{where} is empty.",
                                       "Provide at least one point.")
        if self.beam_origins is not None:
            self.beam_origins = as_points(self.beam_origins, f"beam origins{where}")
            require_near_origin(self.beam_origins, f"beam origins{where}")
            if self.beam_origins.shape != self.points.shape:
                raise InvalidGeometryError(f"The point cloud{where} has "
                                           f"{len(self.beam_origins)} beam origins for "
                                           f"{len(self.points)} points.",
                                           "Give one beam origin per point, or none.")

    def in_space(self, space: str) -> "PointCloud":
        """The same points (and beam origins) expressed in ``space``."""
        space = check_space(space)
        change = space_change(self.space, space)
        return replace(self, points=apply_transform(change, self.points), space=space,
                       beam_origins=None if self.beam_origins is None
                       else apply_transform(change, self.beam_origins))


def read_points(path: str | Path) -> PointCloud:
    """Read a point cloud; a PLY or other mesh file gives its vertices.

    Raises InputFileNotFoundError, UnsupportedFormatError, CorruptFileError, InvalidGeometryError.
    """
    path = require_input_file(path, "point cloud file")
    ext = require_extension(path, "point cloud", POINT_CLOUD_EXTENSIONS)
    if ext == ".ply":
        points, space, origins = _read_ply_with_beams(path)
        return PointCloud(points, space, path, origins)
    reader = {".npy": _read_npy, ".pcd": _read_pcd}.get(ext, _read_xyz)
    points, space = reader(path)
    return PointCloud(points, space, path)


def write_points(cloud: PointCloud, path: str | Path, *, binary: bool = True) -> Path:
    """Write ``cloud`` atomically. PLY and PCD are binary unless ``binary=False``; XYZ is text with
    full float64 precision; NPY holds only the ``(N, 3)`` float64 array, always in LPS (a RAS
    cloud is converted). Returns the path."""
    path = Path(path)
    ext = require_extension(path, "point cloud", POINT_CLOUD_EXTENSIONS)
    writer = {".npy": _write_npy, ".ply": _write_ply, ".pcd": _write_pcd}.get(ext, _write_xyz)
    with atomic_output(path) as tmp:
        writer(cloud, tmp, binary)
    return path


# --- XYZ / TXT / CSV -------------------------------------------------------------------------

def _read_xyz(path: Path) -> tuple[np.ndarray, str]:
    text = path.read_text(encoding="utf-8", errors="replace")
    comments = "\n".join(line for line in text.splitlines() if line.lstrip().startswith("#"))
    match = _SPACE_COMMENT.search(comments)
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.replace(",", " ").split()
        try:
            values = [float(v) for v in fields[:3]]
        except ValueError:
            if not rows:  # a column-name header line such as "x,y,z"
                continue
            raise CorruptFileError(path, f"line {number} is not numeric: {line[:60]!r}") from None
        if len(values) < 3:
            raise CorruptFileError(path, f"line {number} has {len(values)} values, expected x y z")
        rows.append(values)
    if not rows:
        raise CorruptFileError(path, "it contains no x y z rows")
    return np.asarray(rows, dtype=np.float64), match.group(1).upper() if match else "LPS"


def _write_xyz(cloud: PointCloud, tmp: Path, binary: bool) -> None:
    header = f"ComReg point cloud, millimetres. SPACE={cloud.space}\nx y z"
    delimiter = "," if tmp.suffix == ".csv" else " "
    np.savetxt(tmp, cloud.points, fmt="%.17g", delimiter=delimiter, header=header)


# --- NPY ----------------------------------------------------------------------------------------

def _read_npy(path: Path) -> tuple[np.ndarray, str]:
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise CorruptFileError(path, f"not a valid .npy array ({exc})") from None
    if array.ndim != 2 or array.shape[1] < 3 or not np.issubdtype(array.dtype, np.number):
        raise CorruptFileError(path, f"expected a numeric (N, 3) array, found {array.dtype} "
                                     f"{array.shape}")
    return array[:, :3].astype(np.float64), "LPS"


def _write_npy(cloud: PointCloud, tmp: Path, binary: bool) -> None:
    with open(tmp, "wb") as f:  # NPY has no room for a space tag: always store LPS
        np.save(f, cloud.in_space("LPS").points)


# --- PLY ----------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _ply_header(path: Path) -> tuple[str, list[tuple[str, int, list]], list[str], int]:
    """``(format, elements, header lines, data offset)`` of a PLY file; each element is
    ``(name, count, properties)`` with properties ``(name, dtype code)`` or, for lists,
    ``(name, ("list", count dtype code, item dtype code))``. Checks that the file is large
    enough for the counts it declares (before anything is allocated)."""
    with open(path, "rb") as f:
        lines = _read_header_lines(f, path, end=b"end_header", first=b"ply")
        data_start = f.tell()
    fmt, elements = None, []
    for line in lines:
        words = line.split()
        if not words:
            continue
        if words[0] == "format" and len(words) > 1:
            fmt = words[1]
        elif words[0] == "element":
            try:
                count = int(words[2])
            except (IndexError, ValueError):
                raise CorruptFileError(path, f"bad PLY element line {line[:60]!r}") from None
            if count < 0:
                raise CorruptFileError(path, f"the PLY header declares {count} {words[1]}s")
            elements.append((words[1], count, []))
        elif words[0] == "property" and elements and len(words) >= 3:
            if words[1] == "list" and len(words) >= 5:
                kind = ("list", _PLY_TYPES.get(words[2], ""), _PLY_TYPES.get(words[3], ""))
                if not kind[1] or not kind[2]:
                    raise CorruptFileError(path, "unknown PLY property type")
                elements[-1][2].append((words[-1], kind))
            else:
                elements[-1][2].append((words[-1], _PLY_TYPES.get(words[1], "")))
    if fmt is None:
        raise CorruptFileError(path, "the PLY header has no 'format' line")
    needed = sum(count * _ply_min_record_bytes(props, fmt == "ascii")
                 for _, count, props in elements)
    available = path.stat().st_size - data_start
    if needed > available + 1:  # +1: an ASCII file may end without its last newline
        declared = ", ".join(f"'{e}' x {n:,}" for e, n, _ in elements)
        raise CorruptFileError(path, f"its header declares {declared}, which need at least "
                                     f"{needed:,} bytes, but only {available:,} follow it")
    return fmt, elements, lines, data_start


def _ply_min_record_bytes(props: list, ascii_format: bool) -> int:
    """The fewest bytes one record of these properties can take (an empty list for lists)."""
    if ascii_format:  # one character and one separator per value
        return 2 * len(props)
    return sum(np.dtype(kind[1]).itemsize if isinstance(kind, tuple) else
               np.dtype(kind or "u1").itemsize for _, kind in props)


def check_ply_size(path: str | Path) -> None:
    """Raise :class:`CorruptFileError` if a PLY file is shorter than its header's counts need
    (run before handing it to VTK, whose reader allocates what the header says)."""
    _ply_header(Path(path))


#: PLY vertex properties of the beam origins.
BEAM_PROPERTIES = ("beam_x", "beam_y", "beam_z")


def _read_ply(path: Path) -> tuple[np.ndarray, str]:
    """Vertices of a PLY file (faces, if any, are ignored)."""
    points, space, _ = _read_ply_with_beams(path)
    return points, space


def _read_ply_with_beams(path: Path) -> tuple[np.ndarray, str, np.ndarray | None]:
    """Vertices of a PLY file and their beam origins when it has them (faces are ignored)."""
    fmt, elements, header_lines, data_start = _ply_header(path)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise CorruptFileError(path, "the PLY header has no vertex element with x, y, z")
    if names.index("vertex") > 0:
        raise CorruptFileError(path, "elements before 'vertex' are not supported")
    _, vertex_count, vertex_props = elements[0]
    if any(isinstance(t, tuple) for _, t in vertex_props):
        raise CorruptFileError(path, "list properties on vertices are not supported")
    space = _space_from_comments(header_lines)
    names = [name for name, _ in vertex_props]
    if not {"x", "y", "z"} <= set(names):
        raise CorruptFileError(path, "the PLY header has no vertex element with x, y, z")
    if any(not t for _, t in vertex_props):
        raise CorruptFileError(path, "unknown PLY property type")
    if fmt == "ascii":
        with open(path, "rb") as f:
            f.seek(data_start)
            text = f.read().decode("ascii", errors="replace").split("\n")
        rows = [line.split() for line in text if line.strip()][:vertex_count]
        if len(rows) < vertex_count:
            raise CorruptFileError(path, f"expected {vertex_count} vertices, found {len(rows)}")
        try:
            table = np.asarray([[float(v) for v in row[:len(names)]] for row in rows])
        except ValueError:
            raise CorruptFileError(path, "non-numeric vertex values") from None
        if table.ndim != 2 or table.shape[1] != len(names):
            raise CorruptFileError(path, f"vertex rows do not hold {len(names)} values each")
        columns = {name: table[:, i] for i, name in enumerate(names)}
    else:
        order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
        if order is None:
            raise CorruptFileError(path, f"unknown PLY format '{fmt}'")
        dtype = np.dtype([(name, order + t) for name, t in vertex_props])
        columns = _read_binary_records(path, data_start, dtype, vertex_count)
    points = np.column_stack([columns["x"], columns["y"], columns["z"]]).astype(np.float64)
    origins = None
    if set(BEAM_PROPERTIES) <= set(names):
        origins = np.column_stack([columns[k] for k in BEAM_PROPERTIES]).astype(np.float64)
    return points, space, origins


def _write_ply(cloud: PointCloud, tmp: Path, binary: bool) -> None:
    fmt = "binary_little_endian" if binary else "ascii"
    names = ("x", "y", "z") + (BEAM_PROPERTIES if cloud.beam_origins is not None else ())
    header = (f"ply\nformat {fmt} 1.0\ncomment ComReg point cloud, millimetres\n"
              f"comment SPACE={cloud.space}\nelement vertex {len(cloud.points)}\n"
              + "".join(f"property double {name}\n" for name in names) + "end_header\n")
    table = cloud.points if cloud.beam_origins is None else \
        np.hstack([cloud.points, cloud.beam_origins])
    _write_header_and_xyz(tmp, header, table, binary)


# --- PCD ----------------------------------------------------------------------------------------

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def _read_pcd(path: Path) -> tuple[np.ndarray, str]:
    """Points of a PCD v0.7 file (ascii, binary or binary_compressed)."""
    with open(path, "rb") as f:
        lines = _read_header_lines(f, path, end=b"DATA")
        data_start = f.tell()
    header = {}
    for line in lines:
        words = line.split()
        if words and not line.startswith("#"):
            header[words[0].upper()] = words[1:]
    try:
        fields = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = header["TYPE"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
        n_points = int(header["POINTS"][0]) if "POINTS" in header else (
            int(header["WIDTH"][0]) * int(header["HEIGHT"][0]))
        data_kind = header["DATA"][0].lower()
        dtype = np.dtype([(name, _PCD_TYPES[(t.upper(), s)], (c,) if c > 1 else ())
                          for name, s, t, c in zip(fields, sizes, types, counts)])
    except (KeyError, IndexError, ValueError) as exc:
        raise CorruptFileError(path, f"incomplete PCD header ({exc})") from None
    if not {"x", "y", "z"} <= set(fields):
        raise CorruptFileError(path, "the PCD file has no x, y, z fields")
    if n_points < 0:
        raise CorruptFileError(path, f"the PCD header declares {n_points} points")
    if data_kind == "ascii":
        with open(path, "rb") as f:
            f.seek(data_start)
            text = f.read().decode("ascii", errors="replace")
        try:
            table = np.loadtxt(text.splitlines(), ndmin=2, dtype=np.float64)
        except ValueError as exc:
            raise CorruptFileError(path, f"non-numeric data ({exc})") from None
        if len(table) < n_points:
            raise CorruptFileError(path, f"expected {n_points} points, found {len(table)}")
        offsets = np.cumsum([0] + counts)
        columns = {name: table[:n_points, offsets[i]] for i, name in enumerate(fields)}
    elif data_kind == "binary":
        columns = _read_binary_records(path, data_start, dtype, n_points)
    elif data_kind == "binary_compressed":
        columns = _read_pcd_compressed(path, data_start, dtype, n_points)
    else:
        raise CorruptFileError(path, f"unknown PCD DATA kind '{data_kind}'")
    points = np.column_stack([columns["x"], columns["y"], columns["z"]]).astype(np.float64)
    finite = np.isfinite(points).all(axis=1)  # PCL marks missing points of organised clouds NaN
    return points[finite], _space_from_comments(lines)


def _read_pcd_compressed(path: Path, start: int, dtype: np.dtype, n_points: int) -> dict:
    """PCL's binary_compressed: LZF-compressed, fields stored column after column."""
    with open(path, "rb") as f:
        f.seek(start)
        sizes = f.read(8)
        if len(sizes) < 8:
            raise CorruptFileError(path, "truncated compressed PCD data")
        compressed_size, raw_size = struct.unpack("<II", sizes)
        if raw_size != dtype.itemsize * n_points or compressed_size > path.stat().st_size - start:
            raise CorruptFileError(path, f"the compressed PCD data ({compressed_size:,} bytes "
                                         f"for {raw_size:,}) does not match the header's "
                                         f"{n_points:,} points")
        raw = _lzf_decompress(f.read(compressed_size), raw_size, path)
    columns, offset = {}, 0
    for name in dtype.names:
        field = dtype.fields[name][0]
        nbytes = field.itemsize * n_points
        columns[name] = np.frombuffer(raw, field.base, count=n_points * max(1, field.itemsize //
                                      field.base.itemsize), offset=offset)
        offset += nbytes
    return columns


def _lzf_decompress(data: bytes, expected: int, path: Path) -> bytes:
    """Decompress LZF (the liblzf format PCL uses)."""
    out = bytearray()
    i = 0
    try:
        while i < len(data):
            ctrl = data[i]
            i += 1
            if ctrl < 32:  # literal run of ctrl + 1 bytes
                out += data[i:i + ctrl + 1]
                i += ctrl + 1
            else:  # back reference
                length = ctrl >> 5
                if length == 7:
                    length += data[i]
                    i += 1
                ref = len(out) - ((ctrl & 0x1F) << 8) - data[i] - 1
                i += 1
                if ref < 0:
                    raise IndexError
                for _ in range(length + 2):
                    out.append(out[ref])
                    ref += 1
    except IndexError:
        raise CorruptFileError(path, "corrupt LZF-compressed PCD data") from None
    if len(out) != expected:
        raise CorruptFileError(path, f"compressed PCD data gave {len(out)} bytes, "
                                     f"expected {expected}")
    return bytes(out)


def _write_pcd(cloud: PointCloud, tmp: Path, binary: bool) -> None:
    n = len(cloud.points)
    header = (f"# .PCD v0.7 - ComReg point cloud, millimetres. SPACE={cloud.space}\n"
              "VERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\n"
              f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
              f"DATA {'binary' if binary else 'ascii'}\n")
    _write_header_and_xyz(tmp, header, cloud.points, binary)


# --- shared helpers ---------------------------------------------------------------------------

def _read_header_lines(f, path: Path, *, end: bytes, first: bytes | None = None) -> list[str]:
    """Read text header lines up to and including the one starting with ``end``."""
    lines = []
    for _ in range(1000):
        raw = f.readline()
        if not raw:
            raise CorruptFileError(path, f"the header has no '{end.decode()}' line")
        if first is not None and not lines and raw.strip() != first:
            raise CorruptFileError(path, f"it does not start with '{first.decode()}'")
        lines.append(raw.decode("latin-1").strip())
        if raw.strip().startswith(end):
            return lines
    raise CorruptFileError(path, "the header is too long; this does not look like a point cloud")


def _read_binary_records(path: Path, start: int, dtype: np.dtype, count: int) -> np.ndarray:
    """``count`` records of ``dtype`` from ``start``; the file size is checked first, so a
    header claiming billions of points is refused without allocating them."""
    needed, available = dtype.itemsize * count, path.stat().st_size - start
    if count < 0 or needed > available:
        raise CorruptFileError(path, f"its header declares {count:,} points ({needed:,} "
                                     f"bytes), but only {max(available, 0):,} bytes follow it")
    with open(path, "rb") as f:
        f.seek(start)
        data = f.read(needed)
    return np.frombuffer(data, dtype=dtype, count=count)


def _write_header_and_xyz(tmp: Path, header: str, points: np.ndarray, binary: bool) -> None:
    """A text header, then ``(N, C)`` rows (points, with their beam origins in a PLY) as
    little-endian float64 or full-precision text."""
    with open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            f.write(points.astype("<f8").tobytes())
        else:
            np.savetxt(f, points, fmt="%.17g")


def _space_from_comments(lines: list[str]) -> str:
    for line in lines:
        match = _SPACE_COMMENT.search(line)
        if match and (line.startswith("#") or line.startswith("comment")):
            return match.group(1).upper()
    return "LPS"
