"""PLUS sequences (.igs.mha / .igs.nrrd) and device sets: checked against PLUS's own compounded
volumes and against independent readers (SimpleITK, pynrrd, naive header parsing), synthetic
format variants, and every bad input the issue lists."""

from __future__ import annotations

import logging
import re
import zlib
from pathlib import Path

import nrrd
import numpy as np
import pytest
import SimpleITK as sitk

from comreg_core.errors import (ComRegError, CorruptFileError, InputFileNotFoundError,
                                UnsupportedFormatError)
from comreg_core.io.plus_files import read_plus_calibration, read_plus_device_set
from comreg_core.io.plus_sequences import read_plus_sequence
from comreg_core.io.sweeps import CalibrationMismatchError, NoValidFramesError
from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.surfaces.us_compounding import compounding_grid
from tests.helpers import SHARED_DATA, assert_close

PLUS = SHARED_DATA / "plus"
SPINE = PLUS / "TestImages" / "SpinePhantomFreehand.igs.mha"
SPINE_XML = PLUS / "ConfigFiles" / "Testing" / \
    "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"
SPINE_VOLUME = PLUS / "TestImages" / "SpinePhantomFreehandReconstructed.mha"
NWIRE_MHA = PLUS / "TestImages" / "NwirePhantomFreehand.igs.mha"
NWIRE_NRRD = PLUS / "TestImages" / "NwirePhantomFreehand.igs.nrrd"
NWIRE_XML = PLUS / "ConfigFiles" / "Testing" / \
    "PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml"
NWIRE_VOLUME = PLUS / "TestImages" / "NwirePhantomFreehandReconstructed.mha"
FIBULA_DIR = SHARED_DATA / "ultrabones100k-fibula"


# --- naive references ---------------------------------------------------------------------------


def naive_header(path: Path) -> dict[str, str]:
    """'Key = Value' lines of a MetaImage header, parsed with a regex, up to ElementDataFile."""
    fields = {}
    with open(path, "rb") as fh:
        for raw in fh:
            match = re.match(rb"^\s*([\w.]+)\s*=\s*(.*?)\s*$", raw)
            fields[match[1].decode()] = match[2].decode("latin-1")
            if match[1] == b"ElementDataFile":
                return fields
    raise AssertionError("no ElementDataFile")


def naive_matrix(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.split()]).reshape(4, 4)


def naive_image_to_probe(xml: Path) -> np.ndarray:
    text = xml.read_text()
    match = re.search(r'From="Image"\s+To="Probe"\s+Matrix="([^"]+)"', text)
    return naive_matrix(match[1])


def sitk_grid(path: Path):
    """Origin, size and spacing of a volume read by SimpleITK (an independent reader)."""
    image = sitk.ReadImage(str(path))
    return np.array(image.GetOrigin()), np.array(image.GetSize()), np.array(image.GetSpacing())


# --- synthetic PLUS files -------------------------------------------------------------------------


def write_plus_mha(path: Path, frames: np.ndarray, per_frame: list[dict[str, str]],
                   extra: dict[str, str] | None = None, compress: bool = True,
                   dim_frames: int | None = None) -> Path:
    """A PLUS-style sequence metafile with ``frames`` ``(N, H, W)`` uint8."""
    n, h, w = frames.shape
    data = np.ascontiguousarray(frames, dtype=np.uint8).tobytes()
    if compress:
        data = zlib.compress(data)
    header = {"ObjectType": "Image", "NDims": "3", "AnatomicalOrientation": "RAI",
              "BinaryData": "True", "BinaryDataByteOrderMSB": "False",
              "CompressedData": str(compress),
              **({"CompressedDataSize": str(len(data))} if compress else {}),
              "DimSize": f"{w} {h} {dim_frames if dim_frames is not None else n}",
              "ElementSpacing": "1 1 1", "ElementType": "MET_UCHAR", "Offset": "0 0 0",
              "TransformMatrix": "1 0 0 0 1 0 0 0 1", "UltrasoundImageOrientation": "MF",
              "UltrasoundImageType": "BRIGHTNESS", **(extra or {})}
    for i, record in enumerate(per_frame):
        for key, value in record.items():
            header[f"Seq_Frame{i:04d}_{key}"] = value
    header["ElementDataFile"] = "LOCAL"
    text = "".join(f"{k} = {v}\n" for k, v in header.items()).encode("latin-1")
    path.write_bytes(text + data)
    return path


def matrix_text(T: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(T))


