"""The detector's compiled kernels give numpy's and scipy's bits: the Gaussian filters against
``scipy.ndimage.gaussian_filter``, the shadow and tissue terms against their cumulative-sum
formulas in numpy, the bone probability against numpy's expression; on real fibula frames and
on images shorter than the kernels (reflected more than once)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from comreg_core.io.frame_folders import read_frame_image
from comreg_core.surfaces.us_detector import _block_mean
from comreg_core.surfaces.us_filters import bone_probability, gaussian_filter, shadow_and_tissue
from tests.helpers import FIBULA_DIR


def _bits(array: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(array).view(np.uint8)


@pytest.fixture(scope="module")
def fibula_images() -> list[np.ndarray]:
    """Three real fibula frames at the detector's working resolution (2 x 2 blocks), float32."""
    paths = sorted((FIBULA_DIR / "frames").glob("*.png"))
    return [_block_mean(read_frame_image(paths[i]), 2, 2) for i in (0, 40, 90)]


@pytest.mark.parametrize("sigma, order", [((0.463, 0.463), (0, 0)), ((1.39, 1.39), (2, 0)),
                                          ((1.39, 1.39), (0, 2)), ((1.39, 1.39), (1, 1)),
                                          ((2.7, 0.9), (1, 2))])
def test_gaussian_filter_is_scipy_s_bit_for_bit(fibula_images, sigma, order):
    rng = np.random.default_rng(3)
    small = [rng.random((37, 5), np.float32) * 255, rng.random((3, 400), np.float32) * 255]
    for image in fibula_images + small:
        ours = gaussian_filter(image, sigma, order)
        assert ours.dtype == np.float32 and ours.shape == image.shape
        assert np.array_equal(_bits(ours), _bits(ndimage.gaussian_filter(image, sigma,
                                                                          order=order)))
    assert np.abs(gaussian_filter(fibula_images[0], sigma, order)).max() > 0


def test_gaussian_filter_of_other_dtypes_is_scipy_s():
    image = np.random.default_rng(4).random((50, 60))  # float64: scipy itself
    assert np.array_equal(gaussian_filter(image, (2.0, 2.0), (1, 0)),
                          ndimage.gaussian_filter(image, (2.0, 2.0), order=(1, 0)))


def _window_means(cum, start, stop):
    h = len(cum) - 1
    start, stop = np.clip(start, 0, h), np.clip(stop, 0, h)
    count = np.maximum(stop - start, 0)
    return (cum[stop] - cum[start]) / np.maximum(count, 1)[:, None], count


def test_shadow_and_tissue_are_the_cumulative_sum_formulas(fibula_images):
    intensity = gaussian_filter(fibula_images[1], (0.46, 0.46))
    h, w = intensity.shape
    rows = np.arange(h)
    gap, depth, above_n = 5, 46, 19
    expected = np.linspace(20.0, 5.0, h)
    tissue_ref = float(np.median(intensity))
    echo_level = np.float32(0.25 * tissue_ref)
    shadow, tissue = shadow_and_tissue(intensity, expected, gap, depth, above_n, tissue_ref,
                                       echo_level, 0.75, above_n // 2)
    cum = np.vstack([np.zeros((1, w)), np.cumsum(intensity, axis=0, dtype=np.float64)])
    below, n_below = _window_means(cum, rows + gap, rows + gap + depth)
    want_shadow = np.clip(1.0 - below / expected[:, None], 0.0, 1.0)
    want_shadow[n_below == 0] = 0.0
    above, n_above = _window_means(cum, rows - gap - above_n, rows - gap)
    echo = np.vstack([np.zeros((1, w)), np.cumsum(intensity > echo_level, axis=0)])
    fill, _ = _window_means(echo, rows - gap - above_n, rows - gap)
    want_tissue = np.clip(above / tissue_ref, 0.0, 1.0) * np.clip(fill / 0.75, 0.0, 1.0)
    want_tissue[n_above < above_n // 2] = 0.0
    assert np.array_equal(_bits(shadow), _bits(want_shadow))
    assert np.array_equal(_bits(tissue), _bits(want_tissue))
    assert (shadow[-gap:] == 0).all() and (tissue[:gap + above_n // 2] == 0).all()
    assert 0.05 < (shadow > 0.5).mean() < 0.95 and 0.05 < (tissue > 0.5).mean() < 0.95


@pytest.mark.parametrize("powers", [(1.0, 1.0, 1.0, 2.0), (2.0, 1.0, 2.0, 1.0),
                                    (0.5, 1.0, 1.5, 3.0)])
def test_bone_probability_is_numpy_s_expression(powers):
    rng = np.random.default_rng(5)
    norm, ridge = rng.random((2, 80, 90), np.float32)
    shadow, tissue = rng.random((2, 80, 90))
    ours = bone_probability(norm, ridge, shadow, tissue, powers)
    want = ((norm ** powers[0]) * (ridge ** powers[1]) * (shadow ** powers[2])
            * (tissue ** powers[3])).astype(np.float32)
    assert ours.dtype == np.float32 and np.array_equal(_bits(ours), _bits(want))
