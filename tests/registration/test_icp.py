"""The one point-to-plane ICP: against known poses on the real fibula and an analytic box."""

import numpy as np
import pytest

from comreg_core.registration.geometry.icp import MESH_REFINE_POINTS
from comreg_core.registration.geometry.icp import (coarse_to_fine_icp, point_to_plane_icp,
                                                   refine_on_mesh)
from comreg_core.transforms import apply_transform
from tests.helpers import assert_close, box_distance, rigid_about


def _errors(T_est, T_true, points):
    c = points.mean(axis=0)
    rte = float(np.linalg.norm(apply_transform(T_est, c[None]) - apply_transform(T_true, c[None])))
    R = T_est[:3, :3].T @ T_true[:3, :3]
    return rte, float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


@pytest.mark.parametrize("trial", range(3))
def test_exact_icp_converges_from_1mm_1deg_on_clean_data(fibula_surface, fibula_patch, trial):
    rng = np.random.default_rng(trial)
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    axis, direction = axis / np.linalg.norm(axis), direction / np.linalg.norm(direction)
    points = fibula_patch[::2]
    start = rigid_about(axis * 1.0, direction * 1.0, points.mean(axis=0))  # truth = identity
    assert_close(_errors(start, np.eye(4), points), [1.0, 1.0], atol=1e-9)
    fit = point_to_plane_icp(points, start, fibula_surface.matcher(3.0), iterations=50,
                             tolerance_mm=1e-5)
    rte, rre = _errors(fit.T, np.eye(4), points)
    assert rte < 0.1 and rre < 0.1, f"RTE {rte:.4f} mm, RRE {rre:.4f} deg, {fit}"
    assert fit.converged and fit.inlier_fraction == 1.0 and fit.rmse_mm < 0.01




def test_a_batch_of_starts_equals_each_start_alone(fibula_surface, fibula_patch):
    points = fibula_patch[::8]
    cloud = fibula_surface.cloud(20_000)
    rng = np.random.default_rng(1)
    starts = np.stack([rigid_about(rng.normal(size=3) * 3, rng.normal(size=3) * 3, points.mean(0))
                       for _ in range(4)])
    batch = point_to_plane_icp(points, starts, cloud.match, iterations=30, trim_fraction=0.1)
    for i in range(4):
        alone = point_to_plane_icp(points, starts[i], cloud.match, iterations=30,
                                   trim_fraction=0.1)
        assert_close(batch.T[i], alone.T, atol=1e-9, what=f"start {i}")
        assert batch.iterations[i] == alone.iterations
    for T in batch.T:
        rte, rre = _errors(T, np.eye(4), points)
        assert rte < 0.5 and rre < 0.5


def test_one_cloud_per_start(box_surface, box_cloud):
    """(B, n, 3) sources: each start moves its own cloud (the verdict's scale scan)."""
    shifted = np.stack([box_cloud + [0.5, 0.0, 0.3], box_cloud + [-0.4, 0.0, -0.2]])
    fit = point_to_plane_icp(shifted, np.tile(np.eye(4), (2, 1, 1)), box_surface.matcher(5.0),
                             iterations=30, tolerance_mm=1e-7)
    for T, src in zip(fit.T, shifted):
        assert_close(box_distance(apply_transform(T, src)).max(), 0.0, atol=1e-6)


