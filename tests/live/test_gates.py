"""The live verdict's shortcut (comreg_core.live.gates.quick_then_full): a judgement without the
scale check and the profiles that is CHECK means the full one is CHECK too, so a live update
may stop there. Checked on real prefixes of the fibula sweep, their search results and poses
moved off them, and on a patch of the CT's own surface (an OK)."""

from __future__ import annotations

import numpy as np
import pytest

from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.live.gates import quick_then_full
from comreg_core.register.judge import Evidence, judge
from comreg_core.registration.geometry.surface import ct_length_mm
from comreg_core.live.points import SweepPoints
from comreg_core.live.stream import Frame
from tests.helpers import rigid_about
from tests.live.conftest import cut_sweep


@pytest.fixture(scope="module")
def cases(shared_data, search_registrar, tmp_path_factory):
    """``[(name, points (n, 3), T_ct_us (4, 4), Evidence)]``: the search's results on the live
    clouds of 8, 14 and 22 real frames (from frame 30; at most 1,000 points, as a live
    verdict), the last slid 12 mm along the CT and turned 20 deg about it, and a patch of the
    CT's own surface at its own pose."""
    sweep = read_tracked_sweep(cut_sweep(tmp_path_factory.mktemp("gates"), 30, 22))
    target = search_registrar.search_target(search_registrar.search_config.target_points)
    length = ct_length_mm(target)
    points, out = SweepPoints(), []
    for k in range(sweep.n_frames):
        points.add(Frame(k, sweep.frames[k], sweep.spacing, sweep.T_ref_image[k],
                         float(sweep.timestamps[k]), 0.0))
        if k + 1 in (8, 14, 22):
            pts = points.cloud().points
            pts = pts[np.sort(np.random.default_rng(0).choice(len(pts), min(len(pts), 1000),
                                                              replace=False))]
            result = search_registrar.register(pts, seed=0)
            out.append((f"{k + 1} frames", pts, result.T_ct_us,
                        Evidence.of(result, pts, length)))
    _, pts, T, evidence = out[-1]
    centre = T[:3, :3] @ pts.mean(axis=0) + T[:3, 3]
    axis = target.axes[:, 0]
    out.append(("slid 12 mm", pts, rigid_about([0, 0, 0], 12.0 * axis, centre) @ T, evidence))
    out.append(("turned 20 deg", pts, rigid_about(20.0 * axis, [0, 0, 0], centre) @ T,
                evidence))
    patch, result = _ct_patch(search_registrar)
    out.append(("CT patch", patch, np.eye(4), Evidence.of(result, patch, length)))
    return out


def _ct_patch(registrar):
    samples, _ = registrar.surface.samples(3000)
    target = registrar.search_target(registrar.search_config.target_points)
    along = (samples - target.centre) @ target.axes[:, 0]
    patch = samples[np.abs(along - np.median(along)) < 0.3 * ct_length_mm(target)][:1000]
    return patch, registrar.register(patch, seed=0)


def test_a_quick_check_means_a_full_check_and_the_full_figures_are_no_kinder(cases,
                                                                           search_registrar):
    surface = search_registrar.surface
    verdicts = []
    for name, pts, T, evidence in cases:
        quick = judge(pts, T, surface, evidence, scale_scan=False, profiles=False)
        full = judge(pts, T, surface, evidence, scale_scan=True, profiles=True)
        verdicts.append((name, quick.verdict, full.verdict))
        assert quick.ok or not full.ok, name
        assert full.figures["p_correct"] <= quick.figures["p_correct"], name
        assert full.figures["bound_mm"] >= quick.figures["bound_mm"], name
        for key in ("median_mm", "p90_mm", "noise_mm", "refit_shift_mm", "coverage"):
            assert full.figures[key] == quick.figures[key], (name, key)
        shortcut = quick_then_full(pts, T, surface, evidence, quick_first=True)
        assert shortcut.verdict == full.verdict, name
        if not quick.ok:  # the quick judgement's own figures
            assert shortcut.figures == quick.figures and shortcut.reasons == quick.reasons
        else:
            assert shortcut.figures == full.figures
        assert quick_then_full(pts, T, surface, evidence, quick_first=False).figures \
            == full.figures
    names = {name: (q, f) for name, q, f in verdicts}
    assert names["CT patch"] == ("ok", "ok"), verdicts
    assert names["slid 12 mm"][0] == "check" and names["turned 20 deg"][0] == "check", verdicts
