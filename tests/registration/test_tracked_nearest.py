"""The ICP's remembering nearest-point matcher: scipy's KD-tree answers, and the cloud's own
``match`` bit for bit, with most queries skipped while points move little."""

import numpy as np
from scipy.spatial import cKDTree

from comreg_core.registration.geometry.icp import point_to_plane_icp
from comreg_core.registration.geometry.tracked_nearest import NearestTracker
from tests.helpers import rigid_about


def _moving_points(cloud, rng, starts=4, n=300, steps=12):
    """``steps`` arrays ``(starts, n, 3)``: noisy surface points drifting by shrinking steps."""
    points = cloud.points[rng.choice(len(cloud.points), n, replace=False)]
    current = np.stack([points + rng.normal(0, 2.0, 3) for _ in range(starts)])
    for step in range(steps):
        current = (current + rng.normal(0, 0.5 * 0.6 ** step, (starts, 1, 3))
                   + rng.normal(0, 0.02 * 0.6 ** step, current.shape))
        yield current


def test_the_tracker_answers_as_scipy_and_the_cloud_do(fibula_surface):
    cloud = fibula_surface.cloud(20_000)
    reference = cKDTree(cloud.points)
    tracker = NearestTracker(cloud)
    rng = np.random.default_rng(3)
    for step, points in enumerate(_moving_points(cloud, rng)):
        rows = np.arange(4) if step < 6 else np.array([0, 2, 3])  # starts drop out, as in ICP
        closest, normals, distance = tracker(points[rows], rows)
        d_ref, i_ref = reference.query(points[rows].reshape(-1, 3))
        np.testing.assert_array_equal(closest.reshape(-1, 3), cloud.points[i_ref])
        np.testing.assert_array_equal(normals.reshape(-1, 3), cloud.normals[i_ref])
        np.testing.assert_allclose(distance.reshape(-1), d_ref, rtol=0, atol=1e-12)
        for got, want in zip((closest, normals, distance), cloud.match(points[rows])):
            np.testing.assert_array_equal(got, want)  # the same bits as the tree's
    total = tracker.queried + tracker.reused
    assert total == 6 * 4 * 300 + 6 * 3 * 300
    assert tracker.reused > 0.7 * total, (tracker.queried, tracker.reused)  # measured: 80 %


def test_more_remembered_points_skip_more_queries_with_the_same_answers(fibula_surface):
    """Measured share answered from memory: 60 / 74 / 82 % with 1 / 2 / 4 remembered."""
    cloud = fibula_surface.cloud(20_000)
    shares = []
    for remembered in (1, 2, 4):
        tracker = NearestTracker(cloud, remembered=remembered)
        for points in _moving_points(cloud, np.random.default_rng(3)):
            for got, want in zip(tracker(points), cloud.match(points)):
                np.testing.assert_array_equal(got, want)
        shares.append(tracker.reused / (tracker.queried + tracker.reused))
    assert shares[0] + 0.05 < shares[1] < shares[2] - 0.05, shares


def test_a_point_moved_beyond_its_reach_is_queried_again(fibula_surface):
    cloud = fibula_surface.cloud(20_000)
    tracker = NearestTracker(cloud)
    points = cloud.points[:50] + 0.3 * cloud.normals[:50]
    tracker(points)
    assert (tracker.queried, tracker.reused) == (50, 0)
    tracker(points)  # unmoved: every nearest point is known
    assert (tracker.queried, tracker.reused) == (50, 50)
    jumped = points.copy()
    jumped[:7] += 25.0  # far beyond any sample spacing
    closest, _, distance = tracker(jumped)
    assert (tracker.queried, tracker.reused) == (57, 93)
    d_ref, i_ref = cKDTree(cloud.points).query(jumped)
    np.testing.assert_array_equal(closest, cloud.points[i_ref])
    np.testing.assert_allclose(distance, d_ref, rtol=0, atol=1e-12)


def test_icp_with_the_tracker_ends_where_it_ends_without(fibula_surface, fibula_patch):
    """The same poses, residuals and iteration counts, bit for bit, from 1-6 mm / deg off."""
    cloud = fibula_surface.cloud(20_000)
    points = fibula_patch[::4]
    rng = np.random.default_rng(5)
    starts = np.stack([rigid_about(rng.normal(size=3) * s, rng.normal(size=3) * s,
                                   points.mean(axis=0)) for s in (1.0, 2.0, 4.0, 6.0)])
    plain = point_to_plane_icp(points, starts, cloud.match, iterations=30, trim_fraction=0.1)
    tracker = NearestTracker(cloud)
    tracked = point_to_plane_icp(points, starts, tracker, iterations=30, trim_fraction=0.1)
    for got, want in zip(tracked, plain):
        np.testing.assert_array_equal(got, want)
    assert plain.iterations.min() >= 3
    total = tracker.queried + tracker.reused  # measured: 47 % skipped (dense, noiseless)
    assert tracker.reused > 0.35 * total, (tracker.queried, tracker.reused)


def test_a_gated_tracker_leaves_far_pairs_unmatched_as_the_cloud_does(fibula_surface):
    cloud = fibula_surface.cloud(20_000)
    tracker = NearestTracker(cloud, max_distance=2.0)
    rng = np.random.default_rng(4)
    unmatched = 0
    for points in _moving_points(cloud, rng, steps=6):
        got = tracker(points)
        for a, b in zip(got, cloud.match(points, max_distance=2.0)):
            np.testing.assert_array_equal(a, b)
        unmatched += int(np.isinf(got[2]).sum())
    assert 0 < unmatched < 6 * 4 * 300  # some pairs beyond 2 mm, not all
