"""PLY through plyfile and PCD through pypcd4: files written by the hand-written code before
(tests/io/data/legacy_*), bit-identical coordinates, the SPACE comment, beam origins, other
readers, and bad or lying headers refused before anything is allocated."""

import struct
from pathlib import Path

import numpy as np
import pytest

from comreg_core.errors import CorruptFileError
from comreg_core.io.pointclouds import PointCloud, check_ply_size, read_points, write_points
from tests.helpers import assert_close

DATA = Path(__file__).parent / "data"
LEGACY = [  # (file, space, with beam origins): written by the string-building writers
    ("legacy_binary_lps.ply", "LPS", False), ("legacy_ascii_ras.ply", "RAS", False),
    ("legacy_binary_beams_ras.ply", "RAS", True), ("legacy_ascii_beams_lps.ply", "LPS", True),
    ("legacy_binary_ras.pcd", "RAS", False), ("legacy_ascii_lps.pcd", "LPS", False),
]


@pytest.fixture(scope="module")
def legacy():
    return np.load(DATA / "legacy_points.npy"), np.load(DATA / "legacy_beams.npy")


@pytest.mark.parametrize("name, space, beams", LEGACY)
def test_reads_files_written_by_the_old_writers(legacy, name, space, beams):
    points, origins = legacy
    cloud = read_points(DATA / name)
    assert cloud.space == space
    assert np.array_equal(cloud.points, points), "coordinates must come back bit for bit"
    if beams:
        assert np.array_equal(cloud.beam_origins, origins)
    else:
        assert cloud.beam_origins is None


@pytest.mark.parametrize("name, space, beams", [row for row in LEGACY if "binary" in row[0]
                                                 and row[0].endswith(".ply")])
def test_binary_ply_bytes_are_unchanged(tmp_path, legacy, name, space, beams):
    points, origins = legacy
    cloud = PointCloud(points, space, beam_origins=origins if beams else None)
    path = write_points(cloud, tmp_path / name)
    assert path.read_bytes() == (DATA / name).read_bytes()


@pytest.mark.parametrize("ext", [".ply", ".pcd"])
@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("space", ["LPS", "RAS"])
def test_round_trip_keeps_bits_space_and_beams(tmp_path, legacy, ext, binary, space):
    points, origins = legacy
    beams = origins if ext == ".ply" else None  # PCD files hold the points only
    path = write_points(PointCloud(points, space, beam_origins=beams), tmp_path / f"c{ext}",
                        binary=binary)
    header = path.read_bytes().split(b"end_header" if ext == ".ply" else b"DATA")[0]
    assert f"SPACE={space}".encode() in header
    back = read_points(path)
    assert back.space == space and np.array_equal(back.points, points)
    if ext == ".ply":
        assert np.array_equal(back.beam_origins, origins)
        assert b"property double beam_x" in header
    assert list(tmp_path.iterdir()) == [path]


def test_plyfile_sees_the_beam_properties(tmp_path, legacy):
    from plyfile import PlyData

    points, origins = legacy
    path = write_points(PointCloud(points, "RAS", beam_origins=origins), tmp_path / "c.ply")
    ply = PlyData.read(str(path))
    assert "SPACE=RAS" in ply.comments
    assert [p.name for p in ply["vertex"].properties] == ["x", "y", "z", "beam_x", "beam_y",
                                                         "beam_z"]
    assert np.array_equal(ply["vertex"]["beam_y"], origins[:, 1])


def test_open3d_reads_our_ascii_pcd(tmp_path, legacy):
    """(Open3D 0.20 reads binary float64 PCD fields as zeros, ours and its own alike.)"""
    o3d = pytest.importorskip("open3d")
    path = write_points(PointCloud(legacy[0]), tmp_path / "c.pcd", binary=False)
    assert_close(np.asarray(o3d.io.read_point_cloud(str(path)).points), legacy[0],
                 what="points read by Open3D")