def synthetic_records(n: int, rng: np.random.Generator) -> tuple[list[dict], np.ndarray,
                                                                  np.ndarray]:
    """Per-frame fields with random rigid ProbeToTracker / ReferenceToTracker transforms."""
    from scipy.spatial.transform import Rotation

    probe = np.repeat(np.eye(4)[None], n, axis=0)
    probe[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    probe[:, :3, 3] = rng.uniform(-100, 100, (n, 3))
    reference = np.repeat(np.eye(4)[None], n, axis=0)
    reference[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    reference[:, :3, 3] = rng.uniform(-100, 100, (n, 3))
    records = [{"ProbeToTrackerTransform": matrix_text(probe[i]),
                "ProbeToTrackerTransformStatus": "OK",
                "ReferenceToTrackerTransform": matrix_text(reference[i]),
                "ReferenceToTrackerTransformStatus": "OK",
                "Timestamp": f"{10 + 0.1 * i:.6f}", "ImageStatus": "OK"} for i in range(n)]
    return records, probe, reference


IMAGE_TO_PROBE = np.array([[0.0, 0.2, 0.0, 5.0], [-0.2, 0.0, 0.0, 40.0], [0.0, 0.0, 0.2, -1.0],
                           [0.0, 0.0, 0.0, 1.0]])


def write_device_set(path: Path, T: np.ndarray = IMAGE_TO_PROBE, image_size=None,
                     clip=None) -> Path:
    scan = (f'<ScanConversion OutputImageSizePixel="{image_size[0]} {image_size[1]}"/>'
            if image_size else "")
    recon = (f'<VolumeReconstruction OutputSpacing="0.5 0.5 0.5" ClipRectangleOrigin="{clip[0]} '
             f'{clip[1]}" ClipRectangleSize="10 10"/>' if clip else "")
    path.write_text(f'<PlusConfiguration version="2.3">{scan}<CoordinateDefinitions>'
                    f'<Transform From="Image" To="Probe" Matrix="{matrix_text(T)}"/>'
                    f"</CoordinateDefinitions>{recon}</PlusConfiguration>")
    return path


@pytest.fixture
def synthetic(tmp_path):
    """A 5-frame 12 x 16 px sequence with random poses, its per-frame fields and its XML."""
    rng = np.random.default_rng(7)
    frames = rng.integers(0, 255, (5, 12, 16), dtype=np.uint8)
    records, probe, reference = synthetic_records(5, rng)
    xml = write_device_set(tmp_path / "device.xml")
    return frames, records, probe, reference, xml


# --- PLUS: the reference checks -------------------------------------------------------


@pytest.fixture(scope="module")
def spine(shared_data):
    return read_plus_sequence(SPINE, calibration=SPINE_XML)


def test_spine_corners_reproduce_plus_compounded_volume(spine):
    """Done-when: the corners of every frame mapped with the composed transform reproduce the
    origin and extent of PLUS's own compounded SpinePhantomFreehand volume to 0.1 mm."""
    assert spine.frames.shape == (21, 616, 820) and spine.valid.all()
    origin, size, spacing = sitk_grid(SPINE_VOLUME)
    assert_close(spacing, [0.5, 0.5, 0.5], atol=1e-9)
    corners = spine.frame_corners().reshape(-1, 3)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    assert_close(lo, origin, atol=0.1, what="volume origin")
    # PLUS: size = int((max - min) / spacing) + 1, so the far corner lies in the last voxel
    assert np.all(hi >= origin + (size - 1) * spacing - 0.1)
    assert np.all(hi <= origin + size * spacing + 0.1)
    grid_origin, grid_size = compounding_grid(spine, 0.5)
    assert_close(grid_origin, origin, atol=0.1)
    assert np.array_equal(grid_size, size)


def test_nwire_clipped_corners_reproduce_plus_compounded_volume(shared_data):
    """The same with the N-wire recording, its clip rectangle and its INVALID stylus tool."""
    sweep = read_plus_sequence(NWIRE_MHA, calibration=NWIRE_XML)
    device_set = read_plus_device_set(NWIRE_XML)
    assert list(device_set.clip_origin) == [167, 62] and list(device_set.clip_size) == [495, 488]
    origin, size, spacing = sitk_grid(NWIRE_VOLUME)
    grid_origin, grid_size = compounding_grid(sweep, spacing, device_set.clip_origin,
                                              device_set.clip_size)
    assert_close(grid_origin, origin, atol=0.1)
    assert np.array_equal(grid_size, size)


def test_spine_chain_matches_naive_composition(spine):
    """ImageToReference = inv(ReferenceToTracker) @ ProbeToTracker @ ImageToProbe, composed here
    from a regex parse of the header and the XML, applied to pixel indices."""
    fields = naive_header(SPINE)
    image_to_probe = naive_image_to_probe(SPINE_XML)
    assert_close(read_plus_calibration(SPINE_XML), image_to_probe, atol=0)
    pixels = np.array([[0, 0, 0, 1], [819, 0, 0, 1], [0, 615, 0, 1], [400.5, 300.25, 0, 1]])
    for f in (0, 7, 20):
        probe = naive_matrix(fields[f"Seq_Frame{f:04d}_ProbeToTrackerTransform"])
        reference = naive_matrix(fields[f"Seq_Frame{f:04d}_ReferenceToTrackerTransform"])
        expected = (np.linalg.inv(reference) @ probe @ image_to_probe @ pixels.T).T[:, :3]
        ours = spine.pixel_to_reference(np.full(4, f), pixels[:, 1], pixels[:, 0])
        assert_close(ours, expected, atol=1e-9, what=f"frame {f}")
        assert_close(spine.timestamps[f], float(fields[f"Seq_Frame{f:04d}_Timestamp"]), atol=0)
    assert_close(spine.spacing, np.linalg.norm(image_to_probe[:3, :2], axis=0), rtol=1e-5)


def test_nwire_mha_and_nrrd_give_identical_frames_and_transforms(shared_data):
    """Done-when: the .igs.mha and .igs.nrrd N-wire files give identical frames and transforms;
    the frames also equal SimpleITK's and pynrrd's reading of the files."""
    a = read_tracked_sweep(NWIRE_MHA, calibration=NWIRE_XML)
    b = read_tracked_sweep(NWIRE_NRRD, calibration=NWIRE_XML)
    assert a.frames.shape == (97, 616, 820)
    assert np.array_equal(a.frames, b.frames)
    assert np.array_equal(a.T_ref_image, b.T_ref_image)
    assert np.array_equal(a.timestamps, b.timestamps) and np.array_equal(a.valid, b.valid)
    assert a.valid.all()  # the stylus is INVALID throughout, but it is not on the chain
    assert np.array_equal(a.frames, sitk.GetArrayFromImage(sitk.ReadImage(str(NWIRE_MHA))))
    data, _ = nrrd.read(str(NWIRE_NRRD), index_order="C")
    assert np.array_equal(b.frames, data)


# --- PLUS: format variants ---------------------------------------------------------------------


@pytest.mark.parametrize("compress", [True, False])
def test_synthetic_sequence_round_trip(tmp_path, synthetic, compress):
    frames, records, probe, reference, xml = synthetic
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records, compress=compress)
    sweep = read_plus_sequence(path, calibration=xml)
    assert np.array_equal(sweep.frames, frames)
    expected = np.linalg.inv(reference) @ probe @ IMAGE_TO_PROBE
    assert_close(sweep.T_ref_pixel[..., [0, 1, 3]], expected[..., [0, 1, 3]], atol=1e-9)
    assert_close(sweep.spacing, [0.2, 0.2], atol=1e-12)
    assert_close(sweep.timestamps, 10 + 0.1 * np.arange(5), atol=1e-9)


def test_nrrd_form_equals_metaimage_form(tmp_path, synthetic):
    frames, records, probe, reference, xml = synthetic
    mha = write_plus_mha(tmp_path / "s.igs.mha", frames, records)
    header = {"kinds": ["domain", "domain", "list"], "space dimension": 2,
              "space directions": np.array([[1.0, 0], [0, 1.0], [np.nan, np.nan]]),
              "space origin": np.zeros(2), "encoding": "gzip",
              "ultrasound image orientation": "MFA", "ultrasound image type": "BRIGHTNESS"}
    for i, record in enumerate(records):
        for key, value in record.items():
            header[f"Seq_Frame{i:04d}_{key}"] = value
    nrrd.write(str(tmp_path / "s.seq.nrrd"), np.ascontiguousarray(frames.transpose(2, 1, 0)),
               header, index_order="F")
    a = read_tracked_sweep(mha, calibration=xml)
    b = read_tracked_sweep(tmp_path / "s.seq.nrrd", calibration=xml)
    assert np.array_equal(a.frames, b.frames)
    assert_close(a.T_ref_image, b.T_ref_image, atol=0)


@pytest.mark.parametrize("orientation,flip", [("MF", (False, False)), ("UF", (False, True)),
                                              ("MN", (True, False)), ("UN", (True, True)),
                                              ("MFA", (False, False))])
def test_image_orientation_is_flipped_to_mf(tmp_path, synthetic, orientation, flip):
    frames, records, _, _, xml = synthetic
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records,
                          extra={"UltrasoundImageOrientation": orientation})
    expected = frames[:, ::-1] if flip[0] else frames
    expected = expected[:, :, ::-1] if flip[1] else expected
    assert np.array_equal(read_plus_sequence(path, calibration=xml).frames, expected)


