"""Bone points from label masks: top edges and all pixels, mask folders, .npy stacks, frame-stack
and reference-frame label volumes."""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.errors import ComRegError
from comreg_core.io.sweeps import TrackedSweep
from comreg_core.surfaces.us_masks import read_masks, surface_from_masks
from comreg_core.surfaces.us_points import NoBoneFoundError
from tests.helpers import assert_close


def pose(rng):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-50, 50, 3)
    return T


@pytest.fixture
def mask_sweep():
    rng = np.random.default_rng(5)
    T = np.stack([pose(rng) for _ in range(3)])
    sweep = TrackedSweep(np.zeros((3, 20, 30), np.uint8), (0.2, 0.3), T, [0, 1, 2],
                         [True, True, False], frame_names=["a", "b", "c"])
    masks = np.zeros((3, 20, 30), np.uint8)
    masks[0, 5:9, 10:20] = 1  # one run per column: top edge at row 5
    masks[1, 2:4, 3] = 1
    masks[1, 10:12, 3] = 2  # two runs in column 3: top edges at rows 2 and 10
    masks[2, 0:5, 0:5] = 1  # invalid frame: ignored
    return sweep, masks


def test_surface_from_masks_top_edges_and_all_pixels(mask_sweep):
    sweep, masks = mask_sweep
    top = surface_from_masks(sweep, masks)
    assert list(np.bincount(top.frame_index, minlength=3)) == [10, 2, 0]
    expected = [sweep.T_ref_image[0] @ [c * 0.2, 5 * 0.3, 0, 1] for c in range(10, 20)]
    expected += [sweep.T_ref_image[1] @ [3 * 0.2, r * 0.3, 0, 1] for r in (2, 10)]
    assert_close(top.points, np.array(expected)[:, :3], atol=1e-9)
    every = surface_from_masks(sweep, masks, top_edge=False)
    assert len(every.points) == 40 + 4 and every.frames_with_bone == 2
    with pytest.raises(ComRegError, match="inconsistent frame counts"):
        surface_from_masks(sweep, masks[:2])
    with pytest.raises(NoBoneFoundError):
        surface_from_masks(sweep, np.zeros_like(masks))


def test_read_masks_from_folder_npy_and_label_volume(tmp_path, mask_sweep):
    import vtk
    from vtk.util import numpy_support

    from comreg_core.io.volumes import Volume, write_volume

    sweep, masks = mask_sweep
    folder = tmp_path / "masks"
    folder.mkdir()
    for name, mask in zip(sweep.frame_names, masks):
        image = vtk.vtkImageData()
        image.SetDimensions(30, 20, 1)
        image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(
            (255 * (mask[::-1] > 0)).astype(np.uint8).ravel()))
        writer = vtk.vtkPNGWriter()
        writer.SetFileName(str(folder / f"{name}.png"))
        writer.SetInputData(image)
        writer.Write()
    assert np.array_equal(read_masks(folder, sweep), masks > 0)
    np.save(tmp_path / "m.npy", masks)
    assert np.array_equal(read_masks(tmp_path / "m.npy", sweep), masks > 0)
    np.save(tmp_path / "short.npy", masks[:2])
    with pytest.raises(ComRegError, match="inconsistent frame counts"):
        read_masks(tmp_path / "short.npy", sweep)
    (folder / "a.png").rename(folder / "zz.png")
    (folder / "c.png").unlink()
    with pytest.raises(ComRegError, match="lacks masks"):
        read_masks(folder, sweep)
    # a frame stack stored as a W x H x N label volume
    write_volume(Volume(masks.transpose(2, 1, 0).copy(), np.eye(4)), tmp_path / "stack.nrrd")
    assert np.array_equal(read_masks(tmp_path / "stack.nrrd", sweep), masks > 0)
    # a label volume in the reference frame: the half space x > 0 (LPS), 0.5 mm voxels
    grid = np.mgrid[-60:60:0.5, -60:60:0.5, -60:60:0.5][0]
    labels = (grid > 0).astype(np.uint8)
    volume = Volume.from_geometry(labels, (0.5,) * 3, (-60.0, -60.0, -60.0))
    write_volume(volume, tmp_path / "labels.nrrd")
    sampled = read_masks(tmp_path / "labels.nrrd", sweep)
    rr, cc = np.mgrid[0:20, 0:30]
    for f in (0, 1):
        x = sweep.pixel_to_reference(np.full(rr.size, f), rr.ravel(), cc.ravel())[:, 0]
        decided = np.abs(x) > 0.5  # away from the voxel boundary
        assert np.array_equal(sampled[f].ravel()[decided], x[decided] > 0)
    assert not sampled[2].any()  # invalid frame
