"""Point clouds: XYZ (ASCII), PLY, PCD (ASCII, binary, binary_compressed) and NPY.

PLY files are read and written by plyfile, PCD files by pypcd4 (its header model, binary and
LZF-compressed data; ASCII rows are split here at any whitespace, and ASCII files are written
with every bit of each float64). Sizes are checked against the header before either library
allocates what a header claims.

Coordinates are patient millimetres. ComReg writes a ``SPACE=LPS``/``SPACE=RAS`` comment into XYZ,
PLY and PCD files (as 3D Slicer does for models); files without it, and NPY files, are taken as
LPS.
"""

from __future__ import annotations

import io
import re
import struct
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from plyfile import (PlyData, PlyElement, PlyHeaderParseError, PlyListProperty,
                     PlyParseError)

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
    if array.ndim != 2 or array.shape[1] < 3 or array.dtype.kind not in "iuf":
        raise CorruptFileError(path, f"expected a real (N, 3) array, found {array.dtype} "
                                     f"{array.shape}")
    return array[:, :3].astype(np.float64), "LPS"


def _write_npy(cloud: PointCloud, tmp: Path, binary: bool) -> None:
    with open(tmp, "wb") as f:  # NPY has no room for a space tag: always store LPS
        np.save(f, cloud.in_space("LPS").points)


# --- PLY (plyfile) -----------------------------------------------------------------------------

#: PLY vertex properties of the beam origins.
BEAM_PROPERTIES = ("beam_x", "beam_y", "beam_z")
#: The most header bytes looked at: a file without 'end_header' in them is not a point cloud.
_MAX_HEADER_BYTES = 1 << 20
#: bytes.translate table: every byte outside ASCII becomes '?'.
_ASCII_ONLY = bytes(range(128)) + b"?" * 128


class _PlyFile(io.BufferedReader):
    """A PLY file opened for plyfile, which decodes the header as ASCII: header bytes outside
    ASCII (a '®' in a comment) read as '?'; the data from ``data_start`` on are untouched."""

    def __init__(self, path: Path, data_start: int):
        super().__init__(io.FileIO(path, "rb"))
        self._data_start = data_start

    def read(self, size: int | None = -1) -> bytes:
        start = self.tell()
        data = super().read(size)
        if start < self._data_start:
            cut = self._data_start - start
            data = data[:cut].translate(_ASCII_ONLY) + data[cut:]
        return data


def _ply_header(path: Path) -> tuple[PlyData, int]:
    """The header of a PLY file, parsed by plyfile (elements without data), and where its data
    start. Checks that the file is large enough for the counts it declares, before anything is
    allocated: plyfile and VTK allocate what the header says."""
    with open(path, "rb") as f:
        head = io.BytesIO(f.read(_MAX_HEADER_BYTES).translate(_ASCII_ONLY))
    try:
        # plyfile's own header parser; PlyData.read would go on to allocate and read the data.
        header = PlyData._parse_header(head)
    except PlyHeaderParseError as exc:
        raise CorruptFileError(path, _header_problem(exc)) from None
    data_start = head.tell()
    needed = 0
    for element in header.elements:
        if element.count < 0:
            raise CorruptFileError(path, f"the PLY header declares {element.count} "
                                         f"{element.name}s")
        needed += element.count * _ply_min_record_bytes(element.properties, header.text)
    available = path.stat().st_size - data_start
    if needed > available + 1:  # +1: an ASCII file may end without its last newline
        declared = ", ".join(f"'{e.name}' x {e.count:,}" for e in header.elements)
        raise CorruptFileError(path, f"its header declares {declared}, which need at least "
                                     f"{needed:,} bytes, but only {available:,} follow it")
    return header, data_start


def _header_problem(exc: PlyHeaderParseError) -> str:
    if exc.message == "expected 'ply'":
        return "it does not start with 'ply'"
    if exc.message == "early end-of-file":
        return "the header has no 'end_header' line"
    return f"bad PLY header ({exc})"


def _ply_min_record_bytes(properties, text: bool) -> int:
    """The fewest bytes one record of these properties can take (an empty list for lists)."""
    if text:  # one character and one separator per value
        return 2 * len(properties)
    return sum(np.dtype(p.len_dtype if isinstance(p, PlyListProperty) else p.val_dtype).itemsize
               for p in properties)


