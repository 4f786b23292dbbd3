"""Triangle surface meshes: STL, PLY, OBJ, VTK (legacy) and VTP, with Slicer's ``SPACE=`` tag.

3D Slicer writes model files in LPS and marks them with ``SPACE=LPS`` (STL/VTK header, PLY/OBJ
comment, VTP field data); older files may say ``SPACE=RAS``. A file without a tag is taken as LPS,
as 3D Slicer does. Readers keep the file's space; :meth:`SurfaceMesh.in_space` converts.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from comreg_core.errors import CorruptFileError, InvalidGeometryError
from comreg_core.io._files import atomic_output, require_extension, require_input_file
from comreg_core.io._vtk import run_vtk
from comreg_core.io.pointclouds import check_ply_size
from comreg_core.transforms import apply_transform, as_points, check_space, space_change


@dataclass
class SurfaceMesh:
    """A triangle mesh in patient millimetres.

    Attributes:
        vertices: ``(N, 3)`` float64 vertex positions in mm.
        faces: ``(M, 3)`` int64 vertex indices of each triangle (counter-clockwise = outward).
        space: "LPS" or "RAS".
        path: the file it was read from, if any.
    """

    vertices: np.ndarray
    faces: np.ndarray
    space: str = "LPS"
    path: Path | None = None

    def __post_init__(self) -> None:
        self.space = check_space(self.space)
        self.vertices = as_points(self.vertices, "mesh vertices")
        faces = np.asarray(self.faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise InvalidGeometryError(
                f"The mesh{self._where()} has no triangles (faces of shape {faces.shape}).",
                "A bone surface needs triangle faces; point-only files are point clouds.")
        faces = faces.astype(np.int64, copy=False)
        if faces.min() < 0 or faces.max() >= len(self.vertices):
            raise InvalidGeometryError(
                f"The mesh{self._where()} has faces that index missing vertices.",
                "The file is inconsistent; export it again.")
        self.faces = faces

    def _where(self) -> str:
        return f" '{self.path}'" if self.path else ""

    def in_space(self, space: str) -> "SurfaceMesh":
        """The same surface with vertices expressed in ``space``."""
        space = check_space(space)
        T = space_change(self.space, space)
        return replace(self, vertices=apply_transform(T, self.vertices), space=space)

    def to_pyvista(self):
        """As a ``pyvista.PolyData`` (triangles)."""
        import pyvista as pv

        return pv.PolyData.from_regular_faces(self.vertices, self.faces)

    def to_trimesh(self, process: bool = False):
        """As a ``trimesh.Trimesh`` (no processing unless asked)."""
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=process)

    @classmethod
    def from_polydata(cls, polydata, space: str = "LPS", path: Path | None = None) -> "SurfaceMesh":
        """From a ``vtkPolyData``/``pyvista.PolyData``; polygons are triangulated, lines and
        vertices dropped."""
        import pyvista as pv

        mesh = pv.wrap(polydata)
        if mesh.n_cells and not mesh.is_all_triangles:
            mesh = mesh.triangulate()
        faces = mesh.regular_faces if mesh.faces.size else np.empty((0, 3), np.int64)
        return cls(np.asarray(mesh.points, np.float64), faces, space, path)


MESH_EXTENSIONS = [".stl", ".ply", ".obj", ".vtk", ".vtp"]
_SPACE_TAG = re.compile(rb"SPACE=(RAS|LPS)", re.IGNORECASE)


def read_mesh(path: str | Path) -> SurfaceMesh:
    """Read a triangle mesh (STL, PLY, OBJ, VTK, VTP) in the patient space its file declares.

    Raises InputFileNotFoundError, UnsupportedFormatError, CorruptFileError (unparseable or no
    geometry) and InvalidGeometryError (no triangles, non-finite coordinates).
    """
    path = require_input_file(path, "mesh file")
    ext = require_extension(path, "mesh", MESH_EXTENSIONS)
    if ext == ".ply":  # VTK's reader allocates what the header claims, and can crash on it
        check_ply_size(path)
    import vtk

    reader = {
        ".stl": vtk.vtkSTLReader,
        ".ply": vtk.vtkPLYReader,
        ".obj": vtk.vtkOBJReader,
        ".vtk": vtk.vtkPolyDataReader,
        ".vtp": vtk.vtkXMLPolyDataReader,
    }[ext]()
    reader.SetFileName(str(path))
    run_vtk(reader, path)
    polydata = reader.GetOutput()
    if polydata is None or polydata.GetNumberOfPoints() == 0:
        raise CorruptFileError(path, "it holds no points (empty, truncated or not a mesh)")
    return SurfaceMesh.from_polydata(polydata, _space_tag(path, ext, polydata), path)


def _space_tag(path: Path, ext: str, polydata) -> str:
    """The ``SPACE=`` coordinate system of a model file as 3D Slicer writes it; LPS if absent."""
    if ext == ".vtp":
        array = polydata.GetFieldData().GetAbstractArray("SPACE")
        if array is not None and array.GetNumberOfValues():
            return check_space(array.GetValue(0))
        return "LPS"
    with open(path, "rb") as f:
        head = f.read(4096)
    if ext == ".stl" and not head.lstrip().lower().startswith(b"solid"):
        head = head[:80]  # binary STL: only the 80-byte header is text
    match = _SPACE_TAG.search(head)
    return check_space(match.group(1).decode()) if match else "LPS"


def write_mesh(mesh: SurfaceMesh, path: str | Path, *, binary: bool = True) -> Path:
    """Write ``mesh`` atomically, tagged ``SPACE=<mesh.space>`` the way 3D Slicer tags models.

    STL, PLY, VTK and VTP are binary (zlib for VTP) unless ``binary=False``; OBJ is text.
    Returns the path written.
    """
    path = Path(path)
    ext = require_extension(path, "mesh", MESH_EXTENSIONS)
    tag = f"SPACE={mesh.space}"
    with atomic_output(path) as tmp:
        if ext == ".obj":
            _write_obj(mesh, tmp, tag)
        else:
            _write_with_vtk(mesh, tmp, ext, tag, binary)
    return path


def _write_with_vtk(mesh: SurfaceMesh, tmp: Path, ext: str, tag: str, binary: bool) -> None:
    import vtk

    polydata = mesh.to_pyvista()
    header = f"ComReg output. {tag}"
    if ext == ".stl":
        writer = vtk.vtkSTLWriter()
        writer.SetHeader(header)
    elif ext == ".ply":
        writer = vtk.vtkPLYWriter()
        writer.AddComment(tag)
    elif ext == ".vtk":
        writer = vtk.vtkPolyDataWriter()
        writer.SetFileVersion(42)  # readable by older 3D Slicer and most other software
        writer.SetHeader(header)
    else:  # .vtp: Slicer keeps the space in a string field-data array named SPACE
        writer = vtk.vtkXMLPolyDataWriter()
        space = vtk.vtkStringArray()
        space.SetName("SPACE")
        space.InsertNextValue(mesh.space)
        polydata.GetFieldData().AddArray(space)
        writer.SetCompressorTypeToZLib() if binary else writer.SetCompressorTypeToNone()
        writer.SetDataModeToAppended() if binary else writer.SetDataModeToAscii()
    if ext != ".vtp":
        writer.SetFileTypeToBinary() if binary else writer.SetFileTypeToASCII()
    writer.SetInputData(polydata)
    writer.SetFileName(str(tmp))
    run_vtk(writer, tmp, writing=True)


def _write_obj(mesh: SurfaceMesh, tmp: Path, tag: str) -> None:
    with open(tmp, "w", encoding="ascii") as f:
        f.write(f"# ComReg output. {tag}\n")
        np.savetxt(f, mesh.vertices, fmt="v %.17g %.17g %.17g")
        np.savetxt(f, mesh.faces + 1, fmt="f %d %d %d")


def ct_fingerprint(vertices: np.ndarray, faces: np.ndarray) -> dict[str, Any]:
    """Identity of a CT mesh: sha256 over its float64 vertices, int64 faces and bounding box
    (little-endian, C order), plus the sizes and the bounding box (mm) for people to read."""
    v = np.ascontiguousarray(vertices, dtype="<f8")
    f = np.ascontiguousarray(faces, dtype="<i8")
    lo, hi = v.min(axis=0), v.max(axis=0)
    h = hashlib.sha256()
    for part in (np.array(v.shape, "<i8"), v, np.array(f.shape, "<i8"), f, lo, hi):
        h.update(np.ascontiguousarray(part).tobytes())
    return {"sha256": h.hexdigest(), "n_vertices": int(len(v)), "n_faces": int(len(f)),
            "bbox_min_mm": lo.tolist(), "bbox_max_mm": hi.tolist()}


def mesh_fingerprint(mesh) -> dict[str, Any]:
    """:func:`ct_fingerprint` of a mesh path or :class:`~comreg_core.io.SurfaceMesh`, exactly as
    read from the file (no repair or merging)."""
    if not isinstance(mesh, SurfaceMesh):
        mesh = read_mesh(mesh)
    return ct_fingerprint(mesh.vertices, mesh.faces)
