"""Volume and segmentation I/O: NRRD, MetaImage and 3D Slicer .seg.nrrd, cross-checked with
SimpleITK as an independent reader and writer."""

from __future__ import annotations

import zlib
from pathlib import Path

import nrrd
import numpy as np
import pytest
import SimpleITK as sitk

from comreg_core.errors import (
    ComRegError,
    CorruptFileError,
    EmptyMaskError,
    InputFileNotFoundError,
    LabelNotFoundError,
    MissingSpatialMetadataError,
    UnsupportedFormatError,
)
from comreg_core.io.volumes import (
    Segment,
    Segmentation,
    Volume,
    read_metaimage_header,
    read_segmentation,
    read_volume,
    write_segmentation,
    write_volume,
)
from tests.helpers import assert_close, random_rigid

DTYPES = [np.uint8, np.int8, np.int16, np.uint16, np.int32, np.uint32, np.float32, np.float64]


def make_volume(seed: int, dtype=np.int16, space: str = "LPS", shape=(7, 5, 4)) -> Volume:
    """A random volume on an oblique, anisotropic grid."""
    rng = np.random.default_rng(seed)
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        array = rng.integers(max(info.min, -30000), min(info.max, 30000), shape, endpoint=True)
    else:
        array = rng.normal(0.0, 1000.0, shape)
    rotation = random_rigid(rng)[:3, :3]
    spacing = rng.uniform(0.2, 3.0, 3)
    origin = rng.uniform(-200.0, 200.0, 3)
    return Volume.from_geometry(array.astype(dtype), spacing, origin, rotation, space)


def sitk_geometry(image: sitk.Image) -> np.ndarray:
    """SimpleITK's ijk -> LPS matrix."""
    M = np.eye(4)
    M[:3, :3] = np.reshape(image.GetDirection(), (3, 3)) * np.asarray(image.GetSpacing())
    M[:3, 3] = image.GetOrigin()
    return M


def sitk_array(image: sitk.Image) -> np.ndarray:
    """Voxels as ``[i, j, k]`` (SimpleITK's arrays are ``[k, j, i]``)."""
    return sitk.GetArrayFromImage(image).transpose(2, 1, 0)


def assert_same_volume(actual: Volume, expected: Volume, atol: float = 0.0) -> None:
    assert actual.array.shape == expected.array.shape
    assert actual.array.dtype == expected.array.dtype
    np.testing.assert_array_equal(actual.array, expected.array)
    expected = expected.in_space(actual.space)
    assert_close(actual.ijk_to_space, expected.ijk_to_space, atol=atol, what="ijk_to_space")
    assert_close(actual.spacing, expected.spacing, atol=max(atol, 1e-12), what="spacing")
    assert_close(actual.origin, expected.origin, atol=atol, what="origin")
    assert_close(actual.directions, expected.directions, atol=max(atol, 1e-12), what="directions")


def write_text_nrrd(path: Path, header_lines: list[str], data: bytes) -> Path:
    path.write_bytes(("NRRD0004\n" + "\n".join(header_lines) + "\n\n").encode() + data)
    return path


# ---- NRRD ---------------------------------------------------------------------------------------


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


# ---- MetaImage ----------------------------------------------------------------------------------


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


# ---- SimpleITK cross-checks ---------------------------------------------------------------------


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


# ---- Segmentations ------------------------------------------------------------------------------


