"""Test data and image helpers for the report tests: the real fibula, a US-like patch of it, a
known misalignment, a completion with one far point, and colour classifiers."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from comreg_core.transforms import apply_transform

REFERENCE_DIR = Path(__file__).resolve().parent / "reference"
#: Set to 1 to (re)write the reference images instead of comparing with them.
UPDATE_ENV = "COMREG_UPDATE_REFERENCE_IMAGES"
#: Small screenshots keep the tests fast and the stored references small (< 40 KB each).
TEST_WINDOW = (320, 320)


@dataclass
class Case:
    ct: object            # SurfaceMesh (LPS)
    us_after: np.ndarray  # (N, 3) on the CT surface: a one-sided patch of the shaft
    us_before: np.ndarray  # (N, 3) the same under a known rigid misalignment
    completion: np.ndarray  # (M, 3) near the surface, last point far away
    far_point: np.ndarray  # (3,)
    T_before_after: np.ndarray


def make_case(ct) -> Case:
    """Deterministic data from the fibula mesh (LPS): surface samples from the evaluation module's
    seeded area-uniform sampler."""
    from comreg_core.registration.geometry.surface import CTSurface
    from comreg_core.report.cameras import bone_frame

    surface = CTSurface(ct, sample_seed=7)
    points, normals = surface.samples(20000)
    frame = bone_frame(ct.vertices, ct.faces, ct.space)
    t = (points - frame.center) @ frame.axis
    # What one sweep sees: the middle 100 mm of the shaft, surfaces facing the probe (anterior).
    patch = (np.abs(t) < 50) & (normals @ frame.anterior > 0.3)
    us_after = points[patch][:1200]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [25, -15, 20], degrees=True).as_matrix()
    c = us_after.mean(axis=0)
    T[:3, 3] = c - T[:3, :3] @ c + 45.0 * frame.left + 10 * frame.anterior
    us_before = apply_transform(T, us_after)
    rng = np.random.default_rng(3)
    near = surface.samples(2000)[0] + rng.normal(0.0, 0.2, (2000, 3))
    far = frame.center + 30.0 * frame.left + 40.0 * frame.axis
    completion = np.vstack([near, far[None]])
    return Case(ct, us_after, us_before, completion, far, T)


# --- colours -------------------------------------------------------------------------------------

def hsv(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hue (degrees), saturation and value (0-1) of an (H, W, 3) uint8 image."""
    rgb = image.astype(np.float64) / 255.0
    mx, mn = rgb.max(-1), rgb.min(-1)
    delta = mx - mn
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        h = np.where(mx == r, ((g - b) / delta) % 6,
                     np.where(mx == g, (b - r) / delta + 2, (r - g) / delta + 4)) * 60.0
        s = np.where(mx > 0, delta / mx, 0.0)
    return np.nan_to_num(h), s, mx


def bone_mask(image: np.ndarray) -> np.ndarray:
    """Pixels of the semi-transparent bone on white: yellowish, weakly saturated, not dark."""
    h, s, v = hsv(image)
    return (h >= 30) & (h <= 60) & (s >= 0.12) & (s <= 0.6) & (v >= 0.35)


def before_mask(image: np.ndarray) -> np.ndarray:
    """Vermillion (213, 94, 0) under any shading: red-orange hue, strongly saturated."""
    h, s, v = hsv(image)
    return (h >= 10) & (h <= 35) & (s >= 0.7) & (v >= 0.25)


def after_mask(image: np.ndarray) -> np.ndarray:
    """Blue (0, 114, 178), also seen through the translucent bone: hue 185-225 deg."""
    h, s, v = hsv(image)
    return (h >= 185) & (h <= 225) & (s >= 0.25) & (v >= 0.2)


def background_fraction(image: np.ndarray, rgb=(255, 255, 255)) -> float:
    return float((np.abs(image.astype(int) - np.array(rgb)).max(-1) <= 3).mean())


def near_mask(shape: tuple[int, int], pixels: np.ndarray, radius: int) -> np.ndarray:
    """Pixels within ``radius`` (Chebyshev) of any of the (col, row) ``pixels``."""
    from scipy.ndimage import binary_dilation

    mask = np.zeros(shape, bool)
    cols = np.floor(pixels[:, 0]).astype(int)
    rows = np.floor(pixels[:, 1]).astype(int)
    ok = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    mask[rows[ok], cols[ok]] = True
    return binary_dilation(mask, iterations=radius)


def compare_images(actual: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """(mean absolute difference over pixels and channels on the 0-255 scale, fraction of pixels
    whose largest channel difference exceeds 40)."""
    a = actual.astype(np.int16)
    r = reference.astype(np.int16)
    assert a.shape == r.shape, f"image shape {a.shape} != reference {r.shape}"
    diff = np.abs(a - r)
    return float(diff.mean()), float((diff.max(-1) > 40).mean())
