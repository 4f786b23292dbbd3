"""Mesh reading/writing: round trips, Slicer SPACE tags, trimesh as an independent reader, bad input."""

import struct

import numpy as np
import pytest
import trimesh

from comreg_core.errors import (CorruptFileError, InputFileNotFoundError, InvalidGeometryError,
                                UnsupportedFormatError)
from comreg_core.io import meshes as meshes_module
from comreg_core.io.meshes import MESH_EXTENSIONS, SurfaceMesh, read_mesh, write_mesh
from tests.helpers import FIBULA_STL, assert_close


def triangle_soup(mesh) -> np.ndarray:
    """``(M, 9)`` triangles as coordinates (rounded to 1 um), each rotated to start at its
    lexicographically smallest vertex, rows sorted: compares meshes independent of vertex
    numbering and duplication, keeping winding."""
    tris = np.round(np.asarray(mesh.vertices)[np.asarray(mesh.faces)] * 1000).astype(np.int64)
    _, rank = np.unique(tris.reshape(-1, 3), axis=0, return_inverse=True)
    rank = rank.reshape(-1, 3)
    start = np.argmin(rank, axis=1)
    order = (start[:, None] + np.arange(3)) % 3
    rotated = np.take_along_axis(tris, order[:, :, None], axis=1).reshape(-1, 9)
    return rotated[np.lexsort(rotated.T[::-1])] / 1000.0


@pytest.fixture(scope="module")
def fibula():
    return read_mesh(FIBULA_STL)


def test_real_fibula_reads_as_closed_lps_mesh(fibula):
    assert fibula.space == "LPS"  # no SPACE tag in the file: Slicer's default
    assert len(fibula.faces) == 44194
    reference = trimesh.load(FIBULA_STL, force="mesh")  # independent STL reader
    assert len(fibula.vertices) == len(reference.vertices)
    assert_close(triangle_soup(fibula), triangle_soup(reference), atol=1e-3, what="triangles")
    ours = fibula.to_trimesh()
    assert ours.is_watertight
    assert_close(ours.volume, reference.volume, rtol=1e-9, what="volume mm^3")
    assert ours.volume > 0  # outward winding


@pytest.mark.parametrize("ext", MESH_EXTENSIONS)
@pytest.mark.parametrize("space", ["LPS", "RAS"])
def test_round_trip_keeps_geometry_and_space(tmp_path, fibula, ext, space):
    mesh = fibula.in_space(space)
    path = write_mesh(mesh, tmp_path / f"bone{ext}")
    back = read_mesh(path)
    assert back.space == space
    assert len(back.faces) == len(mesh.faces)
    assert_close(triangle_soup(back), triangle_soup(mesh), atol=2e-3, what=f"{ext} triangles")
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


@pytest.mark.parametrize("ext", [".stl", ".ply", ".obj"])
def test_files_we_write_read_the_same_in_trimesh(tmp_path, fibula, ext):
    path = write_mesh(fibula, tmp_path / f"bone{ext}")
    other = trimesh.load(path, force="mesh", process=False)
    assert_close(triangle_soup(other), triangle_soup(fibula), atol=2e-3, what="triangles")


def test_obj_and_ply_keep_float64_precision(tmp_path):
    rng = np.random.default_rng(0)
    mesh = SurfaceMesh(rng.normal(1000.0, 50.0, (4, 3)), [[0, 1, 2], [0, 2, 3]])
    for ext in (".obj", ".vtp"):
        back = read_mesh(write_mesh(mesh, tmp_path / f"m{ext}"))
        assert_close(back.vertices, mesh.vertices, atol=1e-9, what=ext)
        np.testing.assert_array_equal(back.faces, mesh.faces)


def test_slicer_binary_stl_header_space_ras_is_honoured(tmp_path):
    """3D Slicer tags binary STL models in the 80-byte header: '3D Slicer output. SPACE=RAS'."""
    header = b"3D Slicer output. SPACE=RAS".ljust(80, b" ")
    tri = np.array([[10, 20, 30], [11, 20, 30], [10, 21, 30]], np.float32)
    record = struct.pack("<3f", 0, 0, 1) + tri.tobytes() + b"\0\0"
    path = tmp_path / "slicer.stl"
    path.write_bytes(header + struct.pack("<I", 1) + record)
    mesh = read_mesh(path)
    assert mesh.space == "RAS"
    lps = mesh.in_space("LPS")
    assert_close(lps.vertices[:, :2], -mesh.vertices[:, :2], what="x, y flipped")
    assert_close(lps.vertices[:, 2], mesh.vertices[:, 2], what="z kept")


def test_vtk_legacy_header_and_ply_comment_tags(tmp_path):
    (tmp_path / "a.vtk").write_text(
        "# vtk DataFile Version 4.2\n3D Slicer output. SPACE=RAS\nASCII\nDATASET POLYDATA\n"
        "POINTS 3 float\n0 0 0 1 0 0 0 1 0\nPOLYGONS 1 4\n3 0 1 2\n")
    (tmp_path / "b.ply").write_text(
        "ply\nformat ascii 1.0\ncomment SPACE=RAS\nelement vertex 3\nproperty float x\n"
        "property float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert read_mesh(tmp_path / "a.vtk").space == "RAS"
    assert read_mesh(tmp_path / "b.ply").space == "RAS"


def test_missing_file(tmp_path):
    with pytest.raises(InputFileNotFoundError, match="does not exist"):
        read_mesh(tmp_path / "nope.stl")


def test_unknown_extension(tmp_path):
    (tmp_path / "bone.foo").write_text("x")
    with pytest.raises(UnsupportedFormatError, match=r"\.stl"):
        read_mesh(tmp_path / "bone.foo")
    with pytest.raises(UnsupportedFormatError):
        write_mesh(SurfaceMesh(np.eye(3), [[0, 1, 2]]), tmp_path / "bone.foo")


@pytest.mark.parametrize("name, content", [
    ("truncated.stl", FIBULA_STL.read_bytes()[:5000]),
    ("empty.stl", b""),
    ("garbage.vtk", b"this is not a vtk file\n"),
    ("garbage.vtp", b"<VTKFile nope"),
    ("truncated.obj", b"v 0 0 0\nv 1 0"),
])
def test_corrupt_files(tmp_path, name, content):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(CorruptFileError, match="corrupt or truncated"):
        read_mesh(tmp_path / name)


def test_mesh_without_faces_and_non_finite_vertices(tmp_path):
    (tmp_path / "points.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(InvalidGeometryError, match="no triangles"):
        read_mesh(tmp_path / "points.ply")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(InvalidGeometryError, match="non-finite"):
        read_mesh(tmp_path / "nan.obj")
    with pytest.raises(InvalidGeometryError, match="missing vertices"):
        SurfaceMesh(np.eye(3), [[0, 1, 5]])


def test_failed_write_leaves_existing_file_intact(tmp_path, monkeypatch, fibula):
    target = tmp_path / "bone.stl"
    target.write_bytes(b"previous content")

    def broken_writer(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(meshes_module, "_write_with_vtk", broken_writer)
    with pytest.raises(OSError):
        write_mesh(fibula, target)
    assert target.read_bytes() == b"previous content"
    assert [p.name for p in tmp_path.iterdir()] == ["bone.stl"]