def test_trimming_leaves_out_far_outliers(fibula_surface, fibula_patch):
    points = fibula_patch[::10].copy()
    rng = np.random.default_rng(0)
    outliers = points[:len(points) // 20] + rng.normal(size=(len(points) // 20, 3)) * 15
    noisy = np.vstack([points, outliers])
    start = rigid_about([1.0, -1.0, 0.5], [1.0, 0.5, -1.0], points.mean(0))
    cloud = fibula_surface.cloud(20_000)
    trimmed = point_to_plane_icp(noisy, start, cloud.match, iterations=60, trim_fraction=0.1)
    plain = point_to_plane_icp(noisy, start, cloud.match, iterations=60)
    assert _errors(trimmed.T, np.eye(4), points)[0] < _errors(plain.T, np.eye(4), points)[0]
    assert _errors(trimmed.T, np.eye(4), points)[0] < 0.5


def test_too_few_pairs_stop_without_moving(box_surface, box_cloud):
    far = np.eye(4)
    far[:3, 3] = [500.0, 0, 0]
    fit = point_to_plane_icp(box_cloud, far, box_surface.matcher(2.0), iterations=10)
    assert_close(fit.T, far, atol=0)
    assert not fit.converged and fit.inlier_fraction == 0.0 and np.isnan(fit.rmse_mm)


def test_coarse_to_fine_drops_starts_far_behind(fibula_surface, fibula_patch):
    points = fibula_patch[::4]
    cloud = fibula_surface.cloud(20_000)
    near = rigid_about([2.0, 0, 0], [2.0, 0, 0], points.mean(0))
    far = rigid_about([0, 0, 150.0], [0, 0, 60.0], points.mean(0))
    T, rmse = coarse_to_fine_icp(points, np.stack([near, far]), cloud.match, iterations=30,
                                 margin_mm=1.0, trim_fraction=0.1)
    assert _errors(T[0], np.eye(4), points)[0] < 0.3
    assert rmse[1] > rmse[0] + 1.0


@pytest.mark.parametrize("bad", [np.zeros((0, 3)), np.full((10, 3), np.nan)])
def test_bad_sources_are_clear_errors(box_surface, bad):
    from comreg_core.errors import InvalidGeometryError

    with pytest.raises(InvalidGeometryError):
        point_to_plane_icp(bad, np.eye(4), box_surface.matcher())


def test_patience_stops_a_pose_that_jitters_forever():
    """A matcher whose plane moves by +-0.05 mm on every call (as gated pairs coming and
    going do) makes the pose jump 0.1 mm back and forth: the tolerance is never met. With
    patience the start stops once its RMS stops falling, and counts as converged."""
    rng = np.random.default_rng(0)
    source = np.column_stack([rng.uniform(-20, 20, (500, 2)), np.zeros(500)])  # z = 0 plane
    calls = {"n": 0}

    def jittering_plane(points):
        calls["n"] += 1
        offset = 0.05 if calls["n"] % 2 else -0.05
        q = points.copy()
        q[..., 2] = offset
        normals = np.zeros_like(points)
        normals[..., 2] = 1.0
        return q, normals, np.abs(points[..., 2] - offset)

    plain = point_to_plane_icp(source, np.eye(4), jittering_plane, iterations=40)
    assert plain.iterations == 40 and not plain.converged
    calls["n"] = 0
    patient = point_to_plane_icp(source, np.eye(4), jittering_plane, iterations=40, patience=5)
    assert patient.converged and patient.iterations == 1 + 5  # the first RMS, then 5 no better
    assert abs(patient.T[2, 3]) <= 0.05 + 1e-9  # it stopped on one of the two planes


def test_refine_on_mesh_recovers_a_known_pose_through_outliers(fibula_surface, fibula_patch):
    """The refinement after the network's ICP (``model.icp.mesh_refine``): from 5 deg / 5 mm
    off, with 5 % of the points 15 mm off the bone (a sweep's false intersections), it ends on
    the truth; the same ICP untrimmed does not."""
    points = fibula_patch[::10].copy()
    rng = np.random.default_rng(4)
    n_out = len(points) // 20
    points[rng.choice(len(points), n_out, replace=False)] += rng.normal(size=(n_out, 3)) * 15
    axis = rng.normal(size=3)
    start = rigid_about(axis / np.linalg.norm(axis) * 5.0, [3.0, -3.0, 2.5], points.mean(0))
    assert_close(_errors(start, np.eye(4), points)[1], 5.0, atol=1e-9)
    T, rmse = refine_on_mesh(points, start, fibula_surface.matcher())
    rte, rre = _errors(T, np.eye(4), points)
    assert rte < 0.1 and rre < 0.1, (rte, rre)
    assert 0 <= rmse < 0.05
    untrimmed = point_to_plane_icp(points[np.linspace(0, len(points) - 1, MESH_REFINE_POINTS)
                                          .astype(int)], start, fibula_surface.matcher(),
                                   iterations=50)
    pulled = _errors(untrimmed.T, np.eye(4), points)  # the outliers pull it off (0.3 mm, 5.6 deg)
    assert pulled[0] > 0.1 or pulled[1] > 1.0, pulled


def test_apply_poses_sums_in_a_fixed_order():
    """``apply_poses`` gives the bits of ``((x R_j0 + y R_j1) + z R_j2) + t_j`` in plain Python
    floats (no BLAS kernel's order), and agrees with numpy's matmul to rounding, for one cloud
    and for one cloud per pose."""
    from scipy.spatial.transform import Rotation

    from comreg_core.registration.geometry.icp import apply_poses

    rng = np.random.default_rng(7)
    for k in range(20):
        B, n = int(rng.integers(1, 6)), int(rng.integers(1, 40))
        T = np.tile(np.eye(4), (B, 1, 1))
        T[:, :3, :3] = Rotation.random(B, random_state=k).as_matrix()
        T[:, :3, 3] = rng.normal(size=(B, 3)) * 50
        for points in (rng.normal(size=(n, 3)) * 100, rng.normal(size=(B, n, 3)) * 100):
            got = apply_poses(T, points)
            assert got.shape == (B, n, 3) and got.flags["C_CONTIGUOUS"]
            for b in range(B):
                cloud = points if points.ndim == 2 else points[b]
                R, t = T[b, :3, :3].tolist(), T[b, :3, 3].tolist()
                naive = [[((x * R[j][0] + y * R[j][1]) + z * R[j][2]) + t[j] for j in range(3)]
                         for x, y, z in cloud.tolist()]
                np.testing.assert_array_equal(got[b], np.array(naive))
            np.testing.assert_allclose(got, points @ T[:, :3, :3].transpose(0, 2, 1)
                                       + T[:, None, :3, 3], rtol=0, atol=1e-9)
