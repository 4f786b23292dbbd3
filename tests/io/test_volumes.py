"""Volume I/O across formats (NRRD and MetaImage), cross-checked with SimpleITK as an independent
reader and writer, and every bad input: missing files, unknown extensions, truncated, damaged and
garbage files, broken header values."""

from __future__ import annotations

import zlib

import numpy as np
import pytest
import SimpleITK as sitk

from comreg_core.errors import (ComRegError, CorruptFileError, InputFileNotFoundError,
                                UnsupportedFormatError)
from comreg_core.io.metaimage_files import read_metaimage_header
from comreg_core.io.segmentations import read_segmentation, write_segmentation
from comreg_core.io.volumes import read_volume, write_volume
from tests.helpers import assert_close, random_rigid
from tests.io.volume_helpers import (make_segmentation, make_volume, sitk_array, sitk_geometry,
                                     write_text_nrrd)


@pytest.mark.parametrize("name", ["v.nrrd", "v.mha", "v.mhd"])
@pytest.mark.parametrize("space", ["LPS", "RAS"])
def test_simpleitk_reads_what_we_write(tmp_path, name, space):
    volume = make_volume(5, np.float32, space)
    path = write_volume(volume, tmp_path / name)
    image = sitk.ReadImage(str(path))
    lps = volume.in_space("LPS")
    assert_close(image.GetSpacing(), lps.spacing, atol=1e-9, what="spacing")
    assert_close(image.GetOrigin(), lps.origin, atol=1e-9, what="origin")
    assert_close(np.reshape(image.GetDirection(), (3, 3)), lps.directions, atol=1e-9,
                 what="direction")
    np.testing.assert_array_equal(sitk_array(image), volume.array)


@pytest.mark.parametrize("name", ["v.nrrd", "v.mha", "v.mhd"])
@pytest.mark.parametrize("compress", [True, False])
def test_we_read_what_simpleitk_writes(tmp_path, name, compress):
    rng = np.random.default_rng(6)
    array_kji = rng.integers(-1000, 3000, (4, 6, 9)).astype(np.int16)
    image = sitk.GetImageFromArray(array_kji)
    image.SetSpacing((0.3, 0.9, 2.5))
    image.SetOrigin((-12.5, 40.0, 7.25))
    image.SetDirection(random_rigid(rng)[:3, :3].ravel().tolist())
    sitk.WriteImage(image, str(tmp_path / name), useCompression=compress)
    volume = read_volume(tmp_path / name)
    assert volume.space == "LPS"
    np.testing.assert_array_equal(volume.array, array_kji.transpose(2, 1, 0))
    assert_close(volume.ijk_to_space, sitk_geometry(image), atol=1e-9, what="ijk_to_space")


def test_real_plus_reconstructions_match_simpleitk(shared_data):
    for name, shape in [("SpinePhantomFreehandReconstructed.mha", (147, 106, 104)),
                        ("NwirePhantomFreehandReconstructed.mha", (101, 104, 74))]:
        path = shared_data / "plus" / "TestImages" / name
        volume = read_volume(path)
        image = sitk.ReadImage(str(path))
        assert volume.array.shape == shape and volume.array.dtype == np.uint8
        assert volume.space == "LPS"
        np.testing.assert_array_equal(volume.array, sitk_array(image))
        assert_close(volume.ijk_to_space, sitk_geometry(image), atol=1e-12, what=name)
        assert_close(volume.spacing, [0.5, 0.5, 0.5], what="spacing")
        assert volume.array.max() > 0  # real reconstructed echoes, not an empty grid
        fields, _ = read_metaimage_header(path)
        assert fields["Kinds"] == "domain domain list"  # PLUS's custom field, kept verbatim
    fields, offset = read_metaimage_header(shared_data / "plus" / "TestImages" /
                                           "NwirePhantomFreehand.igs.mha")
    assert fields["DimSize"] == "820 616 97" and fields["ElementDataFile"] == "LOCAL"
    assert fields["Seq_Frame0000_ImageStatus"] == "OK" and offset > 0


@pytest.mark.parametrize("name", ["NwirePhantomFreehand.igs.mha", "NwirePhantomFreehand.igs.nrrd"])
def test_ultrasound_sequences_are_not_volumes(shared_data, name):
    path = shared_data / "plus" / "TestImages" / name
    with pytest.raises(ComRegError, match="tracked ultrasound sequence"):
        read_volume(path)


