"""The slide probe of the polish (comreg_core.registration.search.polish.probe_slides) on the real
fibula sweep's first 30 frames: the search alone stops in the basin next to the right one, 4
mm along the shaft; polished again from 5 mm along the CT's long axis, it reaches the pose that
ICP from the recorded tracking finds (the pseudo ground truth of these frames), with a better
exact score. A whole sweep is not probed; a sweep whose stray points reach further than its bone
is still probed (frames 0-50)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from comreg_core.demo import pseudo_ground_truth
from comreg_core.register import Registrar
from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.live.points import SweepPoints
from comreg_core.live.stream import Frame
from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
from comreg_core.registration.geometry.extent import SLIDE_PROBE_MAX_SHARE, spread_mm
from comreg_core.registration.geometry.surface import ct_length_mm
from comreg_core.transforms import apply_transform
from tests.helpers import FIBULA_STL


def sweep_start(shared_data, frames: int):
    """``(points (N, 3), beam origins (N, 3))`` of the sweep's first ``frames``, as
    extract-us."""
    sweep = read_tracked_sweep(shared_data / "ultrabones100k-fibula")
    points = SweepPoints()
    for i in range(frames):
        points.add(Frame(i, sweep.frames[i], sweep.spacing, sweep.T_ref_image[i],
                         float(sweep.timestamps[i]), 0.0))
    cloud = points.cloud()
    return cloud.points, points.beam_origins(cloud)


@pytest.fixture(scope="module")
def first_frames(shared_data):
    """The sweep's frames 0-29 (:func:`sweep_start`; frames 0-27, half the CT long, are a patch
    whose starts over all rotations find the right basin without the probe)."""
    return sweep_start(shared_data, 30)


def test_the_probe_moves_a_slid_pose_into_the_right_basin(first_frames):
    pts, origins = first_frames
    registrar = Registrar.from_ct(FIBULA_STL)
    truth = pseudo_ground_truth(pts, registrar.surface)  # ICP from the recorded tracking
    centroid = pts.mean(axis=0)
    probed = registrar.register(pts, beam_origins=origins)
    registrar.search_config = replace(registrar.search_config, slide_probe_mm=0.0)
    plain = registrar.register(pts, beam_origins=origins)

    assert translation_error_mm(plain.T_ct_us, truth, centroid) > 3.0  # the next basin
    assert translation_error_mm(probed.T_ct_us, truth, centroid) < 1.0
    assert rotation_error_deg(probed.T_ct_us, truth) < 2.0
    chosen = probed.search.best.polish
    assert abs(chosen["slid_mm"]) == 5.0 and 3.0 < chosen["probe_shift_mm"] < 6.0
    assert probed.search.best.score_mm < 0.98 * plain.search.best.score_mm
    assert "slid_mm" not in plain.search.best.polish

    # a sweep along the whole bone is not probed (its basin is not in doubt)
    everything = registrar.register(registrar.surface.samples(3000)[0])
    assert "slid_mm" not in everything.search.best.polish


def test_stray_points_do_not_make_a_partial_sweep_whole(shared_data):
    # frames 0-50: the bone spans 0.79 of the CT (5th-95th percentile), stray points 0.86;
    # judged by the stray points the probe was skipped, and `register` said OK on the pose
    # slid 4.2 mm along the shaft
    pts, origins = sweep_start(shared_data, 51)
    registrar = Registrar.from_ct(FIBULA_STL)
    truth = pseudo_ground_truth(pts, registrar.surface)
    target = registrar.search_target(registrar.search_config.target_points)
    along = apply_transform(truth, pts) @ target.axes[:, 0]
    length = ct_length_mm(target)
    assert np.ptp(along) > SLIDE_PROBE_MAX_SHARE * length > spread_mm(along)

    result = registrar.register(pts, beam_origins=origins)
    assert "slid_mm" in result.search.best.polish
    centroid = pts.mean(axis=0)
    assert translation_error_mm(result.T_ct_us, truth, centroid) < 2.0
    assert rotation_error_deg(result.T_ct_us, truth) < 2.0
