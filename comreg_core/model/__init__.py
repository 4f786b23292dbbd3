"""The ComReg network in pure PyTorch (CPU and CUDA, no compiled extensions).

Modules: :mod:`.ops` (FPS, kNN, gather, Chamfer, quaternions), :mod:`.adapointr` (completion
``f``; its attention blocks in :mod:`.transformer`), :mod:`.pose_head` (registration ``g``),
:mod:`.diff_icp` (differentiable ICP), :mod:`.comreg` (the whole network), :mod:`.losses`,
:mod:`.config` (``ModelConfig``, presets ``paper`` and ``cpu``),
:mod:`comreg_core.normalization` (the CT-based normalised coordinates).
"""

from comreg_core.model.adapointr import AdaPoinTr, CompletionOutput
from comreg_core.model.comreg import ComRegNet, ComRegOutput, TargetEncoding
from comreg_core.model.config import (
    CompletionConfig,
    ICPConfig,
    LossConfig,
    ModelConfig,
    PoseHeadConfig,
)
from comreg_core.model.diff_icp import ICPResult, differentiable_icp, weighted_procrustes
from comreg_core.model.losses import (
    LossTerms,
    comreg_loss,
    output_loss,
    pose_loss,
    rotation_angle,
)
from comreg_core.normalization import Normalization
from comreg_core.model.ops import chamfer_l1, furthest_point_sample, gather_points, knn
from comreg_core.model.pose_head import CorrespondencePoseHead, PoseHead, build_pose_head

__all__ = [
    "AdaPoinTr", "CompletionOutput", "ComRegNet", "ComRegOutput", "TargetEncoding",
    "CompletionConfig", "ICPConfig", "LossConfig", "ModelConfig",
    "PoseHeadConfig", "ICPResult", "differentiable_icp", "weighted_procrustes",
    "LossTerms", "comreg_loss", "output_loss", "pose_loss", "rotation_angle", "Normalization",
    "chamfer_l1", "furthest_point_sample", "gather_points", "knn", "PoseHead",
    "CorrespondencePoseHead", "build_pose_head",
]