def test_transposed_or_rf_images_are_refused(tmp_path, synthetic):
    frames, records, _, _, xml = synthetic
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records,
                          extra={"UltrasoundImageOrientation": "FM"})
    with pytest.raises(ComRegError, match="orientation|Orientation"):
        read_plus_sequence(path, calibration=xml)
    path = write_plus_mha(tmp_path / "r.igs.mha", frames, records,
                          extra={"UltrasoundImageType": "RF_REAL"})
    with pytest.raises(ComRegError, match="B-mode"):
        read_plus_sequence(path, calibration=xml)


def test_per_frame_image_to_reference_needs_no_calibration(tmp_path, synthetic):
    frames, records, probe, reference, _ = synthetic
    chain = np.linalg.inv(reference) @ probe @ IMAGE_TO_PROBE
    records = [{"ImageToReferenceTransform": matrix_text(chain[i]),
                "ImageToReferenceTransformStatus": "OK"} for i in range(5)]
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records)
    assert_close(read_plus_sequence(path).T_ref_pixel[..., [0, 1, 3]], chain[..., [0, 1, 3]],
                 atol=1e-9)


def test_tracker_frame_is_used_when_there_is_no_reference(tmp_path, synthetic, caplog):
    frames, records, probe, _, xml = synthetic
    records = [{k: v for k, v in r.items() if not k.startswith("Reference")} for r in records]
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records)
    with caplog.at_level(logging.WARNING):
        sweep = read_plus_sequence(path, calibration=xml)
    assert sweep.reference == "Tracker" and "Tracker" in caplog.text
    assert_close(sweep.T_ref_pixel[..., [0, 1, 3]], (probe @ IMAGE_TO_PROBE)[..., [0, 1, 3]],
                 atol=1e-9)


