"""The pose search on its own (no network): ambiguity flag, flip recovery, the
score and confidence definitions (its settings: ``test_search_config.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import pyvista as pv
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from comreg_core.registration.search.config import SearchConfig
from comreg_core.registration.geometry.icp import coarse_to_fine_icp
from comreg_core.registration.search.screening import screen_starts
from comreg_core.registration.search.search import (PATCH_ORIENTATIONS, build_starts,
                                                    patch_orientation_starts, principal_axes_pose,
                                                    refine_starts, rotation_about,
                                                    search_poses, slide_offsets_mm, us_subset)
from comreg_core.registration.geometry.surface import CTSurface, SurfaceCloud
from comreg_core.pointsets import farthest_point_indices
from comreg_core.transforms import apply_transform, invert_rigid
from tests.helpers import FIBULA_STL, assert_close


def _errors(T_est, T_true, points):
    """(RTE mm at the centroid of ``points``, RRE deg by scipy's Rotation) of a T_ct_us."""
    c = points.mean(axis=0)
    rte = float(np.linalg.norm(apply_transform(T_est, c[None]) - apply_transform(T_true,
                                                                                c[None])))
    rre = float(np.degrees(Rotation.from_matrix(T_est[:3, :3].T @ T_true[:3, :3]).magnitude()))
    return rte, rre


def _rigid(rotvec_deg, translation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = translation
    return T


def _perturb(T, centre, degrees, mm, seed) -> np.ndarray:
    """``T`` followed by a rotation of ``degrees`` about a random axis through ``centre`` and a
    shift of ``mm`` in a random direction (CT frame)."""
    rng = np.random.default_rng(seed)
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    shift = np.eye(4)
    shift[:3, 3] = direction / np.linalg.norm(direction) * mm
    return shift @ rotation_about(centre, axis, math.radians(degrees)) @ T


# --- the fibula: a distinctive patch ----------------------------------------------------------

@pytest.fixture(scope="module")
def fibula_target(shared_data):
    return CTSurface(FIBULA_STL).cloud(SearchConfig.target_points)


@pytest.fixture(scope="module")
def distal_patch(fibula_target):
    """The fibula's distal end (the malleolus, at the +long-axis end): area-uniform CT surface
    points (another seed than the target's) within 40 mm of the end along the long axis, moved
    into a 'US frame' by a known transform. Returns (us_points, T_ct_us truth, CT points)."""
    surface = CTSurface(FIBULA_STL, sample_seed=11)
    points, _ = surface.samples(40_000)
    axis = fibula_target.axes[:, 0]
    along = (points - fibula_target.centre) @ axis
    if abs(along.min()) > along.max():  # make +axis the distal end (the CT's +z side here)
        along = -along
    patch = points[along > along.max() - 40.0]
    T_us_ct = _rigid([20.0, -35.0, 50.0], [30.0, -12.0, 80.0])
    return apply_transform(T_us_ct, patch), invert_rigid(T_us_ct), patch


def test_distal_patch_near_start_lands_and_is_not_ambiguous(fibula_target, distal_patch):
    us, truth, ct_patch = distal_patch
    assert 1000 < len(us) < 10_000
    start = _perturb(truth, ct_patch.mean(axis=0), degrees=6.0, mm=4.0, seed=1)
    assert _errors(start, truth, us)[1] > 5.0
    result = search_poses(us, start, fibula_target)
    rte, rre = _errors(result.T_ct_us, truth, us)
    assert rte < 2.0 and rre < 2.0, (rte, rre, result.chosen)
    assert not result.ambiguous and result.confidence > 0.5, result.to_json()
    # not ambiguous: no second round (its candidates are named by the half steps)
    assert not any("rot22.5" in h.name or "+turned" in h.name for h in result.candidates)
    # a patch (40 mm of the bone) must lead by patch_min_confidence, not min_confidence
    assert result.patch and result.to_json()["patch"]
    assert result.confidence < 1.0  # it has a runner-up
    stricter = (1.0 + result.confidence) / 2  # above this result's lead
    strict = SearchConfig(patch_min_confidence=stricter)
    flagged = search_poses(us, start, fibula_target, config=strict)
    assert flagged.confidence < stricter and flagged.ambiguous
    whole = search_poses(fibula_target.points[::10], np.eye(4), fibula_target,
                         config=strict)
    assert not whole.patch and not whole.ambiguous
    assert result.runner_up is not None and result.score_gap_mm > 0.1


@pytest.mark.parametrize("short_axis", [1, 2])
@pytest.mark.parametrize("with_completion", [False, True])
def test_flipped_start_on_the_distal_patch_is_recovered(fibula_target, distal_patch,
                                                        short_axis, with_completion):
    """A coarse pose flipped end to end (180 deg about a short axis through the bone centre,
    plus a few degrees) is recovered, with or without a (perfect) completion."""
    us, truth, ct_patch = distal_patch
    flip = rotation_about(fibula_target.centre, fibula_target.axes[:, short_axis], math.pi)
    start = flip @ _perturb(truth, ct_patch.mean(axis=0), degrees=4.0, mm=3.0, seed=2)
    assert _errors(start, truth, us)[1] > 170.0
    completion = None
    if with_completion:
        whole, _ = CTSurface(FIBULA_STL, sample_seed=5).samples(4000)
        completion = apply_transform(invert_rigid(truth), whole)  # the bone in the US frame
    # the flips alone: the 40 mm patch counts as a whole cloud (no patch starts: below)
    config = SearchConfig(patch_max_share=0.05)
    result = search_poses(us, start, fibula_target, completion, config)
    rte, rre = _errors(result.T_ct_us, truth, us)
    assert rte < 2.0 and rre < 2.0, (rte, rre, result.chosen, result.scores)
    assert result.chosen != "network" and not result.ambiguous
    # every start was screened; the network's pose and the best others were refined
    bases = 2 if with_completion else 1  # the network's pose (+ the principal-axes solve)
    slides = len(slide_offsets_mm(fibula_target, config))
    assert result.starts_tried == bases * 8 * 2 * slides
    assert len(result.candidates) == config.refine_top
    assert result.candidates[0].name == "network"
    # the unflipped network pose itself ends up far away and scores clearly worse
    network = next(h for h in result.candidates if h.name == "network")
    assert _errors(network.T_ct_us, truth, us)[1] > 90.0
    assert network.score_mm > result.best.score_mm + 0.5


def test_score_and_confidence_follow_their_definitions(fibula_target, distal_patch):
    us, truth, ct_patch = distal_patch
    config = SearchConfig(icp_points=1024)
    start = _perturb(truth, ct_patch.mean(axis=0), degrees=3.0, mm=2.0, seed=3)
    result = search_poses(us, start, fibula_target, config=config)
    # the score: trimmed mean distance to the tangent plane of the nearest CT point (scipy's
    # KD-tree here) of the ICP subset of the US points (the documented uniform subset: seed 0,
    # in sweep order)
    sub_mm = us[np.sort(np.random.default_rng(0).choice(len(us), config.icp_points,
                                                        replace=False))]
    tree = cKDTree(fibula_target.points)
    keep = len(sub_mm) - int(config.score_trim * len(sub_mm))
    mesh = pv.read(FIBULA_STL)
    assert result.polished and result.polished[0] == result.chosen
    for h in result.candidates:
        moved = apply_transform(h.T_ct_us, sub_mm)
        if h.polish is None:
            idx = tree.query(moved)[1]
            d = np.sort([abs(np.dot(p - fibula_target.points[i], fibula_target.normals[i]))
                         for p, i in zip(moved, idx)])
            assert_close(h.score_mm, d[:keep].mean(), rtol=1e-9, what=f"score of {h.name}")
        else:  # polished: exact distances to the mesh (VTK's closest points here)
            _, closest = mesh.find_closest_cell(moved, return_closest_point=True)
            d = np.sort(np.linalg.norm(closest - moved, axis=1))
            assert_close(h.score_mm, d[:keep].mean(), atol=0.01, what=f"score of {h.name}")
    # the choice, runner-up, gap and confidence
    scores = result.scores
    assert result.chosen == min(scores, key=scores.get)
    best = result.best

    def different(h):
        rte, rre = _errors(h.T_ct_us, best.T_ct_us, us)
        return rre > config.distinct_deg or rte > config.distinct_mm

    distinct = [h for h in result.candidates if h.name != best.name and different(h)]
    runner = min(distinct, key=lambda h: h.score_mm)
    assert result.runner_up == runner.name
    assert_close(result.score_gap_mm, runner.score_mm - best.score_mm, atol=1e-12)
    assert_close(result.confidence, max(runner.score_mm - best.score_mm, 0.0)
                 / max(runner.score_mm, config.score_floor_mm), atol=1e-12)
    assert result.ambiguous == (result.confidence < config.min_confidence)
    data = result.to_json()
    assert data["scores_mm"] == scores and data["chosen"] == result.chosen
    import json

    json.dumps(data, allow_nan=False)


# --- a symmetric shape: a cylinder ---------------------------------------------------------

def test_cylinder_patch_is_flagged_ambiguous():
    """CT = a closed cylinder (r 12 mm, 240 mm long); US = a quarter of its mantle, 80 mm long,
    in the middle: turned about the axis or flipped end to end, it fits just as well."""
    mesh = trimesh.creation.cylinder(radius=12.0, height=240.0, sections=128)
    target = CTSurface((np.asarray(mesh.vertices), np.asarray(mesh.faces))).cloud(20_000)
    rng = np.random.default_rng(4)
    theta, z = rng.uniform(0.0, np.pi / 2, 2000), rng.uniform(-40.0, 40.0, 2000)
    patch = np.column_stack([12.0 * np.cos(theta), 12.0 * np.sin(theta), z])
    T_us_ct = _rigid([-40.0, 10.0, 75.0], [100.0, 20.0, -50.0])
    us, truth = apply_transform(T_us_ct, patch), invert_rigid(T_us_ct)
    result = search_poses(us, truth, target)
    assert result.ambiguous, result.to_json()
    assert result.runner_up is not None and result.score_gap_mm < 0.05
    assert result.confidence < 0.2
    # the runner-up is a genuinely different pose (e.g. turned about the axis), not a duplicate
    runner = next(h for h in result.candidates if h.name == result.runner_up)
    rte, rre = _errors(runner.T_ct_us, result.T_ct_us, us)
    assert rre > 10.0 or rte > 5.0
    # every candidate fits the cylinder (the patch lies on it in all of these poses)
    assert max(result.scores.values()) < 0.05
    # ambiguous: a second round from the interleaved grid was searched too (twice the starts
    # of the first, its candidates named by the half steps)
    config = SearchConfig()
    first_round = (len(build_starts(truth, target, None, config))
                   + len(patch_orientation_starts(us, target, config)))
    assert result.starts_tried == 2 * first_round
    second = ("rot22.5", "+turned")  # the half-step turns of the grid and of the patch starts
    assert any(any(s in h.name for s in second) for h in result.candidates)
    # an ambiguous result says where the runner-up puts the sweep and what to scan
    runner = next(h for h in result.candidates if h.name == result.runner_up)
    advice = result.advice
    assert advice is not None and result.to_json()["advice"] == advice
    assert_close(advice["turn_deg"], _errors(result.T_ct_us, runner.T_ct_us, us)[1], atol=1e-6)
    assert "sweep" in advice["advice"]


# --- starts, refinement, options -------------------------------------------------------------

def test_the_starts_built(fibula_target):
    T = _rigid([10.0, 0.0, 0.0], [1.0, 2.0, 3.0])
    no_slides = SearchConfig(shaft_rotations=4, slide_step_mm=0)
    starts = build_starts(T, fibula_target, None, no_slides, T_coarse=np.eye(4))
    assert list(starts)[0] == "network" and "coarse" in starts
    assert len(starts) == 2 * 4 * 2  # 2 bases x dihedral group of 4 rotations x flips
    assert_close(starts["network"], T, atol=0)
    assert_close(starts["coarse"], np.eye(4), atol=0)
    c, axes = fibula_target.centre, fibula_target.axes
    # rot180 about the long axis = flip about a1 then about a2 (the Klein four-group)
    flip2 = rotation_about(c, axes[:, 2], math.pi)
    assert_close(starts["network+rot180"], flip2 @ starts["network+flip"], atol=1e-9)
    for name, G in starts.items():
        R = G[:3, :3]
        assert_close(R.T @ R, np.eye(3), atol=1e-9, what=name)
        assert np.linalg.det(R) > 0
    only = build_starts(T, fibula_target, None,
                        SearchConfig(shaft_rotations=1, slide_step_mm=0))
    assert list(only) == ["network", "network+flip"]
    # the principal-axes solve of the CT cloud against itself, flipped and turned: the identity
    # is one of its 4 proper sign choices (pca, pca+flip, pca+rot180, pca+flip+rot180)
    completion = fibula_target.points
    with_pca = build_starts(T, fibula_target, completion, no_slides)
    assert len(with_pca) == 2 * 4 * 2
    assert min(np.abs(with_pca[n] - np.eye(4)).max() for n in
               ("pca", "pca+flip", "pca+rot180", "pca+flip+rot180")) < 1e-6
    # slides: multiples of the step along the long axis, up to half the CT's length
    config = SearchConfig(slide_step_mm=20.0)
    slides = slide_offsets_mm(fibula_target, config)
    along = (fibula_target.points - c) @ axes[:, 0]
    half_length = (along.max() - along.min()) / 2
    assert slides[0] == 0 and np.abs(slides).max() <= half_length < np.abs(slides).max() + 20
    assert np.allclose(np.sort(slides), np.arange(-len(slides) // 2 + 1, len(slides) // 2 + 1)
                       * 20.0)
    slid = build_starts(T, fibula_target, completion, config)
    assert len(slid) == 2 * 8 * 2 * len(slides)
    move = slid["network+flip+slide40"][:3, 3] - slid["network+flip"][:3, 3]
    assert abs(np.linalg.norm(move) - 40.0) < 1e-9
    assert_close(slid["network+slide-20"][:3, :3], slid["network"][:3, :3], atol=1e-12)
    assert list(slide_offsets_mm(fibula_target, SearchConfig(slide_step_mm=0))) == [0.0]
    # the interleaved grid of the second round: rotations and slides shifted by half a step
    shifted = build_starts(T, fibula_target, completion, config, grid_offset=0.5)
    assert len(shifted) == len(slid) and not set(shifted) & set(slid)
    half_turn = shifted["network+rot22.5+slide10"] @ invert_rigid(slid["network"])
    assert abs(np.degrees(Rotation.from_matrix(half_turn[:3, :3]).magnitude()) - 22.5) < 1e-6
    assert "network+flip+rot337.5+slide-190" in shifted
    assert len(slide_offsets_mm(fibula_target, SearchConfig(slide_range_mm=30.0))) == 7


def test_screening_ranks_the_true_basin_first(fibula_target, distal_patch):
    """Of hundreds of starts, the screening keeps the network's own (bad) start first and one
    near the truth among the few it keeps; without ``refine_top`` it keeps all, unmoved."""
    us, truth, ct_patch = distal_patch
    config = SearchConfig()
    bad_start = rotation_about(fibula_target.centre, fibula_target.axes[:, 1], math.pi) @ \
        _perturb(truth, ct_patch.mean(axis=0), degrees=25.0, mm=30.0, seed=5)
    starts = build_starts(bad_start, fibula_target, None, config)
    stack = np.stack(list(starts.values()))
    kept, screened = screen_starts(us[::10], stack, fibula_target, config)
    assert len(kept) == config.refine_top and kept[0] == 0
    assert_close(screened[0], bad_start, atol=0)
    errors = [_errors(T, truth, us) for T in screened[1:]]
    assert min(rre for _, rre in errors) < 5.0 and min(rte for rte, _ in errors) < 5.0, errors
    everything, unmoved = screen_starts(us[::10], stack, fibula_target,
                                        SearchConfig(refine_top=0))
    assert np.array_equal(everything, np.arange(len(stack))) and unmoved is stack


def test_closest_point_grid_agrees_with_the_kd_tree(fibula_target):
    """The grid's CT points are at most about half a voxel diagonal worse than the true
    nearest ones; outside the grid, points are clamped onto it."""
    rng = np.random.default_rng(6)
    near = fibula_target.points[rng.integers(0, len(fibula_target.points), 5000)]
    queries = near + rng.normal(0.0, 5.0, near.shape)
    origin, spacing, grid = fibula_target.closest_point_grid
    assert grid.size <= SurfaceCloud.GRID_VOXELS * 1.1
    exact = cKDTree(fibula_target.points).query(queries)[0]
    approx = np.linalg.norm(queries - fibula_target.points[fibula_target.nearest_approx(
        queries)], axis=1)
    assert (approx >= exact - 1e-9).all()
    assert (approx - exact).max() <= spacing * math.sqrt(3)
    assert np.median(approx - exact) < 0.2 * spacing
    far = fibula_target.centre + np.array([[5000.0, 0.0, 0.0]])
    assert fibula_target.nearest_approx(far).shape == (1,)


def test_on_a_symmetric_cylinder_every_turn_ties_and_the_lowest_score_wins():
    """On a cylinder every turn fits: the result is flagged ambiguous and the lowest score is
    kept (the network's pose is one more start, not a tie-break)."""
    mesh = trimesh.creation.cylinder(radius=12.0, height=240.0, sections=128)
    target = CTSurface((np.asarray(mesh.vertices), np.asarray(mesh.faces))).cloud(20_000)
    rng = np.random.default_rng(7)
    theta, z = rng.uniform(0.0, np.pi / 2, 2000), rng.uniform(-40.0, 40.0, 2000)
    patch = np.column_stack([12.0 * np.cos(theta), 12.0 * np.sin(theta), z])
    truth = invert_rigid(_rigid([-40.0, 10.0, 75.0], [100.0, 20.0, -50.0]))
    start = rotation_about(np.zeros(3), [0.0, 0.0, 1.0], math.radians(40.0)) @ truth
    us = apply_transform(invert_rigid(truth), patch)
    result = search_poses(us, start, target)
    assert result.ambiguous
    # the lowest score (chosen on the quick polish's scores; all fit the cylinder to ~0.01 mm)
    assert result.scores[result.chosen] <= min(result.scores.values()) + 0.01


def test_point_to_plane_batch_converges_from_several_starts(fibula_target, distal_patch):
    us, truth, ct_patch = distal_patch
    starts = np.stack([truth] + [_perturb(truth, ct_patch.mean(0), 5.0, 3.0, s)
                                 for s in range(3)])
    refined, rmse = coarse_to_fine_icp(us[::4], starts, fibula_target.match, iterations=50,
                                       trim_fraction=0.1)
    assert refined.shape == (4, 4, 4) and rmse.shape == (4,)
    for T in refined:
        rte, rre = _errors(T, truth, us)
        assert rte < 0.5 and rre < 0.5, (rte, rre)
    assert (rmse < 0.5).all()


def test_polish_gates_out_false_echoes(fibula_target):
    """A quarter of the distal patch's points lifted 3-6 mm off the bone along the surface
    normal (a false echo): the trimmed refinement is pulled off by them; the gated exact polish
    ignores them and lands on the truth. Without a mesh there is no polish."""
    points, normals = CTSurface(FIBULA_STL, sample_seed=11).samples(40_000)
    along = (points - fibula_target.centre) @ fibula_target.axes[:, 0]
    if abs(along.min()) > along.max():
        along = -along
    distal = along > along.max() - 40.0
    rng = np.random.default_rng(3)
    lift = np.where(rng.random(distal.sum()) < 0.25, rng.uniform(3.0, 6.0, distal.sum()), 0.0)
    patch = points[distal] + lift[:, None] * normals[distal]
    truth = invert_rigid(_rigid([20.0, -35.0, 50.0], [30.0, -12.0, 80.0]))
    us = apply_transform(invert_rigid(truth), patch)
    start = _perturb(truth, patch.mean(axis=0), degrees=3.0, mm=2.0, seed=4)

    polished = search_poses(us, start, fibula_target)
    rte, rre = _errors(polished.T_ct_us, truth, us)
    assert rte < 0.1 and rre < 0.2, (rte, rre)
    info = polished.polish
    assert info["converged"] and 0.4 < info["inlier_fraction"] < 0.8, info
    assert info["moved_mm"] > 0.5 and info["rmse_mm"] < 0.2
    assert polished.chosen in polished.polished and polished.to_json()["polish"] == info

    # the refinement alone (the network's start, before the polish) stays off the truth
    config = SearchConfig()
    _, _, refined, _ = refine_starts(us_subset(us, config.icp_points), {"network": start},
                                     fibula_target, config, keep_first=True)
    refined = refined[0]
    rte_net, rre_net = _errors(refined, truth, us)
    assert rte_net > 0.5 and rre_net > 2.0, (rte_net, rre_net)
    centre = us.mean(axis=0)[None]
    assert_close(info["moved_mm"], np.linalg.norm(apply_transform(polished.T_ct_us, centre)
                                                  - apply_transform(refined, centre)), atol=0.05)

    bare = SurfaceCloud(fibula_target.points, normals=fibula_target.normals)
    assert bare.surface is None
    assert search_poses(us, start, bare).polish is None


def test_random_subset_keeps_the_sweeps_share_of_false_echoes(fibula_target):
    """Simulated fibula sweeps (the paper's false intersections): farthest-point sampling picks
    the isolated false echoes first, a uniform subset keeps their share; on that subset the
    trimmed refinement stays on the truth (identity: the sweeps are in the CT frame)."""
    from comreg_core.simulation import simulate_sweeps

    config = SearchConfig()
    for sweep in simulate_sweeps(FIBULA_STL, 3, seed=5):
        cloud = sweep.points
        off = lambda pts: float((fibula_target.surface.closest(pts)[2] > 2.0).mean())
        share = off(cloud)  # measured 2-4 % of a sweep
        random_share = off(us_subset(cloud, config.icp_points))
        fps_share = off(cloud[farthest_point_indices(cloud, config.icp_points)])
        assert 0.005 < share < 0.08, share
        assert random_share < 1.6 * share + 0.01, (share, random_share)
        assert fps_share > 2.0 * share, (share, fps_share)  # measured ~10 % of the subset
        subset = us_subset(cloud, config.icp_points)
        refined, _ = coarse_to_fine_icp(subset, np.eye(4)[None], fibula_target.match,
                                        iterations=config.icp_iterations,
                                        schedule=config.icp_schedule,
                                        trim_fraction=config.icp_trim)
        rte, rre = _errors(refined[0], np.eye(4), cloud)
        assert rte < 0.5 and rre < 0.5, (rte, rre)
    assert len(us_subset(cloud[:100], config.icp_points)) == 100  # fewer points: all of them


def test_target_from_points_estimates_normals():
    """Without a mesh the normals come from local PCA: on a sphere they are radial."""
    rng = np.random.default_rng(0)
    v = rng.normal(size=(5000, 3))
    v = 50.0 * v / np.linalg.norm(v, axis=1, keepdims=True)
    target = SurfaceCloud(v)
    cos = np.abs(np.einsum("ij,ij->i", target.normals, v / 50.0))
    assert np.median(cos) > 0.99


@pytest.mark.parametrize("count", [0, 2, 5])
def test_too_few_us_points_is_a_clear_error(fibula_target, count):
    from comreg_core.errors import InvalidGeometryError

    with pytest.raises(InvalidGeometryError, match="needs at least 6"):
        search_poses(fibula_target.points[:count], np.eye(4), fibula_target)


def test_principal_axes_pose_puts_the_largest_spread_along_the_bone(fibula_target):
    """The patch's largest spread onto the CT's long axis, right-handed, centroid onto the
    CT's centre."""
    rng = np.random.default_rng(2)
    patch = rng.normal(size=(500, 3)) * [30.0, 10.0, 2.0]  # spreads along x, y, z
    T = principal_axes_pose(patch, fibula_target)
    assert_close(np.linalg.det(T[:3, :3]), 1.0, atol=1e-9)
    assert_close(abs(T[:3, :3] @ np.array([1.0, 0, 0]) @ fibula_target.axes[:, 0]), 1.0,
                 atol=0.02, what="the largest spread along the bone")
    assert_close(apply_transform(T, patch.mean(axis=0)[None])[0], fibula_target.centre,
                 atol=1e-9)


# --- patches: starts over all rotations --------------------------------------------------------

def test_patch_starts_cover_all_rotations(fibula_target, distal_patch):
    """A patch (40 mm of a 404 mm bone) gets 60 orientations x the slides, spread over SO(3)
    (every rotation within 45 deg of one of them, by scipy); the whole bone gets none."""
    from comreg_core.registration.search.search import is_patch

    us, _, _ = distal_patch
    config = SearchConfig()
    starts = patch_orientation_starts(us, fibula_target, config)
    slides = len(slide_offsets_mm(fibula_target, config))
    assert is_patch(us, fibula_target, config) and len(starts) == PATCH_ORIENTATIONS * slides
    turns = Rotation.from_matrix(np.stack([T[:3, :3] for n, T in starts.items()
                                           if "slide" not in n]))
    assert len(turns) == PATCH_ORIENTATIONS
    probes = Rotation.random(2000, random_state=3)
    gaps = [np.degrees((turns * probe.inv()).magnitude().min()) for probe in probes]
    assert max(gaps) < 45.0, max(gaps)
    # the retry round's set is turned by half the spacing: no start repeated
    turned = patch_orientation_starts(us, fibula_target, config, grid_offset=0.5)
    assert len(turned) == len(starts) and not set(turned) & set(starts)
    whole = fibula_target.points[::4]
    assert not is_patch(whole, fibula_target, config)
    assert patch_orientation_starts(whole, fibula_target, config) == {}
    # a lower patch_max_share counts the 40 mm cloud as whole: no patch starts
    assert patch_orientation_starts(us, fibula_target, SearchConfig(
        patch_max_share=0.05)) == {}


def test_short_sweep_whose_own_axes_mislead_registers(shared_data):
    """A simulated 40-50 mm one-face sweep of the fibula (the partial-sweep benchmark's trial
    19): from its principal axes alone (the cloud not counted as a patch) the search lands
    60-80 deg off, unflagged or not; with the patch starts it lands on the truth,
    unambiguous."""
    from comreg_core.config import from_dict
    from comreg_core.evaluation.evaluate import (STREAM_CLOUDS, STREAM_POSES,
                                                 evaluation_rng)
    from comreg_core.register import Registrar
    from comreg_core.simulation import BoneModel, sample_initial_pose, simulate_sweep
    from comreg_core.simulation.config import SimulationConfig
    from tests.benchmarks.bench_partial import PARTIAL_SWEEPS

    config = from_dict(SimulationConfig, PARTIAL_SWEEPS, "simulation")
    sweep = simulate_sweep(BoneModel(FIBULA_STL), config, evaluation_rng(0, STREAM_CLOUDS, 19))
    surface = CTSurface(FIBULA_STL)
    T_p = sample_initial_pose(evaluation_rng(0, STREAM_POSES, 19), "paper",
                              surface.bbox_centre)
    us, truth = apply_transform(T_p, sweep.points), invert_rigid(T_p)
    without = Registrar.from_ct(FIBULA_STL, search={"patch_max_share": 0.05}).register(us)
    assert _errors(without.T_ct_us, truth, us)[1] > 30.0
    result = Registrar.from_ct(FIBULA_STL).register(us)
    rte, rre = _errors(result.T_ct_us, truth, us)
    assert rte < 1.0 and rre < 1.0, (rte, rre, result.search.chosen)
    assert result.search.chosen.startswith("patch") and not result.search.ambiguous
