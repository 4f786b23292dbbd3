"""Evaluation: the RANSAC and ICP baselines, the methods by name and the trial harness.

The metrics themselves (RTE, RRE, CD, HD95, success, flip) are defined in
:mod:`comreg_core.registration.geometry.metrics`, below training, which validates with them.

- :mod:`.baselines`: Open3D RANSAC (FPFH) + ICP (Open3D imported lazily), the ICP pseudo
  ground truth ``icp-gt`` (numpy/scipy), :class:`BaselineConfig`.
- :mod:`.evaluate`: :func:`evaluate` (random initial poses -> methods -> ``metrics.json`` dict),
  :func:`write_metrics`, :func:`simulated_us_clouds` (seeds disjoint from training).
- :mod:`.methods`: the methods by name (``comreg`` with the pose search, ``comreg-plain``
  without it, the baselines, ``all``): :func:`registration_methods`.

Typical use::

    methods = baseline_methods(["ransac", "icp-gt"], "fibula.stl")
    result = evaluate(methods, "simulated", "fibula.stl", trials=100, seed=0)
    write_metrics(result, "out/metrics.json")
"""

from comreg_core.evaluation.baselines import (BaselineConfig, IcpGtBaseline,
                                              IcpGtConfig, RansacConfig, RansacIcpBaseline,
                                              baseline_config_from_dict, baseline_methods,
                                              require_open3d)
from comreg_core.evaluation.evaluate import (EVALUATION_SEED_NAMESPACE, PERTURBATIONS,
                                             evaluate, evaluation_rng, simulated_us_clouds,
                                             summarize, write_metrics)
from comreg_core.evaluation.methods import (EvaluateConfig, load_evaluate_config,
                                            method_names, registration_methods)
from comreg_core.evaluation.outputs import RegistrationOutput, as_registration_output

__all__ = [
    "BaselineConfig", "IcpGtBaseline", "IcpGtConfig", "RansacConfig",
    "RansacIcpBaseline", "baseline_config_from_dict", "baseline_methods", "require_open3d",
    "EVALUATION_SEED_NAMESPACE", "PERTURBATIONS", "evaluate", "evaluation_rng",
    "simulated_us_clouds", "summarize", "write_metrics", "RegistrationOutput",
    "as_registration_output", "EvaluateConfig", "load_evaluate_config", "method_names",
    "registration_methods",
]
