"""The paper's stochastic processes against naive reference implementations and statistics."""

import numpy as np
import pytest

from comreg_core.simulation.processes import (dropped_slices, false_hits, moving_average,
                                              reflected_walk, slice_positions,
                                              smoothed_bounded_walk)
from tests.helpers import assert_close


def naive_moving_average(x, window):
    """Centred mean over `window` samples (odd), the series extended by its end values."""
    h = window // 2
    padded = [x[0]] * h + list(x) + [x[-1]] * h
    return np.array([np.mean(padded[i:i + window]) for i in range(len(x))])


@pytest.mark.parametrize("window", [1, 3, 25, 61])
def test_moving_average_matches_naive(window):
    x = np.random.default_rng(0).normal(size=200)
    assert_close(moving_average(x, window), naive_moving_average(x, window), atol=1e-12)


def test_moving_average_on_series_shorter_than_window():
    x = np.array([1.0, 2.0, 4.0])
    assert_close(moving_average(x, 61), naive_moving_average(x, 61), atol=1e-12)


def naive_reflected_walk(lo, hi, start, steps):
    """Step by step: add the step, mirror at whichever wall was crossed until inside."""
    x, out = start, [start]
    for step in steps:
        x += step
        while x < lo or x > hi:
            x = 2 * lo - x if x < lo else 2 * hi - x
        out.append(x)
    return np.array(out)


def test_reflected_walk_has_the_law_of_step_by_step_reflection():
    """Folding the free walk into the interval gives a different path than reflecting the same
    steps one by one, but the same distribution: compare positions after 30 steps over 3000
    walks with a two-sample Kolmogorov-Smirnov test."""
    from scipy.stats import ks_2samp

    rng = np.random.default_rng(1)
    ours = np.array([reflected_walk(31, -2.0, 3.0, 1.5, 0.5, rng)[-1] for _ in range(3000)])
    naive = np.array([naive_reflected_walk(-2.0, 3.0, 0.5, rng.normal(0, 1.5, 30))[-1]
                      for _ in range(3000)])
    assert ks_2samp(ours, naive).pvalue > 1e-3
    walk = reflected_walk(5000, -2.0, 3.0, 1.5, 0.5, rng)
    assert walk.min() >= -2.0 and walk.max() <= 3.0
    assert walk.min() < -1.8 and walk.max() > 2.8  # big steps: it does reach both walls
    # until the free walk first leaves the interval, nothing is folded
    free = 0.5 + np.cumsum(np.r_[0.0, np.random.default_rng(2).normal(0, 0.1, 999)])
    walk = reflected_walk(1000, -2.0, 3.0, 0.1, 0.5, np.random.default_rng(2))
    first_exit = np.argmax((free < -2.0) | (free > 3.0)) or len(free)
    assert_close(walk[:first_exit], free[:first_exit], atol=1e-12)


@pytest.mark.parametrize("bound_deg", [20.0, 5.0])
def test_tilts_bounded_smooth_and_window_effect_measurable(bound_deg):
    bound = np.radians(bound_deg)
    n, step = 400, 0.1
    for seed in range(20):
        raw = smoothed_bounded_walk(n, bound, step, 1, np.random.default_rng(seed))
        smooth = smoothed_bounded_walk(n, bound, step, 25, np.random.default_rng(seed))
        assert np.abs(raw).max() <= bound + 1e-12
        assert np.abs(smooth).max() <= bound + 1e-12
        # the window-25 series is exactly the moving average of the same raw walk
        assert_close(smooth, naive_moving_average(raw, 25), atol=1e-12, what="MA of the walk")
    # window effect: slice-to-slice change of a 25-wide moving average of a random walk is
    # ~ step / 5 versus ~ step for the raw walk (ratio ~ 1/sqrt(25)); measured over 20 seeds
    ratios = []
    for seed in range(20):
        raw = smoothed_bounded_walk(n, bound, step, 1, np.random.default_rng(seed))
        smooth = smoothed_bounded_walk(n, bound, step, 25, np.random.default_rng(seed))
        ratios.append(np.std(np.diff(smooth)) / np.std(np.diff(raw)))
    assert 0.1 < np.median(ratios) < 0.35
    # and the smoothed tilt has much less curvature (second differences)
    assert np.std(np.diff(smooth, 2)) < 0.05 * np.std(np.diff(raw, 2))


def naive_slice_positions(n, s_min, s_max, sigma, window, clip, eps, standardized=False):
    delta = (s_max - s_min) / (n - 1)
    smooth = naive_moving_average(eps, window) * (np.sqrt(window) if standardized else 1.0)
    m = np.clip(np.exp(sigma * smooth), *clip)
    s = [s_min]
    for i in range(n - 1):
        s.append(s[-1] + delta * m[i])
    s = np.array(s)
    return s_min + (s - s_min) * (s_max - s_min) / (s[-1] - s_min), m


