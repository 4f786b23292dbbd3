"""The CT surface against independent references: an analytic box, VTK's exact distances,
hand-solved closest points on a triangle, scipy's KD-tree."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from comreg_core.errors import InvalidGeometryError
from comreg_core.registration.geometry import mesh_kernels
from comreg_core.registration.geometry.surface import (CTSurface, SurfaceCloud, estimate_normals,
                                                       sample_triangles)
from tests.helpers import BOX_CENTRE, assert_close, box_distance


# --- distances and samples ----------------------------------------------------------------------------------

def test_surface_distance_is_exact_point_to_triangle(box_surface):
    rng = np.random.default_rng(11)
    points = BOX_CENTRE + rng.uniform(-35, 35, (3000, 3))
    special = BOX_CENTRE + np.array([[0, 0, 5.0], [20, 10, 5], [25, 15, 10], [0, 0, 0],
                                     [19, 0, 0], [30, 0, 0], [20, 0, 0]])
    points = np.vstack([points, special])
    assert_close(box_surface.distance(points), box_distance(points), atol=1e-9,
                 what="distance to the box")


def test_surface_samples_are_on_the_surface_and_reproducible(box_surface, fibula_surface):
    points, normals = box_surface.samples(5000)
    assert_close(box_distance(points), np.zeros(5000), atol=1e-9)
    assert_close(np.linalg.norm(normals, axis=1), np.ones(5000), atol=1e-12)
    again, _ = type(box_surface)(box_surface).samples(5000)
    assert_close(again, points, atol=0, what="same seed, same samples")
    # area-uniform: the box faces get points in proportion to their areas (40x20 : 40x10 : 20x10)
    top = np.isclose(points[:, 2], BOX_CENTRE[2] + 5).mean() + np.isclose(
        points[:, 2], BOX_CENTRE[2] - 5).mean()
    assert abs(top - 2 * 800 / 2800) < 0.03
    fib, _ = fibula_surface.samples(2000)
    assert fibula_surface.distance(fib).max() < 1e-6


def test_closest_points_match_vtk_distances(fibula_surface):
    rng = np.random.default_rng(4)
    points, _ = fibula_surface.samples(3000)
    points = points + rng.normal(size=points.shape) * 1.0
    q, n, d = fibula_surface.closest(points, max_distance=20.0)
    exact = fibula_surface.distance(points)
    excess = d - exact
    # always a real surface point, so never nearer than the exact closest point ...
    assert excess.min() > -1e-9
    assert_close(fibula_surface.distance(q), np.zeros(len(q)), atol=1e-6, what="on surface")
    # ... and the closest one for almost every query, a hair farther for the others
    assert (excess < 1e-6).mean() > 0.97 and excess.max() < 0.2
    assert_close(np.linalg.norm(q - points, axis=1), d, atol=1e-9)
    assert_close(np.linalg.norm(n, axis=1), np.ones(len(n)), atol=1e-9)


def test_closest_point_on_a_triangle_in_every_region():
    a, b, c = np.array([0.0, 0, 0]), np.array([4.0, 0, 0]), np.array([0.0, 3, 0])
    cases = {(1.0, 1, 2): (1, 1, 0), (-1.0, -1, 0): (0, 0, 0), (5.0, -1, 1): (4, 0, 0),
             (-1.0, 4, 0): (0, 3, 0), (2.0, -2, 0): (2, 0, 0), (-2.0, 1, 0): (0, 1, 0),
             (4.0, 3, 0): tuple(np.array([4.0, 0, 0]) + np.array([-4.0, 3, 0]) * (
                 np.dot([0.0, 3, 0], [-4.0, 3, 0]) / 25))}
    for p, expected in cases.items():
        got = np.array(mesh_kernels._closest_on_triangle(np.array(p), np.stack([a, b, c]),
                                                    np.array([0, 1, 2])))
        assert_close(got, expected, atol=1e-12, what=f"closest point to {p}")



def test_closest_is_gated_and_batched_matcher_keeps_shapes(fibula_surface):
    points, _ = fibula_surface.samples(200)
    far = points + 50.0 * np.array([1.0, 0, 0])
    q, n, d = fibula_surface.closest(np.vstack([points, far]), max_distance=3.0)
    assert np.isfinite(d[:200]).all() and np.isinf(d[200:]).all()
    assert np.isnan(q[200:]).all() and np.isnan(n[200:]).all()
    match = fibula_surface.matcher(3.0)
    qb, nb, db = match(np.stack([points, far]))  # 2 200 3
    assert qb.shape == (2, 200, 3) and db.shape == (2, 200)
    assert_close(db[0], d[:200], atol=0)


def test_sample_triangles_is_area_uniform_and_seeded(box_surface):
    rng = np.random.default_rng(3)
    points, faces = sample_triangles(box_surface.vertices, box_surface.faces,
                                     box_surface.face_areas, 20_000, rng)
    counts = np.bincount(faces, minlength=len(box_surface.faces)) / 20_000
    assert_close(counts, box_surface.face_areas / box_surface.face_areas.sum(), atol=0.01)
    assert_close(box_distance(points), np.zeros(len(points)), atol=1e-9)


def test_cloud_nearest_matches_scipy_and_grid_is_close(fibula_surface):
    cloud = fibula_surface.cloud(20_000)
    assert cloud is fibula_surface.cloud(20_000)  # cached
    rng = np.random.default_rng(5)
    queries = cloud.points[rng.choice(len(cloud.points), 2000)] + rng.normal(size=(2000, 3)) * 3
    d, idx = cloud.nearest(queries)
    d_ref, idx_ref = cKDTree(cloud.points).query(queries)
    assert_close(d, d_ref, atol=1e-9, what="nearest distance vs scipy")
    approx = cloud.nearest_approx(queries)
    off = np.linalg.norm(cloud.points[approx] - queries, axis=1) - d_ref
    origin, spacing, grid = cloud.closest_point_grid
    assert off.max() <= np.sqrt(3) * spacing + 1e-9  # within a voxel diagonal of the nearest
    assert grid.size <= SurfaceCloud.GRID_VOXELS * 1.1
    q, nrm, dist = cloud.match(queries, max_distance=2.0)
    assert_close(dist[d_ref <= 2.0], d_ref[d_ref <= 2.0], atol=1e-9)
    assert np.isinf(dist[d_ref > 2.0]).all()


def test_estimated_normals_of_a_plane_are_its_normal():
    rng = np.random.default_rng(2)
    plane = np.column_stack([rng.uniform(0, 50, 500), rng.uniform(0, 50, 500), np.zeros(500)])
    normals = estimate_normals(plane)
    assert_close(np.abs(normals[:, 2]), np.ones(500), atol=1e-9)


def test_bad_surfaces_are_clear_errors():
    with pytest.raises(InvalidGeometryError, match="fewer than 10"):
        SurfaceCloud(np.zeros((5, 3)))
    with pytest.raises(InvalidGeometryError, match="Cannot use"):
        CTSurface(42)
    flat = (np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), np.array([[0, 1, 2]]))
    with pytest.raises(InvalidGeometryError, match="zero area"):
        CTSurface(flat)
