"""Warm re-registration of a grown sweep (comreg_core/registration/search/warm.py through
Registrar.register(warm_start=...)): the pose the full search finds on the grown cloud, from
a handful of poses, with the same evidence fields."""

from dataclasses import replace

import numpy as np
import pytest

from comreg_core.errors import ComRegError
from comreg_core.register import Registrar
from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
from comreg_core.registration.search.warm import WARM_TOP
from comreg_core.transforms import apply_transform, invert_rigid
from tests.helpers import FIBULA_STL, random_rigid


@pytest.fixture(scope="module")
def grown_sweep(fibula_patch):
    """The fibula patch moved by a known pose, as a sweep that grew: its first 60 % along its
    long spread, then all of it. Returns ``(first, all, T_ct_us truth)``."""
    T_us_ct = random_rigid(np.random.default_rng(7), max_translation=80.0)
    points = apply_transform(T_us_ct, fibula_patch[::4])
    centred = points - points.mean(axis=0)
    along = centred @ np.linalg.svd(centred, full_matrices=False)[2][0]
    order = np.argsort(along)
    return points[order[:int(0.6 * len(order))]], points, invert_rigid(T_us_ct)


def test_a_warm_start_finds_the_full_search_pose_from_few_poses(grown_sweep):
    first, grown, T_truth = grown_sweep
    registrar = Registrar.from_ct(FIBULA_STL)
    earlier = registrar.register(first)
    full = registrar.register(grown)
    warm = registrar.register(grown, warm_start=earlier)
    centroid = grown.mean(axis=0)
    for result in (earlier, full, warm):  # every one right: RTE < 1 mm, RRE < 1 deg
        assert translation_error_mm(result.T_ct_us, T_truth, centroid) < 1.0
        assert rotation_error_deg(result.T_ct_us, T_truth) < 1.0
    assert translation_error_mm(warm.T_ct_us, full.T_ct_us, centroid) < 0.2
    assert warm.info["warm_start"] and not full.info["warm_start"]
    assert warm.search.starts_tried <= WARM_TOP < full.search.starts_tried
    assert warm.search.chosen == earlier.search.chosen
    assert 0.0 <= warm.confidence <= 1.0 and warm.search.polish is not None
    assert warm.n_points == len(grown) and warm.residuals["median"] < 0.5
    # without residuals (live updates): the same pose, bit for bit, and no distances measured
    quiet = registrar.register(grown, warm_start=earlier, residuals=False)
    assert np.array_equal(quiet.T_ct_us, warm.T_ct_us) and quiet.residuals == {}


def test_a_warm_start_needs_the_search(grown_sweep):
    first, grown, _ = grown_sweep
    registrar = Registrar.from_ct(FIBULA_STL)
    earlier = registrar.register(first)
    with pytest.raises(ComRegError, match="warm start needs the pose search"):
        registrar.register(grown, warm_start=replace(earlier, search=None))
