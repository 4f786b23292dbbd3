"""MetaImage volumes (.mha, .mhd): round trips, header fields kept verbatim, big-endian data
cross-checked with SimpleITK, refusals, and atomic writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from comreg_core.errors import ComRegError, InputFileNotFoundError, MissingSpatialMetadataError
from comreg_core.io.metaimage_files import read_metaimage_header
from comreg_core.io.volumes import read_volume, write_volume
from tests.helpers import assert_close
from tests.io.volume_helpers import assert_same_volume, make_volume, sitk_array, sitk_geometry


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.uint32, np.int64, np.float32,
                                   np.float64])
@pytest.mark.parametrize("ext", [".mha", ".mhd"])
@pytest.mark.parametrize("compress", [True, False])
def test_metaimage_round_trip(tmp_path, dtype, ext, compress):
    volume = make_volume(3, dtype)
    path = write_volume(volume, tmp_path / f"v{ext}", compress=compress)
    fields, offset = read_metaimage_header(path)
    assert fields["CompressedData"] == str(compress)
    if ext == ".mhd":
        data_name = "v.zraw" if compress else "v.raw"
        assert fields["ElementDataFile"] == data_name and (tmp_path / data_name).is_file()
        assert offset == path.stat().st_size
    back = read_volume(path)
    assert back.space == "LPS"
    assert_same_volume(back, volume, atol=1e-12)


def test_metaimage_written_from_ras_is_converted_to_lps(tmp_path):
    volume = make_volume(4, np.int16, "RAS")
    back = read_volume(write_volume(volume, tmp_path / "v.mha"))
    assert back.space == "LPS"
    assert_same_volume(back, volume.in_space("LPS"), atol=1e-12)


def test_metaimage_header_keeps_custom_fields_and_big_endian_data(tmp_path):
    values = np.arange(2 * 3 * 2, dtype=np.uint16).reshape((2, 3, 2), order="F") * 1000
    header = ("ObjectType = Image\nNDims = 3\nBinaryData = True\nElementByteOrderMSB = True\n"
              "Position = 1 2 3\nOrientation = 0 1 0 -1 0 0 0 0 1\nElementSpacing = 2 3 4\n"
              "DimSize = 2 3 2\nPlusCustom_Field = keep  this  verbatim\n"
              "ElementType = MET_USHORT\nElementDataFile = LOCAL\n").encode()
    path = tmp_path / "v.mha"
    path.write_bytes(header + values.astype(">u2").tobytes(order="F"))
    fields, offset = read_metaimage_header(path)
    assert list(fields)[:2] == ["ObjectType", "NDims"] and list(fields)[-1] == "ElementDataFile"
    assert fields["PlusCustom_Field"] == "keep  this  verbatim"
    assert offset == len(header)
    volume = read_volume(path)
    np.testing.assert_array_equal(volume.array, values)
    assert volume.array.dtype == np.uint16
    expected = np.array([[0, -3, 0, 1], [2, 0, 0, 2], [0, 0, 4, 3], [0, 0, 0, 1]])
    assert_close(volume.ijk_to_space, expected, what="ijk_to_space")
    sitk_image = sitk.ReadImage(str(path))
    assert_close(volume.ijk_to_space, sitk_geometry(sitk_image), atol=1e-12, what="vs SimpleITK")
    np.testing.assert_array_equal(volume.array, sitk_array(sitk_image))


def test_metaimage_refusals(tmp_path):
    base = "NDims = 3\nDimSize = 2 2 2\nElementType = MET_UCHAR\n"
    no_geometry = tmp_path / "nogeo.mha"
    no_geometry.write_bytes(f"{base}ElementDataFile = LOCAL\n".encode() + bytes(8))
    with pytest.raises(MissingSpatialMetadataError):
        read_volume(no_geometry)
    rgb = tmp_path / "rgb.mha"
    rgb.write_bytes(f"{base}ElementSpacing = 1 1 1\nElementNumberOfChannels = 3\n"
                    "ElementDataFile = LOCAL\n".encode() + bytes(24))
    with pytest.raises(ComRegError, match="3 values per voxel"):
        read_volume(rgb)
    missing_raw = tmp_path / "v.mhd"
    missing_raw.write_text(f"{base}ElementSpacing = 1 1 1\nElementDataFile = gone.raw\n")
    with pytest.raises(InputFileNotFoundError, match="gone.raw"):
        read_volume(missing_raw)


@pytest.mark.parametrize("ext", [".mha", ".mhd"])
def test_failed_metaimage_write_leaves_nothing(tmp_path, monkeypatch, ext):
    real = Path.write_bytes
    calls = []

    def write_bytes(self, data):
        calls.append(self.name)
        if len(calls) == (2 if ext == ".mhd" else 1):  # the header of a .mhd, the .mha itself
            real(self, data[:10])
            raise OSError("disk full")
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", write_bytes)
    with pytest.raises(OSError, match="disk full"):
        write_volume(make_volume(15), tmp_path / f"v{ext}")
    assert list(tmp_path.iterdir()) == []
