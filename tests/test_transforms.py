"""Rigid transform helpers against scipy's Rotation and hand-made references."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comreg_core.errors import InvalidGeometryError, InvalidTransformError
from comreg_core.transforms import (T_RAS_LPS, apply_transform, as_points, check_rigid,
                                    check_space, invert_rigid, orthonormalize,
                                    space_change)
from tests.helpers import assert_close, random_rigid


def test_apply_and_invert_match_scipy():
    rng = np.random.default_rng(3)
    T = random_rigid(rng)
    points = rng.normal(0, 50, (100, 3))
    expected = Rotation.from_matrix(T[:3, :3]).apply(points) + T[:3, 3]
    assert_close(apply_transform(T, points), expected, atol=1e-9, what="mm")
    assert_close(apply_transform(invert_rigid(T), expected), points, atol=1e-9, what="mm")
    assert_close(invert_rigid(T) @ T, np.eye(4), atol=1e-12)


def test_lps_ras_conversion():
    assert_close(space_change("LPS", "RAS") @ [10, 20, 30, 1], [-10, -20, 30, 1])
    assert_close(space_change("RAS", "RAS"), np.eye(4))
    assert_close(T_RAS_LPS @ T_RAS_LPS, np.eye(4))
    assert check_space("left-posterior-superior") == "LPS"
    with pytest.raises(InvalidGeometryError, match="LPS"):
        check_space("scanner-xyz")


def test_bad_transforms_and_points():
    with pytest.raises(InvalidTransformError, match="not rigid"):
        check_rigid(np.diag([2.0, 1, 1, 1]))
    with pytest.raises(InvalidTransformError, match="not rigid"):
        check_rigid(np.diag([-1.0, 1, 1, 1]))  # a mirror
    with pytest.raises(InvalidTransformError, match="4x4"):
        check_rigid(np.eye(3))
    with pytest.raises(InvalidTransformError, match="last row"):
        check_rigid(np.vstack([np.eye(4)[:3], [1, 0, 0, 1]]))
    with pytest.raises(InvalidGeometryError, match=r"\(N, 3\)"):
        as_points(np.zeros((4, 2)))
    with pytest.raises(InvalidGeometryError, match="non-finite"):
        as_points([[0, 0, np.nan]])


def test_orthonormalize_removes_float32_drift():
    rng = np.random.default_rng(5)
    T = random_rigid(rng)
    drifted = T.astype(np.float32).astype(np.float64) + rng.normal(0, 1e-6, (4, 4)) * [1, 1, 1, 1]
    fixed = orthonormalize(drifted)
    assert_close(fixed[:3, :3].T @ fixed[:3, :3], np.eye(3), atol=1e-12)
    assert_close(fixed[3], [0, 0, 0, 1])
    assert_close(fixed, T, atol=1e-4)
    assert np.linalg.det(fixed[:3, :3]) > 0
