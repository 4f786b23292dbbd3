"""Screenshots: against stored reference images (with a tolerance) and for content (numbers).

Reference images: ``tests/report/reference/<scene>_<view>.png``, 320 x 320, rendered by Mesa
llvmpipe (EGL or OSMesa: they give the same pixels, checked below). A screenshot passes when the
mean absolute difference over all pixels and channels is <= 1.5 (of 255) and at most 0.5 % of the
pixels differ by more than 40 in some channel. Re-create them after an intended change of the
look with ``COMREG_UPDATE_REFERENCE_IMAGES=1 .venv/bin/python -m pytest tests/report`` and look
at them before committing. With a GPU's OpenGL (not llvmpipe) the comparison is skipped and only
the content checks run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from comreg_core.errors import InvalidGeometryError
from comreg_core.report.cameras import VIEW_NAMES
from comreg_core.report.scenes import (SCENES, SLAB_MARGIN_MM, SceneData, SceneRenderer,
                                       render_scene, render_screenshots)
from comreg_core.report.style import colormap_rgb
from tests.report.support import (REFERENCE_DIR, TEST_WINDOW, UPDATE_ENV, after_mask,
                                  background_fraction, before_mask, bone_mask, compare_images,
                                  near_mask)

MEAN_DIFF_MAX = 1.5
BAD_PIXELS_MAX = 0.005
ALL = [(scene, view) for scene in SCENES for view in VIEW_NAMES]
#: Rows of the title and legend (top 12 % of the image) hold text and legend discs.
TEXT_ROWS = int(0.12 * TEST_WINDOW[1])


def _load_png(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"))


def _require_llvmpipe() -> None:
    """The references are Mesa llvmpipe pixels; a GPU driver shades and rasterises points a
    little differently, so there only the content checks run."""
    from comreg_core.report.backend import cached_backend, ensure_offscreen_rendering

    backend = cached_backend() or ensure_offscreen_rendering()
    if "llvmpipe" not in backend.renderer:
        pytest.skip(f"reference images are Mesa llvmpipe renderings; this is {backend.renderer!r}")


def _check_against_reference(image: np.ndarray, name: str) -> None:
    from PIL import Image

    _require_llvmpipe()
    path = REFERENCE_DIR / f"{name}.png"
    if os.environ.get(UPDATE_ENV) == "1":
        REFERENCE_DIR.mkdir(parents=True, exist_ok=True)
        Image.fromarray(image).save(path, optimize=True)
        pytest.skip(f"wrote reference image {path}")
    assert path.is_file(), f"no reference image {path}; create it with {UPDATE_ENV}=1"
    mean_diff, bad = compare_images(image, _load_png(path))
    assert mean_diff <= MEAN_DIFF_MAX and bad <= BAD_PIXELS_MAX, (
        f"{name}: mean abs difference {mean_diff:.2f} (max {MEAN_DIFF_MAX}), "
        f"{100 * bad:.2f}% pixels off by > 40 (max {100 * BAD_PIXELS_MAX}%)")


@pytest.mark.parametrize("scene, view", ALL)
def test_screenshot_matches_reference(shots, scene, view):
    shot = shots[(scene, view)]
    assert shot.image.shape == (TEST_WINDOW[1], TEST_WINDOW[0], 3)
    assert shot.image.dtype == np.uint8
    _check_against_reference(shot.image, f"{scene}_{view}")


def test_rendering_is_deterministic(scene_data, shots):
    with SceneRenderer(scene_data, "overlay", window_size=TEST_WINDOW) as renderer:
        again = renderer.screenshot("lateral").image
    assert np.array_equal(again, shots[("overlay", "lateral")].image)


@pytest.mark.parametrize("scene, view", ALL)
def test_screenshot_is_not_blank(shots, scene, view):
    image = shots[(scene, view)].image
    assert image.std() > 15.0
    assert 0.02 <= 1.0 - background_fraction(image) <= 0.5


@pytest.mark.parametrize("scene", ["registered", "overlay"])
@pytest.mark.parametrize("view", VIEW_NAMES)
def test_ct_bone_colour_is_visible_where_the_ct_projects(shots, case, scene, view):
    shot = shots[(scene, view)]
    mask = bone_mask(shot.image)
    mask[:TEXT_ROWS] = False
    assert mask.mean() >= 0.003, f"bone colour on {mask.mean():.2%} of the image"
    ct = near_mask(mask.shape, shot.camera.project(case.ct.vertices), 2)
    assert ct[mask].mean() >= 0.97  # bone-coloured pixels are on the CT's projection


@pytest.mark.parametrize("scene", ["overlay"])
@pytest.mark.parametrize("view", VIEW_NAMES)
def test_registered_points_are_blue_where_they_project(shots, case, scene, view):
    shot = shots[(scene, view)]
    mask = after_mask(shot.image)
    mask[:TEXT_ROWS] = False  # the legend's blue disc
    assert mask.mean() >= 0.002
    pixels = shot.camera.project(case.us_after)
    assert near_mask(mask.shape, pixels, 3)[mask].mean() >= 0.97
    cols, rows = pixels[:, 0].astype(int), pixels[:, 1].astype(int)
    on_blue = mask[rows, cols].mean()
    # Seen from the front the patch faces the camera, so every point shows; from the side or end
    # some are behind the translucent bone (blended) or behind other points.
    assert on_blue >= (0.95 if view == "anterior" else 0.5), on_blue


@pytest.mark.parametrize("view", VIEW_NAMES)
def test_points_before_registration_are_vermillion_where_they_project(shots, case, view):
    shot = shots[("overlay", view)]
    mask = before_mask(shot.image)
    mask[:TEXT_ROWS] = False
    assert mask.mean() >= 0.002
    pixels = shot.camera.project(case.us_before)
    assert near_mask(mask.shape, pixels, 3)[mask].mean() >= 0.97
    cols, rows = pixels[:, 0].astype(int), pixels[:, 1].astype(int)
    assert mask[rows, cols].mean() >= 0.9
    # ...and they are not where the registered points are drawn: the misalignment (45 mm to the
    # left, 10 mm anterior, rotated) shows from the front and end-on; from the left it is mostly
    # along the line of sight.
    if view != "lateral":
        after = shot.camera.project(case.us_after)
        assert np.linalg.norm(pixels.mean(0) - after.mean(0)) > 20  # pixels


def test_registered_scene_has_no_before_colour(shots):
    for view in VIEW_NAMES:
        image = shots[("registered", view)].image
        assert before_mask(image).mean() < 1e-4


def _lut_position(rgb: np.ndarray) -> float:
    """Where on the colour map a rendered colour sits, ignoring shading: compare colours
    normalised by their largest channel with the map's, sampled finely."""
    t = np.linspace(0, 1, 1001)
    table = colormap_rgb(t)
    table /= table.max(axis=1, keepdims=True)
    colour = np.asarray(rgb, np.float64)
    colour = colour / colour.max()
    return float(t[np.argmin(np.linalg.norm(table - colour, axis=1))])


