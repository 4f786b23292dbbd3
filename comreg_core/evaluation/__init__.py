"""Evaluation: the paper's metrics, the RANSAC and ICP baselines, and the trial harness.

- :mod:`.metrics`: RTE, RRE, CD, HD95 of a registration; CD, HD95 of a completion; success/flip.
- :mod:`.baselines`: Open3D RANSAC (FPFH) + ICP (Open3D imported lazily), the ICP pseudo
  ground truth ``icp-gt`` (numpy/scipy), :class:`BaselineConfig`.
- :mod:`.evaluate`: :func:`evaluate` (random initial poses -> methods -> ``metrics.json`` dict),
  :func:`write_metrics`, :func:`simulated_us_clouds` (seeds disjoint from training).
- :mod:`.methods`: the methods by name (``comreg`` with the hypotheses stage, ``comreg-plain``
  without it, the baselines, ``all``): :func:`registration_methods`.

Typical use::

    methods = baseline_methods(["ransac", "icp-gt"], "fibula.stl")
    result = evaluate(methods, "simulated", "fibula.stl", trials=100, seed=0)
    write_metrics(result, "out/metrics.json")
"""

from comreg_core.evaluation.baselines import (BASELINES, BaselineConfig, IcpGtBaseline,
                                              IcpGtConfig, RansacConfig, RansacIcpBaseline,
                                              SurfaceMatcher, closest_points_on_triangles,
                                              baseline_config_from_dict, baseline_methods,
                                              point_to_plane_icp, require_open3d)
from comreg_core.evaluation.evaluate import (EVALUATION_SEED_NAMESPACE, PERTURBATIONS,
                                             evaluate, evaluation_rng, simulated_us_clouds,
                                             summarize, write_metrics)
from comreg_core.evaluation.methods import (COMREG_METHODS, METHODS, method_names,
                                            registration_methods)
from comreg_core.evaluation.metrics import (FLIP_RRE_DEG, SUCCESS_RRE_DEG, SUCCESS_RTE_MM,
                                            SurfaceReference, as_surface, chamfer_l1,
                                            completion_metrics, hd95, is_flip, is_success,
                                            nearest_distances, registration_metrics,
                                            rotation_error_deg, translation_error_mm)
from comreg_core.evaluation.outputs import RegistrationOutput, as_registration_output

__all__ = [
    "BASELINES", "BaselineConfig", "IcpGtBaseline", "IcpGtConfig", "RansacConfig",
    "RansacIcpBaseline", "SurfaceMatcher", "closest_points_on_triangles",
    "baseline_config_from_dict", "baseline_methods", "point_to_plane_icp",
    "require_open3d", "EVALUATION_SEED_NAMESPACE", "PERTURBATIONS", "evaluate",
    "evaluation_rng", "simulated_us_clouds", "summarize", "write_metrics", "FLIP_RRE_DEG",
    "SUCCESS_RRE_DEG", "SUCCESS_RTE_MM", "SurfaceReference", "as_surface", "chamfer_l1",
    "completion_metrics", "hd95", "is_flip", "is_success", "nearest_distances",
    "registration_metrics", "rotation_error_deg", "translation_error_mm",
    "RegistrationOutput", "as_registration_output", "COMREG_METHODS", "METHODS", "method_names",
    "registration_methods",
]
