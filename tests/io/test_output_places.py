"""The one output-place validator (``check_output_file`` / ``check_output_folder``) and readers
that compare the counts a header declares with the file size before allocating."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from comreg_core.errors import CorruptFileError, InputFileNotFoundError, OutputPlaceError
from comreg_core.io import read_mesh, read_points
from comreg_core.io._files import (check_output_file, check_output_folder, is_run_folder,
                                   require_input_file)
from tests.helpers import assert_close, immutable


def _run_folder(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "checkpoint.pt").write_bytes(b"")
    return path


def test_a_new_file_in_a_new_folder_is_fine_and_nothing_is_made(tmp_path):
    out = check_output_file(tmp_path / "a" / "b" / "bone.stl")
    assert out == tmp_path / "a" / "b" / "bone.stl"
    assert check_output_folder(tmp_path / "c") == tmp_path / "c"
    assert list(tmp_path.iterdir()) == []  # the checks create nothing (not even a probe file)


def test_wrong_kinds_are_refused(tmp_path):
    (tmp_path / "x.stl").mkdir()
    with pytest.raises(OutputPlaceError, match="is an existing folder, not a file"):
        check_output_file(tmp_path / "x.stl")
    (tmp_path / "taken").write_text("")
    with pytest.raises(OutputPlaceError, match="exists and is not a folder"):
        check_output_folder(tmp_path / "taken")
    # under a regular file: refused for root as for anyone (chmod would not stop root)
    with pytest.raises(OutputPlaceError, match="'.*taken' is a file, not a folder"):
        check_output_folder(tmp_path / "taken" / "sub" / "deeper")
    with pytest.raises(OutputPlaceError, match="is a file, not a folder"):
        check_output_file(tmp_path / "taken" / "out.ply")


def test_inputs_and_run_folders_are_refused(tmp_path):
    mesh = tmp_path / "bone.stl"
    mesh.write_text("")
    with pytest.raises(OutputPlaceError, match="also an input"):
        check_output_file(tmp_path / "." / "bone.stl", inputs=[None, mesh])
    run = _run_folder(tmp_path / "run")
    assert is_run_folder(run) and not is_run_folder(tmp_path)
    with pytest.raises(OutputPlaceError, match="is the pretraining run folder"):
        check_output_folder(run)
    with pytest.raises(OutputPlaceError, match="inside the pretraining run folder"):
        check_output_folder(run / "new" / "sub")
    with pytest.raises(OutputPlaceError, match="inside the pretraining run folder"):
        check_output_file(run / "config.yaml")
    assert check_output_folder(run, run_folder_ok=True) == run  # what pretrain itself does


def test_an_immutable_folder_is_refused_even_for_root(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    with immutable(locked):
        with pytest.raises(OutputPlaceError, match="not writable .operation not permitted"):
            check_output_folder(locked / "out")
        with pytest.raises(OutputPlaceError, match="not writable"):
            check_output_file(locked / "bone.stl")


def test_a_folder_given_as_an_input_file_is_called_a_folder(tmp_path):
    with pytest.raises(InputFileNotFoundError, match="is a folder, not a file"):
        require_input_file(tmp_path, "mesh file")
    with pytest.raises(InputFileNotFoundError, match="does not exist"):
        require_input_file(tmp_path / "nope.stl", "mesh file")
    if Path("/dev/null").exists():
        with pytest.raises(InputFileNotFoundError, match="is not a regular file"):
            require_input_file("/dev/null", "mesh file")


# --- declared counts against the file size ---------------------------------------------------------

PLY_HEAD = (b"ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\n"
            b"property float y\nproperty float z\nend_header\n")


@pytest.mark.parametrize("count", [4_000_000_000, 4])
def test_binary_ply_shorter_than_its_header_says(tmp_path, count):
    path = tmp_path / "p.ply"
    path.write_bytes(PLY_HEAD % count + np.zeros((3, 3), "<f4").tobytes())
    with pytest.raises(CorruptFileError, match=f"'vertex' x {count:,}.*only 36"):
        read_points(path)
    with pytest.raises(CorruptFileError, match="only 36"):
        read_mesh(path)  # checked before VTK's reader, which crashed on the 4e9 header


def test_ascii_ply_and_pcd_headers_are_checked(tmp_path):
    ply = tmp_path / "a.ply"
    ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 900000\nproperty float x\n"
                    b"property float y\nproperty float z\nend_header\n0 0 0\n")
    with pytest.raises(CorruptFileError, match="900,000"):
        read_points(ply)
    negative = tmp_path / "n.ply"
    negative.write_bytes(PLY_HEAD % -5)
    with pytest.raises(CorruptFileError, match="declares -5"):
        read_points(negative)
    pcd = tmp_path / "c.pcd"
    pcd.write_bytes(b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                    b"WIDTH 5000000000\nHEIGHT 1\nPOINTS 5000000000\nDATA binary_compressed\n"
                    + struct.pack("<II", 10, 4_000_000) + bytes(10))
    with pytest.raises(CorruptFileError, match="does not match the header"):
        read_points(pcd)


def test_a_well_formed_ply_still_reads(tmp_path):
    from comreg_core.io import PointCloud, write_points

    points = np.random.default_rng(0).normal(size=(50, 3)) * 10
    for binary in (True, False):
        path = write_points(PointCloud(points), tmp_path / f"p{binary}.ply", binary=binary)
        assert_close(read_points(path).points, points, atol=1e-12, what="points read back")