# --- PLUS: bad input ---------------------------------------------------------------------------


def test_invalid_transforms_drop_frames_with_a_warning(tmp_path, synthetic, caplog):
    frames, records, _, _, xml = synthetic
    records[1]["ProbeToTrackerTransformStatus"] = "INVALID"
    records[3]["ReferenceToTrackerTransformStatus"] = "INVALID"
    records[4]["ImageStatus"] = "INVALID"
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records)
    with caplog.at_level(logging.WARNING):
        sweep = read_plus_sequence(path, calibration=xml)
    assert list(sweep.valid) == [True, False, True, False, False]
    assert "3 of 5 frames" in caplog.text and "INVALID" in caplog.text
    kept = sweep.only_valid()
    assert kept.n_frames == 2 and np.array_equal(kept.frames, frames[[0, 2]])
    assert kept.frame_names == ["Frame0000", "Frame0002"]


def test_all_transforms_invalid_is_an_error(tmp_path, synthetic):
    frames, records, _, _, xml = synthetic
    for record in records:
        record["ProbeToTrackerTransformStatus"] = "INVALID"
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records)
    with pytest.raises(NoValidFramesError, match="None of the 5 frames"):
        read_plus_sequence(path, calibration=xml)


def test_missing_frames_and_inconsistent_counts(tmp_path, synthetic, caplog):
    frames, records, _, _, xml = synthetic
    # fields describe 5 frames, the data hold 4 images (and DimSize says 4)
    path = write_plus_mha(tmp_path / "a.igs.mha", frames[:4], records)
    with pytest.raises(CorruptFileError, match="inconsistent frame counts"):
        read_plus_sequence(path, calibration=xml)
    # DimSize says 5 frames but only 4 frames of pixels are stored: truncated
    path = write_plus_mha(tmp_path / "b.igs.mha", frames[:4], records, dim_frames=5,
                          compress=False)
    with pytest.raises(CorruptFileError, match="bytes"):
        read_plus_sequence(path, calibration=xml)
    # a frame without any tracking fields: kept as an invalid frame, with a warning
    path = write_plus_mha(tmp_path / "c.igs.mha", frames, records[:4] + [{}])
    with caplog.at_level(logging.WARNING):
        sweep = read_plus_sequence(path, calibration=xml)
    assert list(sweep.valid) == [True] * 4 + [False]
    assert "no Seq_Frame fields" in caplog.text


