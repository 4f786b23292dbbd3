"""Synthetic B-mode frames with a known bone, shared by the ultrasound surface tests."""

from __future__ import annotations

import numpy as np

PX = 0.1  # mm per pixel of the synthetic frames


def bone_depth(x_mm):
    """Depth (mm) of the synthetic bone surface under lateral position ``x_mm`` (a convex arc
    from x = 12 to 30 mm, 17.6 to 20 mm deep; its shadow covers a third of the width)."""
    return 20.0 - 0.03 * (x_mm - 21.0) ** 2


def synthetic_frame(rng, *, bone=True, shadow=True, line=False, H=400, W=500):
    """A B-mode-like frame (PX mm pixels): Rayleigh speckle tissue under a 1 mm dark gel band,
    optionally a bright bone echo on :func:`bone_depth` with an acoustic shadow below it, or a
    bright horizontal fascia line with tissue below."""
    depth = (np.arange(H)[:, None] + 0.0) * PX
    x = np.arange(W)[None, :] * PX
    image = rng.rayleigh(35.0, (H, W)) * np.exp(-0.01 * depth)
    image[depth[:, 0] < 1.0] = rng.rayleigh(2.0, (int(1.0 / PX), W))
    if bone:
        surface = bone_depth(x)
        on = (x >= 12) & (x <= 30)
        echo = 220.0 * np.exp(-0.5 * ((depth - surface) / 0.15) ** 2) * on
        if shadow:
            image = np.where(on & (depth > surface + 0.3), image * 0.08, image)
        image = image + echo
    if line:
        image = image + 220.0 * np.exp(-0.5 * ((depth - 12.0) / 0.15) ** 2)
    return np.clip(image, 0, 255).astype(np.uint8)