def make_segmentation(seed: int = 7) -> Segmentation:
    """3 segments in 2 layers: 'femur' (1) and 'tibia' (2) share layer 0; 'cartilage' (1)
    overlaps them in layer 1."""
    rng = np.random.default_rng(seed)
    layers = np.zeros((2, 10, 8, 6), np.uint8)
    layers[0, 1:4, 2:6, 1:3] = 1
    layers[0, 5:9, 1:7, 2:5] = 2
    layers[1, 2:7, 3:5, 1:4] = 1
    M = np.eye(4)
    M[:3, :3] = random_rigid(rng)[:3, :3] * [0.4, 0.6, 1.2]
    M[:3, 3] = rng.uniform(-50, 50, 3)
    segments = [Segment("femur", 1, 0, "Segment_1", (0.9, 0.8, 0.1)),
                Segment("tibia", 2, 0, "Segment_2", (0.1, 0.5, 0.25)),
                Segment("cartilage", 1, 1, "Segment_3", (0.3, 0.3, 0.3))]
    return Segmentation(layers, M, "LPS", segments)


def test_seg_nrrd_round_trip_with_layers(tmp_path):
    seg = make_segmentation()
    path = write_segmentation(seg, tmp_path / "bones.seg.nrrd")
    header = nrrd.read_header(str(path))
    assert header["dimension"] == 4 and header["kinds"] == ["list", "domain", "domain", "domain"]
    assert header["Segment1_Name"] == "tibia" and header["Segment1_LabelValue"] == "2"
    assert header["Segment2_Layer"] == "1" and header["Segment0_Extent"] == "1 3 2 5 1 2"
    assert header["Segmentation_MasterRepresentation"] == "Binary labelmap"
    assert header["Segmentation_ContainedRepresentationNames"] == "Binary labelmap|"
    back = read_segmentation(path)
    np.testing.assert_array_equal(back.layers, seg.layers)
    assert_close(back.ijk_to_space, seg.ijk_to_space, what="ijk_to_space")
    assert back.space == "LPS" and back.path == path
    assert [(s.name, s.id, s.label_value, s.layer) for s in back.segments] == \
        [(s.name, s.id, s.label_value, s.layer) for s in seg.segments]
    for got, want in zip(back.segments, seg.segments):
        assert_close(got.color, want.color, what=f"{got.name} colour")
        np.testing.assert_array_equal(back.mask(got), seg.mask(want))
    # A multi-layer segmentation is not a volume.
    with pytest.raises(ComRegError, match="read_segmentation"):
        read_volume(path)


def test_single_layer_seg_nrrd_is_3d_and_reads_as_volume_too(tmp_path):
    seg = make_segmentation()
    single = Segmentation(seg.layers[0].astype(np.int32), seg.ijk_to_space, "RAS",
                          seg.segments[:2])
    path = write_segmentation(single, tmp_path / "one.seg.nrrd", compress=False)
    header = nrrd.read_header(str(path))
    assert header["dimension"] == 3 and header["type"] == "uint8"
    back = read_segmentation(path)
    assert back.layers.shape == (1, 10, 8, 6) and back.space == "RAS"
    np.testing.assert_array_equal(back.layers, single.layers)
    assert [s.name for s in back.segments] == ["femur", "tibia"]
    np.testing.assert_array_equal(read_volume(path).array, single.layers[0])
    # A 4D file whose list axis has one entry is still a plain volume.
    nrrd.write(str(tmp_path / "one_layer_4d.nrrd"), single.layers.astype(np.uint8), {
        "space": "right-anterior-superior", "space origin": single.ijk_to_space[:3, 3],
        "space directions": np.vstack([np.full(3, np.nan), single.ijk_to_space[:3, :3].T]),
        "kinds": ["list", "domain", "domain", "domain"]})
    volume = read_volume(tmp_path / "one_layer_4d.nrrd")
    np.testing.assert_array_equal(volume.array, single.layers[0])
    assert_close(volume.ijk_to_space, single.ijk_to_space, what="ijk_to_space")


