"""Cross-sections: B-mode frames with the registered CT contour, and CT cuts with the registered
points, on the bundled sample sweep (real frames) and the shared fibula CT. A wrong registration
must look wrong: the contour leaves the bone echo, the points turn far-coloured."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from comreg_core.registration.geometry.surface import CTSurface
from comreg_core.report.sections import SECTION_HALF_WIDTH_MM, ct_sections, frame_overlays
from comreg_core.report.style import colormap_rgb
from comreg_core.transforms import apply_transform
from tests.helpers import FIBULA_STL


@pytest.fixture(scope="module")
def case():
    """The sample's 37 real frames, their bone points, the shared CT, the pose the search finds
    (the recording's own tracking is ~3 mm off) and a wrong pose 5 mm off the bone's face."""
    from comreg_core.demo import SAMPLE_SWEEP
    from comreg_core.register import Registrar
    from comreg_core.io import read_mesh
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.report.cameras import bone_frame
    from comreg_core.surfaces.us import extract_us_surface

    ct = read_mesh(FIBULA_STL)
    sweep = read_tracked_sweep(SAMPLE_SWEEP)
    points = extract_us_surface(sweep).points.points
    right = Registrar.from_ct(ct).register(points).T_ct_us
    frame = bone_frame(ct.vertices, ct.faces, ct.space)
    outward = apply_transform(right, points).mean(axis=0) - frame.center
    outward -= (outward @ frame.axis) * frame.axis
    wrong = right.copy()
    wrong[:3, 3] += 5.0 * outward / np.linalg.norm(outward)
    return ct, sweep, points, frame, {"right": right, "wrong": wrong}


def _far_share(images: list[np.ndarray]) -> float:
    """Share of the drawn points' pixels coloured 2.5 mm or more (the upper half of the 0-5 mm
    viridis map), the colour bar at the bottom left out."""
    palette = cKDTree(colormap_rgb(np.linspace(0.0, 1.0, 256)).astype(float))
    far = total = 0
    for image in images:
        pixels = image[: int(0.85 * image.shape[0])].reshape(-1, 3).astype(float)
        gap, nearest = palette.query(pixels, distance_upper_bound=12.0)
        is_point = gap < 12
        far += int((nearest[is_point] >= 128).sum())
        total += int(is_point.sum())
    return far / total


def test_ct_cuts_show_a_wrong_registration_in_far_colours(case):
    ct, _, points, frame, poses = case
    shares = {}
    for name, T in poses.items():
        registered = apply_transform(T, points)
        pictures = ct_sections(ct, frame, registered, CTSurface(ct).distance(registered))
        assert [p.name for p in pictures] == ["section_25", "section_50", "section_75"]
        along = (registered - frame.center) @ frame.axis
        for picture, q in zip(pictures, (0.25, 0.5, 0.75)):
            level = np.quantile(along, q)
            assert picture.n_points == int((np.abs(along - level) <= SECTION_HALF_WIDTH_MM).sum())
            assert picture.n_points > 50 and picture.image.shape == (480, 480, 3)
        shares[name] = _far_share([p.image for p in pictures])
    # right: only the detector's false echoes in one frame are far (measured 0.12); wrong: 1.0
    assert shares["right"] < 0.2 and shares["wrong"] > 0.8, shares


def test_frames_show_the_contour_on_the_bone_echo_only_when_right(case):
    ct, sweep, _, _, poses = case
    chosen = np.flatnonzero(sweep.valid)[[5, 18, 30]]
    brightness = {}
    for name, T in poses.items():
        pictures = frame_overlays(sweep.frames[chosen], T @ sweep.T_ref_pixel[chosen],
                                  sweep.spacing, ct, [sweep.frame_names[i] for i in chosen])
        values = []
        for picture, index in zip(pictures, chosen):
            assert picture.image.shape == sweep.frames[index].shape + (3,)
            height, width = sweep.image_shape
            xy = np.round(picture.contour_points).astype(int)
            xy = xy[(xy[:, 0] >= 0) & (xy[:, 0] < width) & (xy[:, 1] >= 0) & (xy[:, 1] < height)]
            assert len(xy) > 100  # the bone crosses every chosen frame
            top: dict[int, int] = {}  # the contour's side facing the probe, per image column
            for x, y in xy:
                top[x] = min(y, top.get(x, height))
            image = sweep.frames[index].astype(float)
            values += [image[max(0, y - 3):y + 4, x].max() for x, y in top.items()]
            drawn = np.all(picture.image == (240, 228, 66), axis=2)
            assert drawn.sum() > 100  # the contour is drawn in
        brightness[name] = float(np.mean(values))
    # the B-mode brightness (0-255) under the contour's probe side: the bone echo when right
    # (measured 124), dark tissue or shadow when 5 mm off (28)
    assert brightness["right"] > 80 and brightness["wrong"] < 0.5 * brightness["right"], brightness
