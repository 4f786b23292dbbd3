"""Registration without a network: geometry, the pose search, and the judgement of a result.

Three sub-packages, each importing only those before it: ``geometry`` (the CT surface, one
batched point-to-plane ICP and its compiled kernels, the metrics, the US cloud's limits) ->
``search`` (settings, start grid with the prior's starts, screening, scoring and the choice,
polish, warm re-registration, the network's poses as further starts, result types, advice)
-> ``judgement`` (the OK/CHECK verdict, ``p_correct`` and its calibration). No torch and no
network here: the package sits below ``model``, ``training``, ``register``, ``evaluation`` and
``report`` and imports none of them (``docs/architecture.md``).
"""

from comreg_core.registration.search.config import SearchConfig, as_search_config
from comreg_core.registration.geometry.icp import ICPResult, coarse_to_fine_icp, point_to_plane_icp
from comreg_core.registration.geometry.metrics import (FLIP_RRE_DEG, SUCCESS_RRE_DEG,
                                                       SUCCESS_RTE_MM, completion_metrics, is_flip,
                                                       is_success, registration_metrics,
                                                       rotation_error_deg, translation_error_mm)
from comreg_core.registration.search.scoring import Candidate, SearchResult
from comreg_core.registration.search.search import build_starts, search_poses
from comreg_core.registration.geometry.surface import CTSurface, SurfaceCloud, as_surface
from comreg_core.registration.search.result import RegistrationResult
from comreg_core.registration.judgement.verdict import Verdict, judge_registration

__all__ = [
    "CTSurface", "Candidate", "FLIP_RRE_DEG", "ICPResult", "RegistrationResult",
    "SUCCESS_RRE_DEG", "SUCCESS_RTE_MM", "SearchConfig", "SearchResult", "SurfaceCloud",
    "Verdict",
    "as_search_config", "as_surface", "build_starts", "coarse_to_fine_icp",
    "completion_metrics", "is_flip", "is_success", "judge_registration", "point_to_plane_icp",
    "registration_metrics", "rotation_error_deg", "search_poses", "translation_error_mm",
]
