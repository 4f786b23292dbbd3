"""3D Slicer volume sequences (.seq.nrrd): frames, spacing, timestamps and geometry, list axis
first or last."""

from __future__ import annotations

import nrrd
import numpy as np
import pytest

from comreg_core.errors import ComRegError, CorruptFileError
from comreg_core.io.slicer_sequences import read_slicer_volume_sequence
from comreg_core.io.tracked_us import read_tracked_sweep
from tests.helpers import assert_close


@pytest.mark.parametrize("list_first", [True, False])
def test_slicer_volume_sequence(tmp_path, list_first):
    rng = np.random.default_rng(3)
    frames = rng.integers(0, 255, (4, 6, 5), dtype=np.uint8)  # N, H, W
    volume = frames.transpose(2, 1, 0)[:, :, None, :]  # i (W), j (H), k (1), frames
    directions = np.array([[0.3, 0, 0], [0, 0.2, 0], [0, 0, 1.0]])
    kinds = ["domain"] * 3
    if list_first:
        volume = np.moveaxis(volume, 3, 0)
        directions = np.vstack([[np.nan] * 3, directions])
        kinds = ["list"] + kinds
        axis = 0
    else:
        directions = np.vstack([directions, [np.nan] * 3])
        kinds = kinds + ["list"]
        axis = 3
    header = {"space": "right-anterior-superior", "space directions": directions,
              "space origin": np.array([10.0, 20.0, 30.0]), "kinds": kinds,
              f"axis {axis} index values": "0.0 0.5 1.0 1.5"}
    path = tmp_path / "seq.seq.nrrd"
    nrrd.write(str(path), np.ascontiguousarray(volume), header, index_order="F")
    sweep = read_tracked_sweep(path)
    assert np.array_equal(sweep.frames, frames)
    assert_close(sweep.spacing, [0.3, 0.2], atol=1e-12)
    assert_close(sweep.timestamps, [0, 0.5, 1.0, 1.5], atol=1e-12)
    # pixel (row 2, col 3) -> RAS (10 + 0.9, 20 + 0.4, 30) -> LPS
    assert_close(sweep.pixel_to_reference([1], [2], [3])[0], [-10.9, -20.4, 30.0], atol=1e-9)
    with pytest.raises(ComRegError, match="3D volumes"):
        nrrd.write(str(tmp_path / "v.seq.nrrd"), np.zeros((3, 3, 3, 2), np.uint8),
                   {**header, "space directions": np.vstack([np.eye(3), [np.nan] * 3]),
                    "kinds": ["domain"] * 3 + ["list"]}, index_order="F")
        read_slicer_volume_sequence(tmp_path / "v.seq.nrrd")


@pytest.mark.parametrize("encoding", ["raw", "gzip"])
def test_a_truncated_volume_sequence_is_a_corrupt_file(tmp_path, encoding):
    frames = np.random.default_rng(4).integers(0, 255, (8, 60, 50, 1), dtype=np.uint8)
    header = {"space": "left-posterior-superior", "encoding": encoding,
              "space directions": np.vstack([[np.nan] * 3, np.diag([0.2, 0.2, 1.0])]),
              "space origin": np.zeros(3), "kinds": ["list", "domain", "domain", "domain"]}
    path = tmp_path / "cut.seq.nrrd"
    nrrd.write(str(path), frames, header, index_order="F")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptFileError, match=r"cut\.seq\.nrrd.*need 24000 voxel values"):
        read_tracked_sweep(path)