def test_legacy_slicer_fields_without_layer_and_label_value(tmp_path):
    masks = np.zeros((2, 4, 4, 4), np.uint8)
    masks[0, :2] = 1
    masks[1, 1:] = 1
    legacy = {f"Segment{i}_{key}": value for i, name in enumerate(["a", "b"])
              for key, value in [("ID", name), ("Name", name), ("Color", "1 0 0")]}
    lps = {"space": "left-posterior-superior", "space origin": [0.0, 0.0, 0.0]}
    nrrd.write(str(tmp_path / "old.seg.nrrd"), masks, {
        **lps, **legacy, "space directions": np.vstack([np.full(3, np.nan), np.eye(3)]),
        "kinds": ["list", "domain", "domain", "domain"]})
    seg = read_segmentation(tmp_path / "old.seg.nrrd")  # Slicer <= 4.10: one mask per layer
    assert [(s.layer, s.label_value) for s in seg.segments] == [(0, 1), (1, 1)]
    np.testing.assert_array_equal(seg.mask(seg.find_segment(name="b")), masks[1] == 1)
    labels = masks[0] + 2 * (masks[1] & ~masks[0])
    nrrd.write(str(tmp_path / "flat.seg.nrrd"), labels,
               {**lps, **legacy, "space directions": np.eye(3)})
    seg = read_segmentation(tmp_path / "flat.seg.nrrd")  # one label map: values i + 1
    assert [(s.layer, s.label_value) for s in seg.segments] == [(0, 1), (0, 2)]


def test_find_segment_and_mask(tmp_path):
    seg = make_segmentation()
    seg.path = tmp_path / "bones.seg.nrrd"
    assert seg.find_segment(name="tibia").label_value == 2
    assert seg.find_segment(name="Segment_3").name == "cartilage"
    assert seg.find_segment(label=2).name == "tibia"
    with pytest.raises(LabelNotFoundError, match="used by 2 segments"):
        seg.find_segment(label=1)
    with pytest.raises(LabelNotFoundError, match="no segment named 'fibula'.*'femur'"):
        seg.find_segment(name="fibula")
    with pytest.raises(LabelNotFoundError, match="No segment has label value 9"):
        seg.find_segment(label=9)
    with pytest.raises(LabelNotFoundError, match="3 segments"):
        seg.find_segment()
    mask = seg.mask(seg.find_segment(name="femur"))
    assert mask.dtype == bool and mask.shape == (10, 8, 6) and mask.sum() == 3 * 4 * 2
    with pytest.raises(EmptyMaskError, match="'ghost'"):
        seg.mask(Segment("ghost", 7))
    with pytest.raises(EmptyMaskError):
        Segmentation(np.zeros((3, 3, 3), np.uint8), np.eye(4)).find_segment()


@pytest.mark.parametrize("name", ["labels.nrrd", "labels.mha", "labels.mhd"])
def test_plain_label_map_reads_as_segmentation(tmp_path, name):
    seg = make_segmentation()
    labels = Volume(seg.layers[0].astype(np.int16), seg.ijk_to_space)
    write_volume(labels, tmp_path / name)
    back = read_segmentation(tmp_path / name)
    assert [(s.name, s.label_value, s.layer) for s in back.segments] == \
        [("Label 1", 1, 0), ("Label 2", 2, 0)]
    np.testing.assert_array_equal(back.layers[0], labels.array)
    assert_close(back.ijk_to_space, seg.ijk_to_space, atol=1e-12, what="ijk_to_space")


def test_intensity_volume_is_not_a_label_map(tmp_path):
    write_volume(make_volume(8, np.float32), tmp_path / "ct.nrrd")
    with pytest.raises(ComRegError, match="segment the bone first"):
        read_segmentation(tmp_path / "ct.nrrd")
    write_volume(make_volume(8, np.int16), tmp_path / "ct.mha")  # HU values go negative
    with pytest.raises(ComRegError, match="segment the bone first"):
        read_segmentation(tmp_path / "ct.mha")


# ---- Bad inputs ---------------------------------------------------------------------------------


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
    with pytest.raises(CorruptFileError, match="Size of the data"):
        read_volume(bad_sizes)


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


# ---- Atomic writes ------------------------------------------------------------------------------


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
