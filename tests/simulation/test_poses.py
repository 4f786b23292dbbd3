"""Random initial poses: the paper's one-axis sampler and the full-rotation sampler."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comreg_core.config import ConfigError
from comreg_core.simulation import full_rotation_pose, paper_initial_pose, sample_initial_pose
from comreg_core.transforms import apply_transform, check_rigid, invert_rigid
from tests.helpers import assert_close

CENTER = np.array([180.0, 330.0, 1500.0])


def test_paper_sampler_one_coordinate_axis_angle_and_shift_within_bounds():
    rng = np.random.default_rng(0)
    axes, angles, shifts = [], [], []
    for _ in range(3000):
        T = check_rigid(paper_initial_pose(rng, center=CENTER))
        rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
        angle = np.linalg.norm(rotvec)
        axis = rotvec / angle
        k = int(np.argmax(np.abs(axis)))
        assert_close(np.abs(axis), np.eye(3)[k], atol=1e-9, what="rotation axis")
        signed = angle * np.sign(axis[k])
        # rotation about the axis through CENTER, then a shift along the same axis
        shift = apply_transform(T, CENTER[None])[0] - CENTER
        assert_close(shift, np.eye(3)[k] * shift[k], atol=1e-9, what="shift along the axis")
        axes.append(k)
        angles.append(np.degrees(signed))
        shifts.append(shift[k])
    angles, shifts = np.array(angles), np.array(shifts)
    assert np.abs(angles).max() <= 90 + 1e-9 and np.abs(shifts).max() <= 100 + 1e-9
    # uniform: every axis used, angles and shifts spread over their whole ranges
    assert np.all(np.bincount(axes, minlength=3) > 800)
    assert abs(np.mean(np.abs(angles)) - 45) < 3 and abs(np.mean(np.abs(shifts)) - 50) < 3
    assert np.abs(angles).max() > 89 and np.abs(shifts).max() > 99


def test_paper_sampler_random_axis_variant():
    rng = np.random.default_rng(1)
    axes = []
    for _ in range(200):
        T = paper_initial_pose(rng, random_axis=True)
        rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
        axis = rotvec / np.linalg.norm(rotvec)
        assert_close(np.cross(axis, T[:3, 3]), np.zeros(3), atol=1e-9)  # shift along the axis
        assert np.linalg.norm(rotvec) <= np.pi / 2 + 1e-9
        axes.append(axis)
    assert np.max(np.min(np.abs(np.array(axes)), axis=1)) > 0.3  # not just coordinate axes


def test_full_rotation_sampler_bounds_and_spread():
    rng = np.random.default_rng(2)
    angles, lengths = [], []
    for _ in range(2000):
        T = check_rigid(full_rotation_pose(rng, center=CENTER))
        angles.append(np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()))
        lengths.append(np.linalg.norm(apply_transform(T, CENTER[None])[0] - CENTER))
    angles, lengths = np.array(angles), np.array(lengths)
    assert angles.max() <= 180 + 1e-9 and lengths.max() <= 500 + 1e-9
    assert angles.max() > 175 and lengths.max() > 490 and abs(np.mean(angles) - 90) < 5


def test_poses_invert_and_reproduce():
    a = sample_initial_pose(np.random.default_rng(5), "paper", CENTER)
    b = sample_initial_pose(np.random.default_rng(5), "paper", CENTER)
    assert np.array_equal(a, b)
    points = np.random.default_rng(0).normal(size=(50, 3)) * 40 + CENTER
    moved = apply_transform(a, points)
    assert_close(apply_transform(invert_rigid(a), moved), points, atol=1e-9)
    assert sample_initial_pose(np.random.default_rng(5), "full").shape == (4, 4)
    with pytest.raises(ConfigError, match="paper"):
        sample_initial_pose(np.random.default_rng(5), "spiral")
