"""Registration geometry: the CT surface, ICP, the pose search, its scores, polish and verdict.

Layers inside (each imports only those above it in this list): ``surface`` (the CT surface
and dense sample clouds) -> ``metrics`` (RTE, RRE, CD, HD95, success, flip) and ``icp`` (one
batched point-to-plane ICP) -> ``config`` -> ``scoring`` -> ``polish`` -> ``search`` (start
grid, screening, refinement, choice); ``verdict`` (OK/CHECK from the files alone) beside them.
No torch and no network here: the package sits below ``model``, ``training``, ``inference``,
``evaluation`` and ``report`` and imports none of them (``docs/architecture.md``).
"""

from comreg_core.registration.config import HypothesisConfig, as_hypothesis_config
from comreg_core.registration.icp import ICPResult, coarse_to_fine_icp, point_to_plane_icp
from comreg_core.registration.metrics import (FLIP_RRE_DEG, SUCCESS_RRE_DEG, SUCCESS_RTE_MM,
                                              completion_metrics, is_flip, is_success,
                                              registration_metrics, rotation_error_deg,
                                              translation_error_mm)
from comreg_core.registration.scoring import Hypothesis, HypothesisResult
from comreg_core.registration.search import build_hypotheses, search_hypotheses
from comreg_core.registration.surface import CTSurface, SurfaceCloud, as_surface
from comreg_core.registration.result import RegistrationResult
from comreg_core.registration.verdict import Verdict, judge_registration

__all__ = [
    "CTSurface", "FLIP_RRE_DEG", "Hypothesis", "HypothesisConfig", "HypothesisResult",
    "ICPResult", "RegistrationResult", "SUCCESS_RRE_DEG", "SUCCESS_RTE_MM", "SurfaceCloud",
    "Verdict",
    "as_hypothesis_config", "as_surface", "build_hypotheses", "coarse_to_fine_icp",
    "completion_metrics", "is_flip", "is_success", "judge_registration", "point_to_plane_icp",
    "registration_metrics", "rotation_error_deg", "search_hypotheses", "translation_error_mm",
]