def _far_share(image: np.ndarray, pixels: np.ndarray) -> float:
    """Share of the given pixels whose colour sits in the upper half of the distance map
    (2.5 mm or more from the CT surface)."""
    cols, rows = pixels[:, 0].astype(int), pixels[:, 1].astype(int)
    return float(np.mean([_lut_position(image[r, c]) >= 0.5 for c, r in zip(cols, rows)]))


def test_a_wrong_registration_shows_far_coloured_points(case):
    """The registered scene colours the US points by their distance to the CT: the right
    registration's points are dark (near 0 mm), the same points slid 15 mm along the bone and
    moved 10 mm across it are mostly coloured as >= 2.5 mm."""
    frame = SceneData(case.ct).frame
    wrong = case.us_after + 15.0 * frame.axis + 10.0 * frame.left
    shares = {}
    for name, points in (("right", case.us_after), ("wrong", wrong)):
        data = SceneData(case.ct, us_after=points)
        with SceneRenderer(data, "registered", window_size=TEST_WINDOW, show_text=False) as r:
            shot = r.screenshot("anterior")
        shares[name] = _far_share(shot.image, shot.camera.project(points))
    print("share of US points coloured >= 2.5 mm:", shares)
    assert shares["right"] < 0.1 and shares["wrong"] > 0.5


@pytest.mark.parametrize("view", VIEW_NAMES)
def test_point_far_from_the_ct_gets_the_top_colour(shots, case, view):
    shot = shots[("completion", view)]
    col, row = shot.camera.project(case.far_point[None])[0].astype(int)
    assert _lut_position(shot.image[row, col]) >= 0.95


def test_distance_colour_map_positions(case):
    """Three isolated points with given distances land at 0, 1/2 and the top of the map."""
    frame = SceneData(case.ct).frame
    points = frame.center + 40.0 * frame.left + np.outer([-60.0, 0.0, 60.0], frame.axis)
    data = SceneData(case.ct, completion=points,
                     completion_distance_mm=np.array([0.0, 2.5, 9.0]))
    with SceneRenderer(data, "completion", window_size=TEST_WINDOW, show_text=False) as r:
        shot = r.screenshot("anterior")
    found = []
    for col, row in shot.camera.project(points).astype(int):
        found.append(_lut_position(shot.image[row, col]))
    assert found == pytest.approx([0.0, 0.5, 1.0], abs=0.06)