def test_missing_file_and_unknown_extension(tmp_path):
    with pytest.raises(InputFileNotFoundError):
        read_volume(tmp_path / "nope.nrrd")
    with pytest.raises(InputFileNotFoundError):
        read_segmentation(tmp_path / "nope.seg.nrrd")
    (tmp_path / "scan.png").write_bytes(b"x")
    with pytest.raises(UnsupportedFormatError):
        read_volume(tmp_path / "scan.png")
    with pytest.raises(UnsupportedFormatError):
        read_segmentation(tmp_path / "scan.png")
    with pytest.raises(UnsupportedFormatError):
        write_volume(make_volume(9), tmp_path / "out.nii")
    with pytest.raises(UnsupportedFormatError):
        write_segmentation(make_segmentation(), tmp_path / "out.mha")


@pytest.mark.parametrize("name", ["v.nrrd", "v.mha"])
@pytest.mark.parametrize("compress", [True, False])
def test_truncated_files_are_corrupt(tmp_path, name, compress):
    path = write_volume(make_volume(10, np.float32, shape=(12, 10, 8)), tmp_path / name,
                        compress=compress)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 100])
    with pytest.raises(CorruptFileError, match="v\\.(nrrd|mha)"):
        read_volume(path)


def test_damaged_compressed_data_and_wrong_sizes_are_corrupt(tmp_path):
    path = write_volume(make_volume(11, np.float32, shape=(12, 10, 8)), tmp_path / "v.nrrd")
    data = bytearray(path.read_bytes())
    data[-200:-150] = bytes(50)
    path.write_bytes(bytes(data))
    with pytest.raises(CorruptFileError):
        read_volume(path)
    mha = write_volume(make_volume(11), tmp_path / "v.mha")
    mha.write_bytes(mha.read_bytes().replace(b"DimSize = 7 5 4", b"DimSize = 7 5 5"))
    with pytest.raises(CorruptFileError, match="need 350 bytes .* holds 280"):
        read_volume(mha)
    mha.write_bytes(b"NDims = 3\nDimSize = 2 2 2\nElementSpacing = 1 1 1\n"
                    b"ElementType = MET_UCHAR\nCompressedData = True\nElementDataFile = LOCAL\n"
                    + zlib.compress(bytes(8))[:-4])
    with pytest.raises(CorruptFileError, match="end early"):
        read_volume(mha)
    bad_sizes = write_text_nrrd(tmp_path / "sizes.nrrd", [
        "type: uchar", "dimension: 3", "space: LPS", "sizes: 2 2 3",
        "space directions: (1,0,0) (0,1,0) (0,0,1)", "encoding: raw",
        "space origin: (0,0,0)"], bytes(8))
    with pytest.raises(CorruptFileError, match="sizes.* need 12 voxel values but the file "
                                               "holds 8"):
        read_volume(bad_sizes)


@pytest.mark.parametrize("compress", [True, False])
def test_a_truncated_mhd_data_file_is_named(tmp_path, compress):
    path = write_volume(make_volume(10, np.float32, shape=(12, 10, 8)), tmp_path / "v.mhd",
                        compress=compress)
    data_file = tmp_path / ("v.zraw" if compress else "v.raw")
    data = data_file.read_bytes()
    data_file.write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptFileError, match=r"v\.z?raw.*(end early|holds).*voxel data of "
                                               r".*v\.mhd"):
        read_volume(path)


@pytest.mark.parametrize("name", ["junk.nrrd", "junk.mha", "junk.mhd", "junk.seg.nrrd"])
def test_garbage_headers_are_corrupt(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(np.random.default_rng(12).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    reader = read_segmentation if name.endswith(".seg.nrrd") else read_volume
    with pytest.raises(CorruptFileError):
        reader(path)
    path.write_bytes(b"")
    with pytest.raises(CorruptFileError):
        reader(path)


def test_broken_header_values_are_corrupt(tmp_path):
    path = tmp_path / "v.mha"
    path.write_bytes(b"NDims = 3\nDimSize = 2 two 2\nElementType = MET_UCHAR\n"
                     b"ElementDataFile = LOCAL\n" + bytes(8))
    with pytest.raises(CorruptFileError, match="DimSize"):
        read_volume(path)
    path.write_bytes(b"NDims = 3\nDimSize = 2 2 2\nElementType = MET_COMPLEX\n"
                     b"ElementDataFile = LOCAL\n" + bytes(8))
    with pytest.raises(CorruptFileError, match="ElementType"):
        read_volume(path)
    nrrd_path = write_text_nrrd(tmp_path / "v.nrrd", [
        "type: uchar", "dimension: 3", "space: LPS", "sizes: 2 2 2",
        "space directions: (1,0,0) (0,0,0) (0,0,1)", "encoding: raw",
        "space origin: (0,0,0)"], bytes(8))
    with pytest.raises(CorruptFileError, match="degenerate"):
        read_volume(nrrd_path)
