"""Shared test helpers: the one ``assert_close`` and small reference geometry builders."""

from __future__ import annotations

import contextlib
import csv
import shutil
from pathlib import Path

import numpy as np

#: Real recorded data shipped beside the project (see ../shared/data/README.md).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FIBULA_STL = SHARED_DATA / "ultrabones100k-fibula" / "fibula.stl"
FIBULA_DIR = SHARED_DATA / "ultrabones100k-fibula"


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


def tibia_like_mesh(length: float = 360.0, n_rings: int = 180, n_around: int = 96, *,
                    anatomical: bool = False):
    """A closed, tibia-like bone surface ``(vertices (V, 3) mm, faces (F, 3))`` made here, for
    learning benchmarks on a bone of another shape than the shared fibula: a 360 mm shaft with a
    rounded-triangular cross-section (anterior crest), a wide proximal plateau (two condyles and
    a tuberosity bump in front), a narrower distal end with a medial malleolus bulge. Long axis
    z (0 = distal, ``length`` = proximal), anterior +y, medial +x. Star-shaped rings, capped.

    Its mid-shaft (about 30-80 % of the length) is an extrusion: one cross-section, unchanged
    but for a 6 mm bow, so a short patch of it fits equally well anywhere along ~150 mm.
    ``anatomical=True`` makes the shaft vary as a real tibia's does: narrowest at the distal
    third (radius 10 mm there, widening to 12.5 mm at 70 %), triangular proximally and rounder distally,
    and twisted by 30 deg from end to end (tibial torsion)."""
    z = np.linspace(0.0, length, n_rings)
    theta = np.linspace(0.0, 2 * np.pi, n_around, endpoint=False)
    u = z / length
    # radius profile along the bone: narrow shaft, flared ends (proximal wider)
    base = 11.0 + 22.0 * np.exp(-((1 - u) / 0.09) ** 2) + 12.0 * np.exp(-(u / 0.07) ** 2)
    rings = []
    for k in range(n_rings):
        t = theta
        r = base[k] * (1.0 + 0.18 * np.cos(3 * (t - np.pi / 2)))  # triangular, crest in front
        if anatomical:
            twist = np.radians(30.0) * (u[k] - 0.5)
            shaft = min(10.0 + 16.0 * (u[k] - 0.3) ** 2, 12.5)  # narrowest at the distal third
            corners = 0.06 + 0.16 * u[k]  # rounder distally, triangular proximally
            r = (base[k] - 11.0 + shaft) * (1.0 + corners * np.cos(3 * (t - np.pi / 2 - twist)))
        prox = np.exp(-((1 - u[k]) / 0.06) ** 2)
        r = r * (1.0 + prox * (0.35 * np.cos(2 * t) ** 2 - 0.15 * np.sin(t)))  # condyles
        tub = np.exp(-((u[k] - 0.88) / 0.03) ** 2)
        r = r + 9.0 * tub * np.exp(-((t - np.pi / 2) / 0.35) ** 2)  # tuberosity, anterior
        mall = np.exp(-((u[k] - 0.03) / 0.04) ** 2)
        r = r + 10.0 * mall * np.exp(-(np.angle(np.exp(1j * t)) / 0.5) ** 2)  # medial malleolus
        bow = 6.0 * np.sin(np.pi * u[k])  # a gentle anterior bow of the shaft
        rings.append(np.stack([r * np.cos(t), r * np.sin(t) + bow, np.full_like(t, z[k])], 1))
    vertices = np.concatenate(rings + [np.array([[0.0, 0.0, -2.0], [0.0, 0.0, length + 2.0]])])
    faces = []
    n = n_around
    for k in range(n_rings - 1):
        a = k * n + np.arange(n)
        b = k * n + (np.arange(n) + 1) % n
        faces += [np.stack([a, b, a + n], 1), np.stack([b, b + n, a + n], 1)]
    bottom, top = len(vertices) - 2, len(vertices) - 1
    ring0, ring1 = np.arange(n), (n_rings - 1) * n + np.arange(n)
    faces.append(np.stack([np.full(n, bottom), (ring0 + 1) % n, ring0], 1))
    faces.append(np.stack([np.full(n, top), ring1, (n_rings - 1) * n + (np.arange(n) + 1) % n], 1))
    return vertices, np.concatenate(faces).astype(np.int64)


@contextlib.contextmanager
def immutable(folder: Path):
    """Make ``folder`` immutable (``chattr +i``: refused even to root, which plain permissions
    are not) for the ``with`` block; skips the test where chattr is unavailable or not allowed."""
    import shutil
    import subprocess

    import pytest

    if shutil.which("chattr") is None or subprocess.run(
            ["chattr", "+i", str(folder)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not available here")
    try:
        yield folder
    finally:
        subprocess.run(["chattr", "-i", str(folder)], check=True)


# --- an axis-aligned box "bone" with analytic distances ---

BOX_CENTRE = np.array([100.0, -50.0, 300.0])
BOX_HALF = np.array([20.0, 10.0, 5.0])


def box_distance(points: np.ndarray) -> np.ndarray:
    """Exact unsigned distance of points to the surface of the box (analytic)."""
    q = np.abs(np.asarray(points, dtype=np.float64) - BOX_CENTRE) - BOX_HALF
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = -q.max(axis=1)
    return np.where((q > 0).any(axis=1), outside, inside)


def rigid_about(rotvec_deg, translation, about) -> np.ndarray:
    """``(4, 4)`` rigid transform: a rotation (rotation vector, deg) about the point ``about``
    (mm), then a translation (mm)."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = np.asarray(about) - T[:3, :3] @ np.asarray(about) + np.asarray(translation,
                                                                              dtype=np.float64)
    return T


def cut_sweep(out: Path, start: int, count: int, step: int = 1) -> Path:
    """Frames ``start, start + step, ...`` (``count`` of them) of the shared fibula sweep as a
    frame folder (frames/, tracking.csv, calibration.json) in ``out``."""
    (out / "frames").mkdir(parents=True)
    shutil.copy(FIBULA_DIR / "calibration.json", out / "calibration.json")
    with open(FIBULA_DIR / "tracking.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    keep = rows[start:][::step][:count]
    with open(out / "tracking.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(keep)
    for row in keep:
        shutil.copy(FIBULA_DIR / "frames" / f"{row['timestamp']}.png", out / "frames")
    return out


def paths_under(root: Path) -> set[str]:
    """Every path under ``root`` (relative to it), to see what a command left behind."""
    return {str(p.relative_to(root)) for p in root.rglob("*")}
