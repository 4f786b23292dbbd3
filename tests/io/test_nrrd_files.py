"""NRRD volumes (.nrrd, .nhdr): exact round trips, hand-written headers (short space names, cell
centering, big endian, detached data), refusals, and atomic writes."""

from __future__ import annotations

from pathlib import Path

import nrrd
import numpy as np
import pytest

from comreg_core.errors import (ComRegError, CorruptFileError, InputFileNotFoundError,
                                MissingSpatialMetadataError)
from comreg_core.io.segmentations import read_segmentation, write_segmentation
from comreg_core.io.volumes import read_volume, write_volume
from tests.helpers import assert_close
from tests.io.volume_helpers import (DTYPES, assert_same_volume, make_segmentation, make_volume,
                                     write_text_nrrd)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("space", ["LPS", "RAS"])
@pytest.mark.parametrize("compress", [True, False])
def test_nrrd_round_trip_is_exact(tmp_path, dtype, space, compress):
    volume = make_volume(1, dtype, space)
    path = write_volume(volume, tmp_path / "v.nrrd", compress=compress)
    header = nrrd.read_header(str(path))
    assert header["encoding"] == ("gzip" if compress else "raw")
    assert header["space"] == {"LPS": "left-posterior-superior",
                               "RAS": "right-anterior-superior"}[space]
    assert header["kinds"] == ["domain"] * 3
    back = read_volume(path)
    assert back.space == space and back.path == path
    assert_same_volume(back, volume)


def test_nrrd_short_space_names_cell_centering_and_big_endian(tmp_path):
    values = np.arange(24, dtype=">i2").reshape((2, 3, 4), order="F")
    path = write_text_nrrd(tmp_path / "v.nrrd", [
        "type: short", "dimension: 3", "space: RAS", "sizes: 2 3 4",
        "space directions: (0,0.5,0) (2,0,0) (0,0,-1.5)", "kinds: space space space",
        "centerings: cell cell cell", "endian: big", "encoding: raw",
        "space origin: (10,-20,30.25)"], values.tobytes(order="F"))
    volume = read_volume(path)
    assert volume.space == "RAS"
    np.testing.assert_array_equal(volume.array, values.astype(np.int16))
    # 'space origin' is the first sample's centre whatever the centering: no half-voxel shift.
    expected = np.array([[0, 2, 0, 10], [0.5, 0, 0, -20], [0, 0, -1.5, 30.25], [0, 0, 0, 1]])
    assert_close(volume.ijk_to_space, expected, what="ijk_to_space")


def test_detached_nhdr_is_read(tmp_path):
    volume = make_volume(2, np.float32)
    header = {"space": "left-posterior-superior", "space directions": volume.ijk_to_space[:3, :3].T,
              "space origin": volume.origin, "kinds": ["domain"] * 3, "encoding": "gzip"}
    nrrd.write(str(tmp_path / "v.nhdr"), volume.array, header)
    assert (tmp_path / "v.raw.gz").is_file()
    assert_same_volume(read_volume(tmp_path / "v.nhdr"), volume)
    (tmp_path / "v.raw.gz").unlink()
    with pytest.raises(InputFileNotFoundError):
        read_volume(tmp_path / "v.nhdr")


def test_nrrd_without_spatial_metadata_is_refused(tmp_path):
    nrrd.write(str(tmp_path / "plain.nrrd"), np.zeros((3, 3, 3), np.uint8))
    with pytest.raises(MissingSpatialMetadataError, match="'space directions'"):
        read_volume(tmp_path / "plain.nrrd")
    nrrd.write(str(tmp_path / "spacings.nrrd"), np.zeros((3, 3, 3), np.uint8),
               {"spacings": [1.0, 1.0, 2.0]})
    with pytest.raises(MissingSpatialMetadataError, match="no spatial metadata"):
        read_segmentation(tmp_path / "spacings.nrrd")
    nrrd.write(str(tmp_path / "no_origin.nrrd"), np.zeros((3, 3, 3), np.uint8),
               {"space": "left-posterior-superior", "space directions": np.eye(3)})
    with pytest.raises(MissingSpatialMetadataError, match="'space origin'"):
        read_volume(tmp_path / "no_origin.nrrd")


@pytest.mark.parametrize("space_line", ["space: scanner-xyz", "space: 3D-right-handed",
                                        "space dimension: 3"])
def test_nrrd_in_a_non_patient_space_is_refused(tmp_path, space_line):
    path = write_text_nrrd(tmp_path / "v.nrrd", [
        "type: uchar", "dimension: 3", space_line, "sizes: 2 2 2",
        "space directions: (1,0,0) (0,1,0) (0,0,1)", "encoding: raw",
        "space origin: (0,0,0)"], bytes(8))
    with pytest.raises(ComRegError, match="LPS") as info:
        read_volume(path)
    assert not isinstance(info.value, CorruptFileError)


def _nrrd_write_failing_midway(file, *args, **kwargs):
    Path(file).write_bytes(b"half a file")
    raise OSError("disk full")


def test_failed_nrrd_write_leaves_old_file_and_no_temp(tmp_path, monkeypatch):
    target = tmp_path / "v.nrrd"
    write_volume(make_volume(13), target)
    before = target.read_bytes()
    monkeypatch.setattr(nrrd, "write", _nrrd_write_failing_midway)
    with pytest.raises(OSError, match="disk full"):
        write_volume(make_volume(14), target)
    with pytest.raises(OSError, match="disk full"):
        write_segmentation(make_segmentation(), tmp_path / "s.seg.nrrd")
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.nrrd"]