@pytest.mark.parametrize("noise", ["mean", "standardized"])
def test_slice_positions_follow_the_paper(noise):
    n, s_min, s_max, clip = 300, -37.5, 212.0, (0.03, 10.0)
    for seed in range(10):
        s, m = slice_positions(n, s_min, s_max, sigma=1.8, window=61, clip=clip,
                               rng=np.random.default_rng(seed), noise=noise)
        eps = np.random.default_rng(seed).standard_normal(n - 1)
        s_ref, m_ref = naive_slice_positions(n, s_min, s_max, 1.8, 61, clip, eps,
                                             noise == "standardized")
        assert_close(s, s_ref, atol=1e-9, what="positions")
        assert_close(m, m_ref, atol=1e-12, what="multipliers")
        assert s[0] == s_min and s[-1] == s_max
        steps = np.diff(s)
        assert np.all(steps > 0)  # monotone
        assert np.all((m >= clip[0]) & (m <= clip[1]))
        # after the final rescale each step is Delta * m_i * k for one common factor k
        k = steps / ((s_max - s_min) / (n - 1) * m)
        assert_close(k, np.full_like(k, k[0]), rtol=1e-9, what="common rescale factor")
        assert steps.max() / steps.min() <= clip[1] / clip[0] * (1 + 1e-9)


def test_speed_noise_readings_differ_as_documented():
    """'mean' (MA as written) leaves the multipliers within ~exp(+-0.5): the clip never binds;
    'standardized' spreads them over most of [0.03, 10] (uneven speed like the real sweep)."""
    spreads, clipped = {}, {}
    for noise in ("mean", "standardized"):
        ms = np.concatenate([
            slice_positions(400, 0, 300, sigma=1.8, window=61, clip=(0.03, 10.0),
                            rng=np.random.default_rng(seed), noise=noise)[1]
            for seed in range(20)])
        spreads[noise] = np.percentile(ms, 95) / np.percentile(ms, 5)
        clipped[noise] = np.mean((ms == 0.03) | (ms == 10.0))
    assert spreads["mean"] < 3.0 and clipped["mean"] == 0.0
    assert spreads["standardized"] > 50.0 and clipped["standardized"] > 0.01


def test_dropped_slice_rate():
    n, p = 100_000, 0.05
    mask = dropped_slices(n, p, np.random.default_rng(3))
    assert abs(mask.sum() - n * p) < 5 * np.sqrt(n * p * (1 - p))


def test_false_hits_rate_neighbours_and_depths():
    n_slices, n_rays, p, k = 2000, 256, 0.003, 1
    events, affected, depth = false_hits(n_slices, n_rays, p, k, (0.1, 0.9),
                                         np.random.default_rng(5))
    n = n_slices * n_rays
    # event rate: binomial, 5 sigma bound
    assert abs(events.sum() - n * p) < 5 * np.sqrt(n * p * (1 - p))
    # affected rays are exactly the events dilated by k rays on each side, within a slice
    naive = np.zeros_like(events)
    for s, r in zip(*np.nonzero(events)):
        naive[s, max(0, r - k):r + k + 1] = True
    assert np.array_equal(affected, naive)
    # about (2k+1) p of the rays are affected
    assert abs(affected.mean() / p - (2 * k + 1)) < 0.3
    # depths: uniform in [0.1, 0.9], shared by an event's neighbours, NaN elsewhere
    d = depth[affected]
    assert d.min() >= 0.1 and d.max() <= 0.9
    assert abs(d.mean() - 0.5) < 0.02 and abs(np.std(d) - 0.8 / np.sqrt(12)) < 0.02
    assert np.isnan(depth[~affected]).all()
    isolated = [(s, r) for s, r in zip(*np.nonzero(events))
                if 1 <= r < n_rays - 1 and events[s, max(0, r - 2 * k):r + 2 * k + 1].sum() == 1]
    assert len(isolated) > 1000
    for s, r in isolated[:200]:
        assert depth[s, r - 1] == depth[s, r] == depth[s, r + 1]


def test_false_hits_without_neighbours_and_probability_zero():
    rng = np.random.default_rng(6)
    events, affected, _ = false_hits(100, 64, 0.05, 0, (0.1, 0.9), rng)
    assert np.array_equal(events, affected)
    events, affected, depth = false_hits(100, 64, 0.0, 2, (0.1, 0.9), rng)
    assert not affected.any() and np.isnan(depth).all()
