"""The detector's compiled percentiles give numpy's bits: ``numpy.percentile`` over the whole
map, per column and per row of chosen columns, and ``numpy.median``, on real fibula frames
(smoothed as the detector smooths them) and on random maps with ties, constant lines and
single values; maps with a NaN or an infinity go to numpy."""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.io.frame_folders import read_frame_image
from comreg_core.surfaces.us_detector import _block_mean
from comreg_core.surfaces.us_filters import gaussian_filter
from comreg_core.surfaces.us_percentiles import median, percentile
from tests.helpers import FIBULA_DIR


def _same(ours, numpy_s) -> bool:
    ours, numpy_s = np.asarray(ours), np.asarray(numpy_s)
    return (ours.dtype == numpy_s.dtype and ours.shape == numpy_s.shape
            and ours.tobytes() == numpy_s.tobytes())


def _all_agree(image: np.ndarray, q: float, columns: np.ndarray) -> list[str]:
    """Names of the statistics of ``image`` whose bits differ from numpy's."""
    pairs = {"whole": (percentile(image, q), np.percentile(image, q)),
             "columns": (percentile(image, q, axis=0), np.percentile(image, q, axis=0)),
             "rows": (percentile(image, q, axis=1), np.percentile(image, q, axis=1)),
             "median": (median(image), np.median(image))}
    if columns.any():
        pairs["rows of chosen columns"] = (percentile(image, q, axis=1, columns=columns),
                                           np.percentile(image[:, columns], q, axis=1))
    return [name for name, (ours, numpy_s) in pairs.items() if not _same(ours, numpy_s)]


@pytest.mark.parametrize("index", [0, 40, 90])
def test_percentiles_of_real_frames_are_numpy_s(index):
    path = sorted((FIBULA_DIR / "frames").glob("*.png"))[index]
    intensity = gaussian_filter(_block_mean(read_frame_image(path), 2, 2), (0.93, 0.93))
    assert intensity.shape == (405, 475)
    columns = np.arange(475) % 3 > 0  # as if a third of the columns were black margins
    for q in (99.0, 95.0, 50.0, 12.5):
        assert _all_agree(intensity, q, columns) == []


def test_percentiles_of_random_maps_are_numpy_s():
    rng = np.random.default_rng(0)
    differ = []
    for trial in range(600):
        h, w = int(rng.integers(1, 50)), int(rng.integers(1, 50))
        image = (rng.random((h, w)) * rng.choice([1e-3, 1.0, 300.0])).astype(np.float32)
        if trial % 3 == 0:
            image = np.round(image, 1).astype(np.float32)  # many ties
        if trial % 7 == 0:
            image[:, : w // 2] = 3.0  # constant lines
        q = float(rng.choice([0.0, 50.0, 95.0, 99.0, 100.0, 100 * rng.random()]))
        differ += [(trial, name) for name in _all_agree(image, q, rng.random(w) < 0.6)]
    assert differ == []


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")  # numpy's, with inf
def test_a_map_with_nan_or_inf_is_numpy_s():
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    image[1, 2] = np.nan
    assert np.isnan(percentile(image, 50))
    assert np.isnan(percentile(image, 50, axis=0)).sum() == 1
    assert _same(percentile(image, 50, axis=1, columns=np.array([1, 1, 0, 1], bool)),
                 np.array([1.0, 5.0, 9.0], np.float32))
    assert np.isnan(median(image))
    image[1, 2] = np.inf  # an infinity goes to numpy too
    assert _all_agree(image, 50.0, np.array([1, 0, 1, 1], bool)) == []
