"""The paper's stochastic processes, as small vectorised numpy functions of a seeded Generator.

Each function is one sentence of the paper (section 2, "Patient-specific Synthetic US Bone Surface
Simulation"); the simulator composes them. Nothing here knows about meshes or rays.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter1d


def moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average ``MA_w`` of a 1-D series, same length, ends padded with the edge
    value (so an average of values in [a, b] stays in [a, b]). ``window=1`` returns a copy."""
    x = np.asarray(x, dtype=np.float64)
    if window <= 1 or len(x) == 0:
        return x.copy()
    return uniform_filter1d(x, size=int(window), mode="nearest")


def reflected_walk(n: int, lo: float, hi: float, step: float, start: float,
                   rng: np.random.Generator) -> np.ndarray:
    """Bounded random walk of ``n`` values in ``[lo, hi]``: Gaussian steps of std ``step`` from
    ``start``, reflected at the bounds (a free walk folded into the interval, which has the law
    of a walk reflected step by step)."""
    if n <= 0:
        return np.zeros(0)
    if hi <= lo:
        return np.full(n, lo, dtype=np.float64)
    steps = rng.normal(0.0, step, n - 1) if step > 0 else np.zeros(n - 1)
    free = start + np.concatenate([[0.0], np.cumsum(steps)])
    span = hi - lo
    folded = np.mod(free - lo, 2.0 * span)
    return lo + np.where(folded <= span, folded, 2.0 * span - folded)


def smoothed_bounded_walk(n: int, bound: float, step_fraction: float, window: int,
                          rng: np.random.Generator) -> np.ndarray:
    """Per-slice tilt angles: a random walk bounded to ``[-bound, bound]`` (starting at 0, steps
    of std ``step_fraction * bound``) followed by a moving average of ``window`` slices.
    The result stays within the bound. Units follow ``bound``."""
    walk = reflected_walk(n, -bound, bound, step_fraction * bound, 0.0, rng)
    return moving_average(walk, window)


def slice_positions(n: int, s_min: float, s_max: float, *, sigma: float, window: int,
                    clip: tuple[float, float], rng: np.random.Generator,
                    noise: str = "mean") -> tuple[np.ndarray, np.ndarray]:
    """Non-uniform sweep speed: ``n`` monotone slice positions from ``s_min`` to ``s_max``.

    Delta = (s_max - s_min)/(n-1); eps_i ~ N(0, 1) for the n-1 steps; eps~ = MA_w(eps) (times
    sqrt(w) if ``noise == "standardized"``); m_i = clip(exp(sigma eps~_i), f_min, f_max);
    s_0 = s_min, s_{i+1} = s_i + Delta m_i; finally rescaled linearly about s_min so that
    s_{n-1} = s_max.

    Returns:
        positions ``(n,)`` (same units as s_min, s_max) and the multipliers m ``(n-1,)``.
    """
    if n < 2:
        return np.array([s_min], dtype=np.float64)[:n], np.zeros(0)
    delta = (s_max - s_min) / (n - 1)
    eps = rng.standard_normal(n - 1)
    smooth = moving_average(eps, window)
    if noise == "standardized":
        smooth = smooth * np.sqrt(max(int(window), 1))
    multipliers = np.clip(np.exp(sigma * smooth), clip[0], clip[1])
    s = s_min + np.concatenate([[0.0], np.cumsum(delta * multipliers)])
    if s[-1] != s_min:
        s = s_min + (s - s_min) * ((s_max - s_min) / (s[-1] - s_min))
    s[0], s[-1] = s_min, s_max
    return s, multipliers


def dropped_slices(n: int, probability: float, rng: np.random.Generator) -> np.ndarray:
    """``(n,)`` bool mask of dropped slices, each dropped independently with ``probability``."""
    return rng.random(n) < probability


def false_hits(n_slices: int, n_rays: int, probability: float, neighbors: int,
               depth_range: tuple[float, float], rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Segmentation noise: each ray starts a false intersection with ``probability``; it also
    replaces the result of ``neighbors`` rays on each side in the same slice, all at the event's
    depth fraction drawn uniformly from ``depth_range`` (where events overlap, the nearest event
    sets the depth).

    Returns:
        events ``(n_slices, n_rays)`` bool (where an event starts), affected ``(n_slices,
        n_rays)`` bool, and depth ``(n_slices, n_rays)`` fraction of the image depth (NaN where
        not affected).
    """
    events = rng.random((n_slices, n_rays)) < probability
    event_depth = rng.uniform(depth_range[0], depth_range[1], (n_slices, n_rays))
    depth = np.full((n_slices, n_rays), np.nan)
    # 2k+1 shifted copies (not a loop over rays), farthest first so the nearest event wins
    for offset in sorted(range(-neighbors, neighbors + 1), key=lambda o: (-abs(o), o)):
        src = slice(max(0, -offset), n_rays - max(0, offset))
        dst = slice(max(0, offset), n_rays - max(0, -offset))
        hit = events[:, src]
        target = depth[:, dst]
        target[hit] = event_depth[:, src][hit]
    affected = ~np.isnan(depth)
    return events, affected, depth
