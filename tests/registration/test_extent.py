"""A sweep's extent: one measure (5th-95th percentile along the points' largest principal axis,
over the CT's length) for the search's patch and the verdict's short sweep."""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.register.judge import SHORT_SWEEP_SHARE, is_short_sweep
from comreg_core.registration.geometry.extent import (PATCH_MAX_SHARE, SHORT_SWEEP_SHARE as HOME,
                                                      extent_mm, extent_share, spread_mm)
from comreg_core.registration.geometry.surface import CTSurface, ct_length_mm
from comreg_core.registration.search.config import SearchConfig
from comreg_core.registration.search.search import is_patch
from tests.helpers import FIBULA_STL


@pytest.fixture(scope="module")
def fibula_target(shared_data):
    return CTSurface(FIBULA_STL).cloud(SearchConfig.target_points)


def _strip(length_mm: float, direction, n: int = 1001, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` points evenly along ``length_mm`` of a unit ``direction`` through (10, 20, 30)
    mm, with 1 mm of scatter across it: a sweep whose extent is known."""
    d = np.asarray(direction, dtype=np.float64)
    d /= np.linalg.norm(d)
    rng = np.random.default_rng(seed)
    across = rng.normal(0.0, 1.0, (n, 3))
    across -= np.outer(across @ d, d)
    return np.array([10.0, 20.0, 30.0]) + np.outer(np.linspace(0.0, length_mm, n), d) + across


def test_the_extent_is_the_5th_to_95th_percentile_along_the_largest_axis():
    direction = [1.0, 2.0, -2.0]  # any axis: the points' own principal axis is found
    strip = _strip(100.0, direction)
    # evenly spaced positions 0..100 mm: percentiles 5 and 95 are 5 and 95 mm
    assert extent_mm(strip) == pytest.approx(90.0, abs=0.05)
    assert extent_mm(strip, np.asarray(direction) / 3.0) == pytest.approx(90.0, abs=1e-9)
    assert spread_mm(np.linspace(0.0, 100.0, 1001)) == pytest.approx(90.0, abs=1e-9)
    # a few stray echoes far along the axis do not lengthen the sweep (a peak-to-peak would)
    strays = np.array([10.0, 20.0, 30.0]) + np.outer([300.0, 320.0, -250.0], direction) / 3.0
    with_strays = np.vstack([strip, strays])
    assert extent_mm(with_strays) == pytest.approx(90.0, abs=0.5)
    assert extent_share(strip, 400.0) == pytest.approx(90.0 / 400.0, abs=1e-3)
    assert extent_share(strip, 50.0) == 1.0  # clipped


def test_the_patch_and_the_short_sweep_use_the_one_extent(fibula_target):
    """The search's patch test is the extent share against ``patch_max_share``; the verdict's
    short sweep the same share against :data:`SHORT_SWEEP_SHARE`; both limits live with the
    measure."""
    length = ct_length_mm(fibula_target)
    axis = fibula_target.axes[:, 0]
    assert SearchConfig().patch_max_share == PATCH_MAX_SHARE and SHORT_SWEEP_SHARE is HOME
    for mm in (60.0, 150.0, 190.0, 215.0, 240.0, 330.0):
        strip = _strip(mm, axis)
        share = extent_share(strip, length)
        assert share == pytest.approx(0.9 * mm / length, abs=1e-3)
        for limit in (0.3, PATCH_MAX_SHARE, 0.6):
            assert is_patch(strip, fibula_target, SearchConfig(patch_max_share=limit)) == \
                (share < limit)
        assert is_short_sweep(share) == (share < SHORT_SWEEP_SHARE)
    # with stray echoes a partial sweep stays a patch
    strip = _strip(0.4 * length / 0.9, axis)
    strays = strip[:3] + np.outer([0.6 * length, 0.7 * length, -0.5 * length], axis)
    assert is_patch(np.vstack([strip, strays]), fibula_target, SearchConfig())