def test_malformed_transform_is_a_corrupt_file(tmp_path, synthetic):
    frames, records, _, _, xml = synthetic
    records[2]["ProbeToTrackerTransform"] = "1 0 0"
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records)
    with pytest.raises(CorruptFileError, match="16 numbers"):
        read_plus_sequence(path, calibration=xml)


def test_missing_calibration_says_what_to_pass(tmp_path, synthetic):
    frames, records, _, _, _ = synthetic
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records)
    with pytest.raises(ComRegError, match="calibration"):
        read_tracked_sweep(path)
    with pytest.raises(ComRegError, match="XML"):
        read_tracked_sweep(path, calibration=FIBULA_DIR / "calibration.json")


def test_calibration_for_another_image_size(tmp_path, synthetic):
    frames, records, _, _, _ = synthetic
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records)
    xml = write_device_set(tmp_path / "d.xml", image_size=(820, 616))
    with pytest.raises(CalibrationMismatchError, match="820 x 616"):
        read_plus_sequence(path, calibration=xml)
    xml = write_device_set(tmp_path / "e.xml", clip=(50, 3))
    with pytest.raises(CalibrationMismatchError, match="outside"):
        read_plus_sequence(path, calibration=xml)
    xml = write_device_set(tmp_path / "f.xml", T=np.diag([50.0, 50.0, 50.0, 1.0]))
    with pytest.raises(CalibrationMismatchError, match="pixel size"):
        read_plus_sequence(path, calibration=xml)


def test_bad_files(tmp_path):
    with pytest.raises(InputFileNotFoundError):
        read_tracked_sweep(tmp_path / "missing.igs.mha")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(UnsupportedFormatError):
        read_tracked_sweep(tmp_path / "x.txt")
    (tmp_path / "bad.igs.mha").write_bytes(b"not a header\x00\x01")
    with pytest.raises(CorruptFileError):
        read_tracked_sweep(tmp_path / "bad.igs.mha")
    (tmp_path / "bad.xml").write_text("<PlusConfiguration><Transform From='Image' To='Probe' "
                                      "Matrix='1 2 3'/></PlusConfiguration>")
    with pytest.raises(CorruptFileError, match="16 numbers"):
        read_plus_device_set(tmp_path / "bad.xml")
    (tmp_path / "none.xml").write_text("<PlusConfiguration/>")
    with pytest.raises(ComRegError, match="no ImageToProbe"):
        read_plus_calibration(tmp_path / "none.xml")


@pytest.mark.parametrize("source", [NWIRE_MHA, NWIRE_NRRD], ids=["igs.mha", "igs.nrrd"])
def test_a_truncated_recording_is_a_corrupt_file(tmp_path, shared_data, source):
    """The real PLUS recordings (zlib and gzip voxel data) cut to half their bytes."""
    data = source.read_bytes()
    path = tmp_path / source.name
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptFileError, match=re.escape(source.name) + ".*(end early|need)"):
        read_tracked_sweep(path, calibration=NWIRE_XML)


def test_truncated_raw_voxel_data_is_a_corrupt_file(tmp_path, synthetic):
    frames, records, _, _, xml = synthetic
    path = write_plus_mha(tmp_path / "s.igs.mha", frames, records, compress=False)
    data = path.read_bytes()
    path.write_bytes(data[:-frames[0].size // 2])
    with pytest.raises(CorruptFileError, match=r"s\.igs\.mha.*need \d+ bytes .* holds \d+"):
        read_tracked_sweep(path, calibration=xml)
    # the same as a .mhd header and a data file that was cut: the message names the data file
    header, voxels = data[: -frames.size], data[-frames.size:]
    (tmp_path / "s.mhd").write_bytes(header.replace(b"ElementDataFile = LOCAL",
                                                    b"ElementDataFile = s.raw"))
    (tmp_path / "s.raw").write_bytes(voxels[: len(voxels) // 2])
    with pytest.raises(CorruptFileError, match=r"s\.raw.*holds \d+ \(the voxel data of .*s\.mhd"):
        read_tracked_sweep(tmp_path / "s.mhd", calibration=xml)