def test_projection_matches_vtk(scene_data, case):
    with SceneRenderer(scene_data, "overlay", window_size=(320, 240)) as renderer:
        for view in VIEW_NAMES:
            shot = renderer.screenshot(view)
            vtk_renderer = renderer.plotter.renderer
            points = np.vstack([case.us_after[:5], case.us_before[:5], case.far_point[None]])
            ours = shot.camera.project(points)
            for point, (col, row) in zip(points, ours):
                vtk_renderer.SetWorldPoint(*point, 1.0)
                vtk_renderer.WorldToDisplay()
                x, y, _ = vtk_renderer.GetDisplayPoint()
                assert col == pytest.approx(x, abs=0.01)
                assert row == pytest.approx(240 - y, abs=0.01)


def test_ras_input_gives_the_same_picture(case, shots):
    from comreg_core.transforms import apply_transform, space_change

    T = space_change("LPS", "RAS")
    shot = render_scene(case.ct.in_space("RAS"), us_after=apply_transform(T, case.us_after),
                        scene="registered", view="anterior", window_size=TEST_WINDOW)
    mean_diff, bad = compare_images(shot.image, shots[("registered", "anterior")].image)
    assert mean_diff <= 0.5 and bad <= 0.001


def test_bone_axis_view_cuts_the_ct_to_the_registered_points(scene_data, case):
    with SceneRenderer(scene_data, "registered", window_size=TEST_WINDOW) as renderer:
        frame = scene_data.frame
        span = (case.us_after - frame.center) @ frame.axis
        slab = (renderer._slab_vertices - frame.center) @ frame.axis
        assert slab.min() >= span.min() - SLAB_MARGIN_MM - 1e-3
        assert slab.max() <= span.max() + SLAB_MARGIN_MM + 1e-3
        assert "CT cut" in renderer.view_title("bone_axis")
        assert "CT cut" not in renderer.view_title("anterior")
        whole = renderer.camera("anterior")
        end_on = renderer.camera("bone_axis")
        assert end_on.mm_per_pixel < whole.mm_per_pixel  # the cross-section fills the view


def test_ct_alone(case):
    shot = render_scene(case.ct, view="lateral", window_size=(200, 200), show_text=False)
    assert shot.scene == "ct"
    assert bone_mask(shot.image).mean() > 0.01
    assert after_mask(shot.image).mean() == 0 and before_mask(shot.image).mean() == 0


def test_bad_points_are_rejected_before_rendering(case):
    bad = case.us_after.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InvalidGeometryError, match="non-finite"):
        SceneData(case.ct, us_after=bad)
    with pytest.raises(InvalidGeometryError, match="expected \\(N, 3\\)"):
        SceneData(case.ct, us_before=case.us_after[:, :2])
    with pytest.raises(ValueError, match="needs us_before"):
        next(render_screenshots(SceneData(case.ct, us_after=case.us_after), ["overlay"]))


_OTHER_BACKEND = r"""
import json, sys
import numpy as np
from comreg_core.io import read_mesh
from comreg_core.report.scenes import SceneData, SceneRenderer
from tests.helpers import FIBULA_STL
from tests.report.support import TEST_WINDOW, make_case
case = make_case(read_mesh(FIBULA_STL))
data = SceneData(case.ct, case.us_before, case.us_after, case.completion)
with SceneRenderer(data, "overlay", window_size=TEST_WINDOW) as renderer:
    image = renderer.screenshot("anterior").image
    window = renderer.plotter.render_window.GetClassName()
np.save(sys.argv[1], image)
print(json.dumps({"window": window}))
"""


def test_egl_and_osmesa_give_the_same_pixels(shots, tmp_path):
    from comreg_core.report.backend import EGL, OSMESA, cached_backend

    _require_llvmpipe()
    here = cached_backend().window_class
    other = OSMESA if here == EGL else EGL
    env = dict(os.environ, VTK_DEFAULT_OPENGL_WINDOW=other)
    root = Path(__file__).resolve().parents[2]
    env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")])
    out = tmp_path / "image.npy"
    done = subprocess.run([sys.executable, "-c", _OTHER_BACKEND, str(out)], env=env, cwd=root,
                          capture_output=True, text=True, timeout=120)
    if done.returncode != 0 or json.loads(done.stdout.strip().splitlines()[-1])["window"] != other:
        pytest.skip(f"{other} does not render here: {done.stderr[-300:]}")
    image = np.load(out)
    mean_diff, bad = compare_images(image, shots[("overlay", "anterior")].image)
    assert mean_diff <= 0.5 and bad <= 0.001, (mean_diff, bad)
