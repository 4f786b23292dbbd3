"""ComReg losses: completion (Chamfer on centres and dense points), pose, adaptive weighting.

* ``L_sparse = CD(C, T^t)``, ``L_dense = CD(dense, T^t)`` with the L1 Chamfer distance of
  :func:`comreg_core.model.ops.chamfer_l1`; ``L_completion = mean(L_sparse + L_dense)``.
* ``L_reg(T_hat, T) = ||t_hat - t|| + angle(R_hat^T R)`` where the angle equals
  ``arccos((tr(R_hat^T R) - 1) / 2)`` but is computed as ``atan2(sin, cos)`` so that value and
  gradient stay finite at 0 and 180 degrees (see :func:`rotation_angle`).
* ``L_registration = mean(lambda_coarse L_reg(coarse) + lambda_fine L_reg(fine))``, the fine
  term gated per sample by the coarse pose error (``LossConfig.fine_gate_*``); with the
  correspondence head, ``+ lambda_correspondence (mean_i ||y_i - T^-1 c_i|| + L_reg(global))``
  (each token's predicted CT point against where the truth puts its query centre, and the
  head's global rotation and translation against the truth).
* ``L_final = L_completion + lambda_reg L_registration`` with
  ``lambda_reg = rho L_completion / L_registration``, the weight detached (a number, not a path
  for gradients).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor

from comreg_core.model.config import LossConfig
from comreg_core.model.ops import chamfer_l1, safe_norm, transform_points

if TYPE_CHECKING:
    from comreg_core.model.comreg import ComRegOutput
    from comreg_core.model.pose_head import Correspondences


def rotation_angle(R_hat: Tensor, R: Tensor) -> Tensor:
    """Angle of the relative rotation ``R_hat^T R`` in radians, in [0, pi].

    ``cos = (tr(M) - 1) / 2`` and ``sin = ||vee(M - M^T)|| / 2`` for ``M = R_hat^T R``; the angle is
    ``atan2(sin, cos)``. This equals ``arccos(cos)`` for rotations, but is accurate for small
    angles and has finite gradients everywhere (arccos' is infinite at +-1; the norm uses
    :func:`safe_norm`, whose gradient is 0 at the exact 0 and 180 degree points).

    Args:
        R_hat, R: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(...)`` angles.
    """
    if R_hat.shape[-2:] != (3, 3) or R.shape[-2:] != (3, 3):
        raise ValueError(f"need (..., 3, 3) rotations, got {tuple(R_hat.shape)}, {tuple(R.shape)}")
    M = R_hat.transpose(-1, -2) @ R  # ... 3 3
    cos = (M.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0  # ...
    A = M - M.transpose(-1, -2)  # ... 3 3, = 2 sin(theta) [axis]_x
    vee = A[..., [2, 0, 1], [1, 2, 0]]  # ... 3
    sin = safe_norm(vee, dim=-1) / 2.0  # ...
    return sin.atan2(cos)


def pose_loss(T_hat: Tensor, T: Tensor) -> Tensor:
    """``L_reg = ||t_hat - t|| + angle(R_hat^T R)`` per transform.

    Args:
        T_hat, T: ``(B, 4, 4)`` estimated and ground-truth rigid transforms.

    Returns:
        ``(B,)`` losses (translation in the transforms' length unit + rotation in radians).
    """
    if T_hat.shape != T.shape or T.shape[-2:] != (4, 4):
        raise ValueError(f"need two (B, 4, 4) transforms, got {tuple(T_hat.shape)}, "
                         f"{tuple(T.shape)}")
    translation = safe_norm(T_hat[..., :3, 3] - T[..., :3, 3], dim=-1)
    return translation + rotation_angle(T_hat[..., :3, :3], T[..., :3, :3])


def in_fine_gate(coarse_transform: Tensor, gt_transform: Tensor, config: LossConfig) -> Tensor:
    """``(B,)`` bool: which samples' fine term counts (coarse estimate within
    ``fine_gate_deg`` and ``fine_gate_translation`` of the truth; all when ungated)."""
    with torch.no_grad():
        if not config.fine_gated:
            return torch.ones(coarse_transform.shape[0], dtype=torch.bool,
                              device=coarse_transform.device)
        angle = rotation_angle(coarse_transform[..., :3, :3], gt_transform[..., :3, :3])
        shift = (coarse_transform[..., :3, 3] - gt_transform[..., :3, 3]).norm(dim=-1)
        return (angle < math.radians(config.fine_gate_deg)) & (
            shift < config.fine_gate_translation)


class LossTerms(NamedTuple):
    """All loss terms, batch means (scalars). ``total`` is the one to back-propagate."""

    total: Tensor
    completion: Tensor
    sparse: Tensor
    dense: Tensor
    registration: Tensor
    reg_coarse: Tensor
    reg_fine: Tensor
    lambda_reg: Tensor
    correspondence: Tensor


def comreg_loss(centres: Tensor, dense: Tensor, gt_points: Tensor, coarse_transform: Tensor,
                fine_transform: Tensor, gt_transform: Tensor,
                config: LossConfig | None = None,
                correspondences: Correspondences | None = None) -> LossTerms:
    """The ComReg training objective.

    Args:
        centres: ``(B, Q, 3)`` predicted centres C of the source completion.
        dense: ``(B, Nd, 3)`` dense completion.
        gt_points: ``(B, M, 3)`` the complete cloud in the source frame, ``T^t = T . T``.
        coarse_transform: ``(B, 4, 4)`` predicted ``T_coarse^-1`` (source -> CT).
        fine_transform: ``(B, 4, 4)`` predicted ``T_fine^-1``.
        gt_transform: ``(B, 4, 4)`` ground truth ``T^-1`` (source -> CT).
        config: :class:`LossConfig` (lambda_coarse, lambda_fine, rho); None = the paper's.
        correspondences: the correspondence head's predictions, or None (MLP head).

    Returns:
        :class:`LossTerms`.
    """
    config = config or LossConfig()
    sparse = chamfer_l1(centres, gt_points).mean()
    dense_cd = chamfer_l1(dense, gt_points).mean()
    completion = sparse + dense_cd
    reg_coarse = pose_loss(coarse_transform, gt_transform).mean()
    fine = pose_loss(fine_transform, gt_transform)  # B
    if config.fine_gated:
        in_basin = in_fine_gate(coarse_transform, gt_transform, config)
        fine = torch.where(in_basin, fine, torch.zeros_like(fine))
    reg_fine = fine.mean()
    registration = config.lambda_coarse * reg_coarse + config.lambda_fine * reg_fine
    correspondence = correspondence_loss(correspondences, gt_transform)
    if correspondences is not None:
        registration = registration + config.lambda_correspondence * correspondence
        registration = registration + config.lambda_correspondence * pose_loss(
            correspondences.global_transform, gt_transform).mean()
    lambda_reg = balance_weight(completion, registration, config)
    total = completion + lambda_reg * registration
    return LossTerms(total, completion, sparse, dense_cd, registration, reg_coarse, reg_fine,
                     lambda_reg, correspondence)


def balance_weight(completion: Tensor, registration: Tensor, config: LossConfig) -> Tensor:
    """The adaptive weight ``lambda_reg = rho * L_completion / L_registration`` (detached) of
    the registration term, from batch-mean losses (scalars). Training on several processes
    passes the means over all processes, so every process weighs with the global batch's
    ratio, as a single process would (:mod:`comreg_core.training.distributed`)."""
    return (config.rho * completion / registration.clamp_min(1e-12)).detach()


def correspondence_loss(correspondences: Correspondences | None, gt_transform: Tensor) -> Tensor:
    """Mean distance of the predicted CT points ``y_i`` from ``T^-1 c_i`` (0 when None).

    Args:
        correspondences: positions ``c_i`` ``(B, T, 3)`` (source frame) and predictions ``y_i``.
        gt_transform: ``(B, 4, 4)`` ground truth ``T^-1`` (source -> CT).
    """
    if correspondences is None:
        return gt_transform.new_zeros(())
    truth = transform_points(gt_transform, correspondences.positions.detach())  # B T 3
    return safe_norm(correspondences.predicted - truth, dim=-1).mean()


def output_loss(output: ComRegOutput, gt_points: Tensor, gt_transform: Tensor,
                config: LossConfig | None = None) -> LossTerms:
    """:func:`comreg_loss` of a :class:`~comreg_core.model.comreg.ComRegOutput`.

    Args:
        output: the network's output for sources ``S^t``.
        gt_points: ``(B, M, 3)`` the complete CT cloud moved into each source frame (``T^t``).
        gt_transform: ``(B, 4, 4)`` ground-truth ``T^-1`` (source -> CT).
        config: loss weights.
    """
    return comreg_loss(output.completion.centres, output.completion.dense, gt_points,
                       output.coarse_transform, output.fine_transform, gt_transform, config,
                       output.correspondences)
