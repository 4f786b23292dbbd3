"""The TrackedSweep type: frame selection and validity."""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.io.sweeps import NoValidFramesError, TrackedSweep


def test_sweep_selection_and_validation():
    sweep = TrackedSweep(np.zeros((3, 4, 5), np.uint8), [0.1, 0.2],
                         np.repeat(np.eye(4)[None], 3, axis=0), [0, 1, 2], [True, True, False])
    assert sweep.image_shape == (4, 5) and sweep.frame_names[2] == "Frame0002"
    assert sweep.select([2, 0]).frame_names == ["Frame0002", "Frame0000"]
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    T[1] = np.nan
    assert list(TrackedSweep(np.zeros((3, 4, 5)), [1, 1], T, [0, 0, 0],
                             [True] * 3).valid) == [True, False, True]
    with pytest.raises(NoValidFramesError):
        sweep.select([2]).only_valid()
