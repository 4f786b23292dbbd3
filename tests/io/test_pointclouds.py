"""Point cloud reading/writing: round trips, real PCD files, compressed PCD, trimesh reference, bad input."""

import struct

import numpy as np
import pytest
import trimesh

from comreg_core.errors import (CorruptFileError, InputFileNotFoundError, InvalidGeometryError,
                                UnsupportedFormatError)
from comreg_core.io.pointclouds import POINT_CLOUD_EXTENSIONS, PointCloud, read_points, write_points
from tests.helpers import assert_close

SPINE = "ismr24-spine-phantom/dataset"


@pytest.fixture()
def cloud():
    rng = np.random.default_rng(7)
    return PointCloud(rng.normal([120.0, -40.0, 1500.0], 30.0, (500, 3)))


@pytest.mark.parametrize("ext", POINT_CLOUD_EXTENSIONS)
@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("space", ["LPS", "RAS"])
def test_round_trip_is_exact(tmp_path, cloud, ext, binary, space):
    cloud = cloud.in_space(space)
    path = write_points(cloud, tmp_path / f"c{ext}", binary=binary)
    back = read_points(path)
    expected = cloud.in_space(back.space)  # NPY stores LPS; every other format keeps the space
    assert back.space == ("LPS" if ext == ".npy" else space)
    assert_close(back.points, expected.points, atol=0.0, what=f"{ext} points")
    assert list(tmp_path.iterdir()) == [path]


@pytest.mark.parametrize("ext", [".ply", ".xyz"])
def test_trimesh_reads_what_we_write(tmp_path, cloud, ext):
    path = write_points(cloud, tmp_path / f"c{ext}", binary=True)
    if ext == ".ply":
        other = np.asarray(trimesh.load(path).vertices)
    else:
        other = np.loadtxt(path)  # plain numpy: comments start with '#'
    assert_close(other, cloud.points, atol=1e-9, what="points")


def test_real_matlab_pcd_files(shared_data):
    """MATLAB pcwrite files: a non-ASCII comment, float64 xyz, an extra rgb column."""
    us = read_points(shared_data / SPINE / "2023-11-13_spine_phantom_franka_US/vertebrae_clean_scaled.pcd")
    assert us.points.shape == (9618, 3)
    extent = us.points.max(0) - us.points.min(0)
    assert_close(extent, [82.0, 162.3, 37.6], atol=0.5, what="extent mm (README: ~82 x 162 x 38)")
    fiducials = read_points(shared_data / SPINE / "2023-10-26_spine_phantom_CT/fiducials.pcd")
    assert fiducials.points.shape == (6, 3)
    assert_close(fiducials.points[0], [-55.880859375, 39.25, 2.0419921875], atol=1e-9)


def _lzf_literals(data: bytes) -> bytes:
    """A valid LZF stream made of literal runs only (each run at most 32 bytes)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out += bytes([len(chunk) - 1]) + chunk
    return bytes(out)


def test_binary_compressed_pcd(tmp_path):
    """PCL's binary_compressed: field-major layout, LZF; includes one back reference."""
    x = np.array([1.5, 2.5, 3.5], np.float32)
    y = np.array([-1.0, -2.0, -3.0], np.float32)
    z = np.zeros(3, np.float32)  # 12 zero bytes: a literal zero then a back reference
    raw = x.tobytes() + y.tobytes() + z.tobytes()
    head = _lzf_literals(x.tobytes() + y.tobytes()) + bytes([0, 0])  # literal: one 0 byte
    # back reference: copy 11 bytes from distance 1 -> ctrl length field (11 - 2) = 9 -> 7 + 2
    compressed = head + bytes([(7 << 5) | 0, 2, 0])
    header = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\n"
              "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA binary_compressed\n").encode()
    path = tmp_path / "c.pcd"
    path.write_bytes(header + struct.pack("<II", len(compressed), len(raw)) + compressed)
    points = read_points(path).points
    assert_close(points, np.column_stack([x, y, z]), what="decompressed points")


def test_organised_pcd_drops_nan_points(tmp_path):
    path = tmp_path / "o.pcd"
    path.write_text("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\n"
                    "HEIGHT 2\nPOINTS 4\nDATA ascii\n1 2 3\nnan nan nan\n4 5 6\nnan nan nan\n")
    assert read_points(path).points.shape == (2, 3)


def test_xyz_with_column_header_and_extra_columns(tmp_path):
    path = tmp_path / "c.csv"
    path.write_text("x,y,z,intensity\n1,2,3,0.5\n4,5,6,0.7\n")
    assert_close(read_points(path).points, [[1, 2, 3], [4, 5, 6]])


def test_missing_and_unknown(tmp_path):
    with pytest.raises(InputFileNotFoundError):
        read_points(tmp_path / "none.xyz")
    (tmp_path / "c.las").write_text("x")
    with pytest.raises(UnsupportedFormatError, match=r"\.pcd"):
        read_points(tmp_path / "c.las")


@pytest.mark.parametrize("name, content, message", [
    ("t.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 10\n"
              b"HEIGHT 1\nPOINTS 10\nDATA binary\n" + bytes(100), "truncated"),
    ("h.pcd", b"VERSION 0.7\nFIELDS x y z\nDATA ascii\n1 2 3\n", "incomplete PCD header"),
    ("n.pcd", b"VERSION 0.7\nFIELDS a b\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nPOINTS 1\nDATA ascii\n1 2\n",
     "no x, y, z"),
    ("t.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty double x\n"
              b"property double y\nproperty double z\nend_header\n" + bytes(30), "truncated"),
    ("g.ply", b"not a ply\n", "does not start with 'ply'"),
    ("g.xyz", b"1 2 3\n4 five 6\n", "not numeric"),
    ("s.xyz", b"1 2\n", "expected x y z"),
    ("e.xyz", b"# nothing\n", "no x y z rows"),
    ("g.npy", b"\x93NUMPY garbage", "not a valid .npy"),
])
def test_corrupt_files(tmp_path, name, content, message):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(CorruptFileError, match=message):
        read_points(tmp_path / name)


def test_npy_shape_and_non_finite(tmp_path):
    np.save(tmp_path / "flat.npy", np.zeros(9))
    with pytest.raises(CorruptFileError, match=r"\(N, 3\)"):
        read_points(tmp_path / "flat.npy")
    np.save(tmp_path / "complex.npy", np.ones((10, 3), complex))  # not read as its real part
    with pytest.raises(CorruptFileError, match=r"real \(N, 3\) array, found complex128"):
        read_points(tmp_path / "complex.npy")
    np.save(tmp_path / "nan.npy", np.array([[0, 0, 0], [np.inf, 0, 0]], float))
    with pytest.raises(InvalidGeometryError, match="non-finite"):
        read_points(tmp_path / "nan.npy")
    with pytest.raises(InvalidGeometryError, match="empty"):
        PointCloud(np.zeros((0, 3)))