def check_ply_size(path: str | Path) -> None:
    """Raise :class:`CorruptFileError` if a PLY file is not a PLY file or is shorter than its
    header's counts need (run before handing it to VTK, whose reader allocates what the header
    says)."""
    _ply_header(Path(path))


def _read_ply_with_beams(path: Path) -> tuple[np.ndarray, str, np.ndarray | None]:
    """Vertices of a PLY file and their beam origins when it has them (faces are ignored)."""
    header, data_start = _ply_header(path)
    names = {p.name for p in header["vertex"].properties} if "vertex" in header else set()
    if not {"x", "y", "z"} <= names:
        raise CorruptFileError(path, "the PLY header has no vertex element with x, y, z")
    try:
        with _PlyFile(path, data_start) as f:
            vertices = PlyData.read(f)["vertex"].data
    except PlyParseError as exc:
        raise CorruptFileError(path, f"bad PLY data ({exc})") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise CorruptFileError(path, f"bad PLY data ({type(exc).__name__})") from None
    points = np.column_stack([vertices[k] for k in ("x", "y", "z")]).astype(np.float64)
    origins = None
    if set(BEAM_PROPERTIES) <= names:
        origins = np.column_stack([vertices[k] for k in BEAM_PROPERTIES]).astype(np.float64)
    comments = header.comments + [c for e in header.elements for c in e.comments]
    return points, _space_from_comments([f"comment {c}" for c in comments]), origins


def _write_ply(cloud: PointCloud, tmp: Path, binary: bool) -> None:
    columns = {"x": cloud.points[:, 0], "y": cloud.points[:, 1], "z": cloud.points[:, 2]}
    if cloud.beam_origins is not None:
        columns.update(zip(BEAM_PROPERTIES, cloud.beam_origins.T))
    vertices = np.empty(len(cloud.points), dtype=[(name, "<f8") for name in columns])
    for name, values in columns.items():
        vertices[name] = values
    PlyData([PlyElement.describe(vertices, "vertex")], text=not binary, byte_order="<",
            comments=["ComReg point cloud, millimetres", f"SPACE={cloud.space}"]).write(str(tmp))


# --- PCD (pypcd4) ------------------------------------------------------------------------------

def _read_pcd(path: Path) -> tuple[np.ndarray, str]:
    """Points of a PCD file (ascii, binary or binary_compressed); points PCL marks missing
    (NaN, in organised clouds) are dropped."""
    with open(path, "rb") as f:
        lines = _read_header_lines(f, path, end=b"DATA")
        data_start = f.tell()
    meta = _pcd_metadata(path, lines)
    if meta.data.value == "ascii":
        columns = _read_pcd_ascii(path, data_start, meta)
    else:
        columns = _read_pcd_binary(path, data_start, meta)
    points = np.column_stack([columns["x"], columns["y"], columns["z"]]).astype(np.float64)
    finite = np.isfinite(points).all(axis=1)
    return points[finite], _space_from_comments(lines)


def _pcd_metadata(path: Path, lines: list[str]):
    """pypcd4's validated header. Any VERSION is read (pypcd4 knows only 0.7); a header without
    POINTS has WIDTH x HEIGHT of them, one without WIDTH is one row of POINTS."""
    from pydantic import ValidationError
    from pypcd4 import MetaData  # imports pydantic: only when a PCD file is read or written

    words = {line.split()[0].upper(): line.split()[1:] for line in lines
             if line.split() and not line.startswith("#")}
    lines = [line for line in lines if not line.upper().startswith("VERSION")]
    try:
        if "POINTS" not in words and {"WIDTH", "HEIGHT"} <= set(words):
            lines.append(f"POINTS {int(words['WIDTH'][0]) * int(words['HEIGHT'][0])}")
        elif "WIDTH" not in words and "POINTS" in words:
            lines.append(f"WIDTH {int(words['POINTS'][0])}")
    except (IndexError, ValueError):
        pass  # pypcd4 says what is wrong
    try:
        meta = MetaData.parse_header(lines)
        meta.build_dtype()
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}"
                             for e in exc.errors())
        missing = any(e["type"] == "missing" for e in exc.errors())
        raise CorruptFileError(path, f"{'incomplete' if missing else 'invalid'} PCD header "
                                     f"({problems})") from None
    except (KeyError, ValueError) as exc:
        raise CorruptFileError(path, f"invalid PCD header ({exc})") from None
    if not {"x", "y", "z"} <= set(meta.fields):
        raise CorruptFileError(path, "the PCD file has no x, y, z fields")
    return meta


