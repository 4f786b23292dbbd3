"""Scores against hand-made poses on an analytic box: the trimmed distance score and the
acoustic rule (a surface facing away from its beam's origin is penalised)."""

import numpy as np

from comreg_core.registration.search.config import SearchConfig
from comreg_core.registration.search.scoring import score_poses
from comreg_core.registration.geometry.surface import facing_away
from tests.helpers import BOX_CENTRE, assert_close, rigid_about


def _top_patch():
    """200 points on the box's top face (z = +5 mm) and their probe 25 mm above each."""
    rng = np.random.default_rng(3)
    points = BOX_CENTRE + np.column_stack([rng.uniform(-15, 15, 200), rng.uniform(-8, 8, 200),
                                           np.full(200, 5.0)])
    return points, points + [0.0, 0.0, 25.0]


def test_a_pose_that_puts_the_probe_inside_the_bone_loses(box_surface):
    """Turned 180 deg about a line in the face, the patch lies on the same face (it fits just as
    well) but its probe is now inside the box: only the beam origins tell the poses apart."""
    points, origins = _top_patch()
    cloud = box_surface.cloud(20_000)
    flip = rigid_about([180.0, 0.0, 0.0], [0.0, 0.0, 0.0], points.mean(axis=0))
    poses = np.stack([np.eye(4), flip])
    config = SearchConfig()
    plain = score_poses(poses, points, cloud, config)
    assert_close(plain, [0.0, 0.0], atol=1e-9, what="both fit the face")
    with_beams = score_poses(poses, points, cloud, config, origins=origins)
    assert_close(with_beams, [0.0, config.facing_penalty_mm], atol=1e-9,
                 what="the flipped probe is behind the surface for every point")
    off = SearchConfig(facing_penalty_mm=0.0)
    assert_close(score_poses(poses, points, cloud, off, origins=origins), plain, atol=0)


def test_facing_away_is_the_sign_of_the_beam_against_the_normal():
    normals = np.array([[0.0, 0, 1], [0, 0, 1], [1, 0, 0]])
    points = np.zeros((3, 3))
    origins = np.array([[0.0, 0, 10], [0, 0, -10], [-5, 0, 0]])
    assert facing_away(normals, points, origins).tolist() == [False, True, True]
