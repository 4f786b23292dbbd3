"""Builders and independent readers shared by the volume, NRRD, MetaImage and segmentation
tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

from comreg_core.io.segmentations import Segment, Segmentation
from comreg_core.io.volumes import Volume
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
