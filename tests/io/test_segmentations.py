"""Segmentations: 3D Slicer .seg.nrrd round trips with layers, legacy Slicer fields, segment
selection and masks, plain label maps read as segmentations, intensity volumes refused."""

from __future__ import annotations

import nrrd
import numpy as np
import pytest

from comreg_core.errors import ComRegError, EmptyMaskError, LabelNotFoundError
from comreg_core.io.segmentations import (Segment, Segmentation, read_segmentation,
                                          write_segmentation)
from comreg_core.io.volumes import Volume, read_volume, write_volume
from tests.helpers import assert_close
from tests.io.volume_helpers import make_segmentation, make_volume


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
