"""Baselines: Open3D RANSAC + ICP recovers a known pose of a fibula patch; the ICP pseudo ground
truth converges from a near-perfect start; config and error handling."""

import sys

import numpy as np
import pytest

from comreg_core.config import ConfigError
from comreg_core.errors import ComRegError
from comreg_core.evaluation import (BaselineConfig, IcpGtBaseline, RansacConfig,
                                    baseline_config_from_dict, baseline_methods, evaluate,
                                    require_open3d)
from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
from comreg_core.transforms import apply_transform, invert_rigid
from tests.helpers import assert_close, box_distance, rigid_about


def _errors(T_est, T_true, points):
    return (translation_error_mm(T_est, T_true, points.mean(axis=0)),
            rotation_error_deg(T_est, T_true))


# --- RANSAC + ICP (Open3D) ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def ransac(fibula_surface):
    pytest.importorskip("open3d")
    return baseline_methods(["ransac"], fibula_surface, seed=0)["ransac"]


def test_ransac_recovers_a_known_pose_of_a_fibula_patch(ransac, fibula_patch, fibula_surface):
    # the patch moved by 60 deg about a skew axis through its centroid and 80 mm
    T_us_ct = rigid_about(np.array([40.0, -25.0, 30.0]) * 60 / np.linalg.norm([40, -25, 30]),
                    [30.0, -50.0, 50.0], fibula_patch.mean(axis=0))
    moved = apply_transform(T_us_ct, fibula_patch)
    truth = invert_rigid(T_us_ct)
    ransac.reseed(0)
    out = ransac(moved)
    rte, rre = _errors(out.T_ct_us, truth, moved)
    assert rte < 2.0 and rre < 2.0, f"RTE {rte:.2f} mm, RRE {rre:.2f} deg"
    assert out.runtime_s > 0 and out.info["ransac_fitness"] > 0.5
    # the same seed gives the same pose, up to Open3D's thread scheduling (its parallel RANSAC
    # may keep another, equally good pose; ICP then lands within ~0.01 mm)
    ransac.reseed(0)
    again = ransac(moved)
    assert_close(_errors(again.T_ct_us, out.T_ct_us, moved), [0.0, 0.0], atol=0.05,
                 what="same seed, same pose (mm, deg)")


def test_ransac_through_the_harness(ransac, fibula_patch, fibula_surface):
    result = evaluate({"ransac": ransac}, fibula_patch[::4], fibula_surface, trials=2, seed=5)
    rows = result["trials"]
    assert all(r["error"] is None for r in rows)
    assert all(r["info"]["ransac_correspondences"] > 0 for r in rows)
    assert result["summary"]["ransac"]["runtime_s"]["mean"] > 0


def test_ransac_rejects_tiny_and_bad_clouds(ransac):
    with pytest.raises(ComRegError, match="too few for RANSAC"):
        ransac(np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]))
    with pytest.raises(ComRegError, match="non-finite"):
        ransac(np.array([[0.0, 0, np.nan]] * 10))
    with pytest.raises(ComRegError, match="0 points"):
        ransac(np.zeros((0, 3)))


def test_missing_open3d_is_a_clear_error(monkeypatch, fibula_surface):
    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d -> ImportError
    with pytest.raises(ComRegError, match="pip install open3d"):
        require_open3d()
    with pytest.raises(ComRegError, match="needs Open3D"):
        baseline_methods(["ransac"], fibula_surface)
    # the pseudo ground truth does not need Open3D
    assert "icp-gt" in baseline_methods(["icp-gt"], fibula_surface)


# --- ICP pseudo ground truth ----------------------------------------------------------------------

def test_icp_gt_baseline_in_the_harness(fibula_surface, fibula_patch):
    methods = baseline_methods(["icp-gt"], fibula_surface)
    result = evaluate(methods, fibula_patch[::4], fibula_surface, trials=2, seed=0,
                      perturbation="full")
    s = result["summary"]["icp-gt"]
    assert s["success_rate"] == 1.0 and s["RTE_mm"]["mean"] < 0.05


def test_icp_on_the_box_stays_put(box_surface, box_cloud):
    icp = IcpGtBaseline(box_surface)
    out = icp(box_cloud, np.eye(4))
    assert_close(box_distance(apply_transform(out.T_ct_us, box_cloud)).max(), 0.0, atol=1e-6)


# --- config and names -----------------------------------------------------------------------------

def test_config_from_dict_and_validation():
    config = baseline_config_from_dict({"ransac": {"max_iterations": 1_000_000,
                                                   "confidence": 0.99},
                                        "icp_gt": {"max_distance_mm": 2}})
    assert config.ransac.max_iterations == 1_000_000 and config.ransac.voxel_size_mm == 1.0
    assert config.icp_gt.max_distance_mm == 2.0
    assert BaselineConfig().ransac == RansacConfig()
    with pytest.raises(ConfigError, match="Unknown config key.*'iterations'.*max_iterations"):
        baseline_config_from_dict({"ransac": {"iterations": 5}})
    with pytest.raises(ConfigError, match="confidence"):
        baseline_config_from_dict({"ransac": {"confidence": 1.5}})
    with pytest.raises(ConfigError, match="voxel_size_mm"):
        baseline_config_from_dict({"ransac": {"voxel_size_mm": 0}})
    with pytest.raises(ConfigError, match="point_to_plane"):
        baseline_config_from_dict({"ransac": {"icp": "plane"}})
    with pytest.raises(ConfigError, match="must be a number"):
        baseline_config_from_dict({"icp_gt": {"max_distance_mm": "far"}})


def test_unknown_baseline_names_are_listed(fibula_surface):
    with pytest.raises(ComRegError, match="Unknown baseline method.*'comreg'.*ransac, icp-gt"):
        baseline_methods(["icp-gt", "comreg"], fibula_surface)
