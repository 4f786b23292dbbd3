"""Compounding a sweep against PLUS's own reconstructed volume."""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.config import ConfigError
from comreg_core.io.plus_sequences import read_plus_sequence
from comreg_core.surfaces.us_compounding import compound_sweep, compounding_grid
from tests.helpers import SHARED_DATA, assert_close


def test_compounding_matches_plus_reconstruction(shared_data, tmp_path):
    """Our nearest-voxel mean compounding of SpinePhantomFreehand on PLUS's grid against PLUS's
    own compounded volume (linear interpolation, hole filling): the same grid, and voxel values
    that agree where both are filled."""
    from comreg_core.io.volumes import read_volume, write_volume

    plus = SHARED_DATA / "plus"
    sweep = read_plus_sequence(
        plus / "TestImages" / "SpinePhantomFreehand.igs.mha",
        calibration=plus / "ConfigFiles" / "Testing" /
        "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml")
    ours = compound_sweep(sweep, 0.5)
    theirs = read_volume(plus / "TestImages" / "SpinePhantomFreehandReconstructed.mha")
    assert ours.array.shape == theirs.array.shape and ours.array.dtype == np.uint8
    assert_close(ours.origin, theirs.origin, atol=1e-3)
    a, b = ours.array.astype(float), theirs.array.astype(float)
    both = (a > 0) & (b > 0)
    assert both.sum() > 100_000
    assert np.corrcoef(a[both], b[both])[0, 1] > 0.95
    assert np.abs(a[both] - b[both]).mean() < 10
    peak = compound_sweep(sweep.select(np.arange(0, 21, 4)), 1.0, "max")
    mean = compound_sweep(sweep.select(np.arange(0, 21, 4)), 1.0, "mean")
    assert np.all(peak.array >= mean.array)
    write_volume(mean, tmp_path / "c.nrrd")
    assert np.array_equal(read_volume(tmp_path / "c.nrrd").array, mean.array)
    origin, dims = compounding_grid(sweep, 1.0)
    assert tuple(dims) == mean.array.shape
    with pytest.raises(ConfigError):
        compound_sweep(sweep, 0.5, "median")