def test_ply_from_elsewhere(tmp_path):
    """Big-endian, float32, a non-ASCII comment, SPACE in an element comment, faces first and
    quads: all read (faces are ignored)."""
    vertices = np.array([(1.5, 2, 3, 9), (4, 5, 6, 9), (7, 8, 9, 9), (0, 1, 0, 9)],
                        dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("red", "u1")])
    face = struct.pack(">B4i", 4, 0, 1, 2, 3)
    path = tmp_path / "other.ply"
    path.write_bytes(b"ply\nformat binary_big_endian 1.0\ncomment MATLAB\xc2\xae made it\n"
                     b"element face 1\nproperty list uchar int vertex_indices\n"
                     b"element vertex 4\ncomment SPACE=RAS\nproperty float x\nproperty float y\n"
                     b"property float z\nproperty uchar red\nend_header\n"
                     + face + vertices.tobytes())
    cloud = read_points(path)
    assert cloud.space == "RAS" and cloud.beam_origins is None
    assert_close(cloud.points, [[1.5, 2, 3], [4, 5, 6], [7, 8, 9], [0, 1, 0]])


def test_pcd_ascii_with_any_whitespace_old_version_and_no_width(tmp_path):
    path = tmp_path / "c.pcd"
    path.write_text("# SPACE=RAS\nVERSION .5\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
                    "COUNT 1 1 1\nPOINTS 3\nDATA ascii\n1\t2\t3 \n4  5 6\n7 8 9\n")
    cloud = read_points(path)
    assert cloud.space == "RAS"
    assert_close(cloud.points, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])


def _huge_files(tmp_path):
    ply = (b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\n"
           b"property float x\nproperty float y\nproperty float z\nelement face 1\n"
           b"property list uchar int vertex_indices\nend_header\n" + bytes(49))
    ascii_ply = (b"ply\nformat ascii 1.0\nelement vertex 4000000000\nproperty float x\n"
                 b"property float y\nproperty float z\nend_header\n1 2 3\n")
    pcd = (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
           b"WIDTH 4000000000\nHEIGHT 1\nPOINTS 4000000000\nDATA binary\n" + bytes(36))
    paths = []
    for name, content in (("h.ply", ply), ("a.ply", ascii_ply), ("h.pcd", pcd)):
        (tmp_path / name).write_bytes(content)
        paths.append(tmp_path / name)
    return paths


def test_headers_claiming_billions_of_points_are_refused(tmp_path):
    for path in _huge_files(tmp_path):
        with pytest.raises(CorruptFileError, match=r"4,000,000,000.*follow"):
            read_points(path)
        if path.suffix == ".ply":
            with pytest.raises(CorruptFileError, match=r"4,000,000,000.*follow"):
                check_ply_size(path)


_PCD = b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nPOINTS 3\n"
_PLY = b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n" \
       b"property float z\nend_header\n"


@pytest.mark.parametrize("name, content, message", [
    ("n.ply", _PLY + b"1 2 3\n4 five 6\n", r"row 1: property 'y': malformed input"),
    ("s.ply", _PLY + b"1 2 3\n        \n", r"early end-of-line"),
    ("f.ply", b"ply\nformat weird 1.0\nend_header\n", r"format 'weird'"),
    ("e.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "end_header"),
    ("m.ply", b"ply\nformat ascii 1.0\nelement vertex -3\nend_header\n", "declares -3"),
    ("k.pcd", _PCD + b"DATA zipped\n" + bytes(36), "invalid PCD header"),
    ("l.pcd", _PCD + b"DATA binary_compressed\n" + struct.pack("<II", 10, 36) + b"\xff" * 10,
     "corrupt LZF-compressed PCD data"),
    ("c.pcd", _PCD + b"DATA binary_compressed\n" + struct.pack("<II", 10, 99) + bytes(10),
     "does not match the header's 3 points"),
    ("a.pcd", _PCD + b"DATA ascii\n1 2 3\n", "expected 3 points, found 1"),
])
def test_bad_files_raise_one_line_errors(tmp_path, name, content, message):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(CorruptFileError, match=message) as caught:
        read_points(tmp_path / name)
    assert "\n" not in str(caught.value)
