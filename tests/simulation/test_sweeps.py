"""Ray-cast sweeps on the real fibula, checked against independent VTK references: every
non-false point on the surface, first hits only (shadowing), false hits on their ray at the right
depth, dropped slices empty, trajectories carrying the paper's perturbations."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comreg_core.simulation import (SimulationConfig, cast_sweep, sample_trajectory,
                                    simulate_from_poses, simulate_sweep, sweep_rng)
from tests.helpers import assert_close
from tests.simulation.support import (naive_ray, obb_tree, segment_hits, vtk_distance,
                                      vtk_surface, with_perturbation, with_trajectory)


@pytest.fixture(scope="module")
def raw_sweeps(fibula_bone):
    """Raw (not resampled) sweeps: transverse and longitudinal, more false hits to test them."""
    config = with_perturbation(SimulationConfig(), false_hit_probability=0.01,
                               drop_probability=0.1)
    sweeps = []
    for i, p_long in enumerate([0.0, 0.0, 1.0]):
        c = with_trajectory(config, longitudinal_probability=p_long)
        sweeps.append(simulate_sweep(fibula_bone, c, sweep_rng(7, i), resample_points=False))
    return config, sweeps


@pytest.fixture(scope="module")
def fibula_polydata(fibula_bone):
    return vtk_surface(fibula_bone.vertices, fibula_bone.faces)


def test_sweep_kinds_and_counts(raw_sweeps):
    config, sweeps = raw_sweeps
    assert [s.trajectory.kind for s in sweeps] == ["transverse", "transverse", "longitudinal"]
    for s in sweeps:
        n = s.trajectory.n_slices
        lo, hi = config.trajectory.n_slices
        assert lo <= n <= hi
        assert s.n_rays_cast == (~s.trajectory.dropped).sum() * config.probe.n_rays
        assert len(s) > 2000 and (~s.is_false).sum() > 2000


def test_non_false_points_lie_on_the_surface(raw_sweeps, fibula_polydata, fibula_bone):
    for s in raw_sweeps[1]:
        true_points = s.points[~s.is_false]
        pick = np.random.default_rng(0).choice(len(true_points), 1500, replace=False)
        d = vtk_distance(fibula_polydata, true_points[pick])
        assert d.max() < 1e-4, d.max()
        # the bulk path (vectorised VTK call) agrees and covers every point
        assert fibula_bone.distance(true_points).max() < 1e-4


def test_each_ray_reports_at_most_its_first_hit(raw_sweeps, fibula_polydata):
    """Shadowing: no ray reports two points, and a reported point is the nearest intersection
    along its ray (VTK's OBB tree lists all of them); rays without a point hit nothing within
    the image depth (unless they start inside the bone)."""
    config, sweeps = raw_sweeps
    probe = config.probe
    tree = obb_tree(fibula_polydata)
    rng = np.random.default_rng(1)
    for s in sweeps:
        key = s.slice_index * probe.n_rays + s.ray_index
        assert len(np.unique(key)) == len(key)  # one point per ray at most
        true_idx = np.flatnonzero(~s.is_false)
        behind = 0
        for i in rng.choice(true_idx, 150, replace=False):
            T = s.trajectory.T_ct_image[s.slice_index[i]]
            origin, direction = naive_ray(T, s.ray_index[i], probe.width_mm, probe.n_rays)
            hits, dist = segment_hits(tree, origin, direction, probe.depth_mm)
            assert len(hits) >= 1
            assert_close(s.points[i], hits[0], atol=1e-4, what="first hit")
            behind += len(hits) > 1
        assert behind > 0  # there were shadowed surfaces behind some first hits
        # rays that report nothing: no surface within the image depth
        kept = np.flatnonzero(~s.trajectory.dropped)
        all_keys = (kept[:, None] * probe.n_rays + np.arange(probe.n_rays)).ravel()
        empty = np.setdiff1d(all_keys, key)
        for k in rng.choice(empty, 150, replace=False):
            T = s.trajectory.T_ct_image[k // probe.n_rays]
            origin, direction = naive_ray(T, k % probe.n_rays, probe.width_mm, probe.n_rays)
            hits, _ = segment_hits(tree, origin, direction, probe.depth_mm)
            assert len(hits) == 0 or tree.InsideOrOutside(list(origin)) == -1


def test_false_hits_on_their_ray_at_allowed_depths(raw_sweeps):
    config, sweeps = raw_sweeps
    probe, pc = config.probe, config.perturbation
    total_rays = total_events = 0
    for s in sweeps:
        f = np.flatnonzero(s.is_false)
        assert len(f) > 0
        for i in f:
            T = s.trajectory.T_ct_image[s.slice_index[i]]
            origin, direction = naive_ray(T, s.ray_index[i], probe.width_mm, probe.n_rays)
            offset = s.points[i] - origin
            depth = offset @ direction
            assert np.linalg.norm(offset - depth * direction) < 1e-6  # on the ray
            assert pc.false_hit_depth[0] * probe.depth_mm - 1e-9 <= depth
            assert depth <= pc.false_hit_depth[1] * probe.depth_mm + 1e-9
        total_rays += s.n_rays_cast
        total_events += s.n_false_events
    p = pc.false_hit_probability
    assert abs(total_events - p * total_rays) < 5 * np.sqrt(total_rays * p * (1 - p))
    # each event replaces its ray and its neighbours (fewer at slice edges or on overlaps)
    n_false = sum(int(s.is_false.sum()) for s in sweeps)
    assert 2.0 < n_false / total_events <= 2 * pc.false_hit_neighbors + 1


def test_dropped_slices_are_missing(raw_sweeps):
    for s in raw_sweeps[1]:
        dropped = np.flatnonzero(s.trajectory.dropped)
        assert len(dropped) > 0
        assert not np.isin(s.slice_index, dropped).any()
        # kept slices that face the bone do produce points
        assert len(np.unique(s.slice_index)) > 0.5 * (~s.trajectory.dropped).sum()


def test_trajectory_carries_tilts_positions_and_faces_the_bone(fibula_bone):
    config = with_trajectory(SimulationConfig(), longitudinal_probability=0.0)
    pc = config.perturbation
    for seed in range(5):
        t = sample_trajectory(fibula_bone, config, np.random.default_rng(seed))
        R = t.T_ct_image[:, :3, :3]
        assert_close(np.linalg.det(R), np.ones(t.n_slices), atol=1e-9)
        # R = R_base Ry(twist) Rx(theta_x) Rz(theta_y): recover the angles independently
        rel = np.einsum("nji,njk->nik", t.R_base, R)
        twist, tx, ty = Rotation.from_matrix(rel).as_euler("YXZ").T
        assert_close(twist, t.twist, atol=1e-9, what="twist")
        jitter = np.radians(config.trajectory.direction_jitter_deg)
        assert np.abs(t.twist).max() <= jitter + 1e-12
        assert_close(tx, t.tilt_x, atol=1e-9, what="theta_x")
        assert_close(ty, t.tilt_y, atol=1e-9, what="theta_y")
        assert np.abs(t.tilt_x).max() <= np.radians(pc.tilt_x_max_deg) + 1e-12
        assert np.abs(t.tilt_y).max() <= np.radians(pc.tilt_y_max_deg) + 1e-12
        # transverse: the face centres advance along the long axis by the slice positions
        face = t.T_ct_image[:, :3, 3] + config.probe.width_mm / 2 * R[:, :, 0]
        axial = (face - fibula_bone.centre) @ fibula_bone.axes[:, 0]
        assert_close(np.abs(np.diff(axial)), np.diff(t.positions), atol=1e-9)
        # the beam of the untilted probe points at the long axis
        u = -t.R_base[:, :, 1]
        assert_close(np.abs(u @ fibula_bone.axes[:, 0]), np.zeros(t.n_slices), atol=1e-9)
        # the face stays outside the bone
        assert fibula_bone.distance(face).min() > 0.5 * config.trajectory.face_distance_mm[0]


def test_sweeps_are_reproducible_and_seed_dependent(fibula_bone):
    config = SimulationConfig(n_points=5000)
    a = simulate_sweep(fibula_bone, config, sweep_rng(3, 0))
    b = simulate_sweep(fibula_bone, config, sweep_rng(3, 0))
    c = simulate_sweep(fibula_bone, config, sweep_rng(3, 1))
    assert np.array_equal(a.points, b.points) and np.array_equal(a.slice_index, b.slice_index)
    assert np.array_equal(a.trajectory.T_ct_image, b.trajectory.T_ct_image)
    assert not np.array_equal(a.points, c.points)


def test_resampling_to_fixed_count(fibula_bone):
    rng = np.random.default_rng(0)
    config = SimulationConfig()
    sweep = simulate_sweep(fibula_bone, config, rng)
    assert sweep.points.shape == (20_000, 3) and sweep.slice_index.shape == (20_000,)
    assert np.all(np.diff(sweep.slice_index) >= 0)  # ordered by slice
    small = simulate_sweep(fibula_bone, SimulationConfig(n_points=1000), rng)
    assert len(small) == 1000 and len(np.unique(small.points, axis=0)) == 1000
    big = simulate_sweep(fibula_bone, SimulationConfig(n_points=200_000), rng)
    assert len(big) == 200_000  # more than the raw points: every point once plus repeats
    assert len(np.unique(big.points, axis=0)) < 200_000


def test_replay_of_given_poses(fibula_bone):
    config = with_perturbation(SimulationConfig(), drop_probability=0.0,
                               false_hit_probability=0.0)
    t = sample_trajectory(fibula_bone, config, np.random.default_rng(4))
    direct = cast_sweep(fibula_bone, t, config, np.random.default_rng(0))
    replay = simulate_from_poses(fibula_bone, t.T_ct_image, config, np.random.default_rng(0),
                                 resample_points=False)
    assert replay.trajectory.kind == "replay"
    assert np.array_equal(direct.points, replay.points)
    assert np.array_equal(direct.slice_index, replay.slice_index)


def test_capsule_hits_match_the_analytic_surface(capsule_bone, capsule_mesh):
    """A second bone with a known shape: every hit is on the (faceted) capsule, the probe looks
    at it from the side and points lie on the probe-facing half."""
    config = with_perturbation(SimulationConfig(), false_hit_probability=0.0)
    config = with_trajectory(config, longitudinal_probability=0.5, coverage_fraction=(0.8, 1.0))
    for seed in range(4):
        s = simulate_sweep(capsule_bone, config, np.random.default_rng(seed),
                           resample_points=False)
        p = s.points - np.array([10.0, -20.0, 300.0])
        radial = np.linalg.norm(p[:, :2], axis=1)
        cyl = np.abs(p[:, 2]) <= 60
        sphere = np.linalg.norm(p - np.c_[np.zeros((len(p), 2)),
                                          np.clip(p[:, 2], -60, 60)], axis=1)
        assert np.all(sphere[~cyl] <= 8.0 + 1e-6) and np.all(radial[cyl] <= 8.0 + 1e-6)
        assert np.all(sphere > 7.8)  # faceted: within the chord error of 32 segments
        # first hits face the probe: the surface normal points against the ray
        T = s.trajectory.T_ct_image[s.slice_index]
        beam = T[:, :3, 1]
        normal = p - np.c_[np.zeros((len(p), 2)), np.clip(p[:, 2], -60, 60)]
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        facing = np.einsum("ij,ij->i", normal, beam)
        assert np.all(facing < np.sin(np.radians(360 / 32)))  # facets vs the smooth capsule
        assert np.mean(facing < 0) > 0.99


def test_longitudinal_sweep_moves_across_the_bone(fibula_bone):
    """Array along the long axis; with the slow drifts switched off the face centre moves
    sideways by exactly the slice-position steps."""
    config = with_trajectory(SimulationConfig(), longitudinal_probability=1.0, drift_step=0.0,
                             direction_jitter_deg=0.0)
    config = with_perturbation(config, tilt_x_max_deg=0.0, tilt_y_max_deg=0.0)
    t = sample_trajectory(fibula_bone, config, np.random.default_rng(8))
    assert t.kind == "longitudinal"
    e0 = fibula_bone.axes[:, 0]
    x = t.T_ct_image[:, :3, 0]
    assert_close(np.abs(x @ e0), np.ones(t.n_slices), atol=1e-9, what="array along the bone")
    face = t.T_ct_image[:, :3, 3] + config.probe.width_mm / 2 * x
    step = np.linalg.norm(np.diff(face, axis=0), axis=1)
    assert_close(step, np.diff(t.positions), atol=1e-9, what="sideways steps")
    assert_close(np.diff(face, axis=0) @ e0, np.zeros(t.n_slices - 1), atol=1e-9)


def test_side_reference_sets_where_the_probe_looks_from(fibula_bone):
    reference = np.array([1.0, 0.0, 0.0])
    config = with_trajectory(SimulationConfig(), side_reference=tuple(reference),
                             side_angle_deg=(30.0, 30.0), side_drift_deg=0.0,
                             longitudinal_probability=0.0)
    t = sample_trajectory(fibula_bone, config, np.random.default_rng(9))
    e0 = fibula_bone.axes[:, 0]
    r = reference - (reference @ e0) * e0
    r /= np.linalg.norm(r)
    towards_probe = -t.R_base[:, :, 1]
    assert_close(towards_probe @ r, np.full(t.n_slices, np.cos(np.radians(30))), atol=1e-9)