def _read_pcd_ascii(path: Path, start: int, meta) -> dict:
    """ASCII rows, split at any whitespace (pypcd4 takes single spaces only)."""
    with open(path, "rb") as f:
        f.seek(start)
        text = f.read().decode("ascii", errors="replace")
    try:
        table = np.loadtxt(text.splitlines(), ndmin=2, dtype=np.float64)
    except ValueError as exc:
        raise CorruptFileError(path, f"non-numeric data ({exc})") from None
    if len(table) < meta.points:
        raise CorruptFileError(path, f"expected {meta.points} points, found {len(table)}")
    offsets = np.cumsum([0, *meta.count])
    return {name: table[:meta.points, offsets[i]] for i, name in enumerate(meta.fields)}


def _read_pcd_binary(path: Path, start: int, meta) -> np.ndarray:
    """binary and binary_compressed data, decoded by pypcd4 once the sizes are checked."""
    from pypcd4 import PointCloud as PcdCloud

    record = meta.build_dtype().itemsize
    needed, available = record * meta.points, path.stat().st_size - start
    if meta.data.value == "binary" and needed > available:
        raise CorruptFileError(path, f"its header declares {meta.points:,} points ({needed:,} "
                                     f"bytes), but only {max(available, 0):,} bytes follow it")
    with open(path, "rb") as f:
        f.seek(start)
        data = f.read()
    if meta.data.value != "binary":
        if len(data) < 8:
            raise CorruptFileError(path, "truncated compressed PCD data")
        compressed_size, raw_size = struct.unpack("<II", data[:8])
        if raw_size != needed or compressed_size > available - 8:
            raise CorruptFileError(path, f"the compressed PCD data ({compressed_size:,} bytes "
                                         f"for {raw_size:,}) does not match the header's "
                                         f"{meta.points:,} points")
    try:
        return PcdCloud.from_fileobj(io.BytesIO(meta.compose_header().encode("ascii") + data)
                                     ).pc_data
    except (ValueError, TypeError, RuntimeError, struct.error) as exc:
        detail = ("corrupt LZF-compressed PCD data" if meta.data.value != "binary" else
                  f"corrupt PCD data ({type(exc).__name__}: {exc})")
        raise CorruptFileError(path, detail) from None


def _write_pcd(cloud: PointCloud, tmp: Path, binary: bool) -> None:
    from pypcd4 import Encoding, PointCloud as PcdCloud

    pcd = PcdCloud.from_points(cloud.points, ("x", "y", "z"), (np.float64,) * 3)
    with open(tmp, "wb") as f:
        f.write(f"# .PCD v0.7 - ComReg point cloud, millimetres. SPACE={cloud.space}\n"
                .encode("ascii"))
        if binary:
            pcd.save(f, Encoding.BINARY)
        else:  # pypcd4's ASCII rows have 10 decimals: write every bit of each float64
            f.write(pcd.metadata.compose_header(Encoding.ASCII).encode("ascii"))
            np.savetxt(f, cloud.points, fmt="%.17g")


# --- shared helpers ---------------------------------------------------------------------------

def _read_header_lines(f, path: Path, *, end: bytes) -> list[str]:
    """Read text header lines up to and including the one starting with ``end`` (comments may
    be in any 8-bit encoding: MATLAB writes a UTF-8 '®')."""
    lines = []
    for _ in range(1000):
        raw = f.readline()
        if not raw:
            raise CorruptFileError(path, f"the header has no '{end.decode()}' line")
        lines.append(raw.decode("latin-1").strip())
        if raw.strip().startswith(end):
            return lines
    raise CorruptFileError(path, "the header is too long; this does not look like a point cloud")


def _space_from_comments(lines: list[str]) -> str:
    for line in lines:
        match = _SPACE_COMMENT.search(line)
        if match and (line.startswith("#") or line.startswith("comment")):
            return match.group(1).upper()
    return "LPS"
