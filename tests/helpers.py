"""Shared test helpers: the one ``assert_close`` and small reference geometry builders."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Real recorded data shipped beside the project (see ../shared/data/README.md).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FIBULA_STL = SHARED_DATA / "ultrabones100k-fibula" / "fibula.stl"


def assert_close(actual, expected, *, rtol: float = 0.0, atol: float = 0.0, what: str = "value"):
    """Assert ``|actual - expected| <= atol + rtol * |expected|`` elementwise, with a message
    naming the worst element."""
    actual = np.asarray(actual, dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    assert actual.shape == expected.shape, f"{what}: shape {actual.shape} != {expected.shape}"
    err = np.abs(actual - expected)
    tol = atol + rtol * np.abs(expected)
    if not np.all(err <= tol):
        worst = np.unravel_index(np.argmax(err - tol), err.shape) if err.ndim else ()
        raise AssertionError(
            f"{what}: max error {err.max():.3g} beyond tolerance (atol={atol}, rtol={rtol}); "
            f"worst at {worst}: actual {actual[worst]!r} vs expected {expected[worst]!r}")


def random_rigid(rng: np.random.Generator, max_translation: float = 100.0) -> np.ndarray:
    """A random rigid ``(4, 4)`` transform (uniform rotation, translation in a cube, mm)."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-max_translation, max_translation, 3)
    return T
