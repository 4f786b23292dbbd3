"""Differentiable ICP with soft correspondences and weighted Procrustes (SVD) steps.

Each of the K iterations matches every source point ``x_i`` (the coarse-aligned source moved by
the current estimate) to a soft target ``y_i = sum_j w_ij t_j`` with
``w_ij = softmax_j(-||x_i - t_j||^2 / (2 sigma^2))`` over its k nearest targets (found with a
KD-tree, no gradient; the weights and ``y_i`` are recomputed in torch, so they are exact and
differentiable), then solves ``min_{R,t} sum_i a_i ||R s_i + t - y_i||^2`` in closed form (weighted
Procrustes by SVD with the reflection fix). ``a_i`` are optional per-point
weights. Gradients flow through every iteration to the initial (coarse) transform and to the
source and target points.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from comreg_core.model.ops import KNNIndex, check_points, gather_points, make_transform


class ICPResult(NamedTuple):
    """Result of :func:`differentiable_icp`.

    Attributes:
        transform: ``(B, 4, 4)`` final source -> target transform (the initial one included).
        aligned: ``(B, N, 3)`` source points moved by ``transform``.
        rmse: ``(B,)`` weighted RMS distance of ``aligned`` to the correspondences of the last
            iteration.
        transform_history: ``(B, K', 4, 4)`` the transform after each iteration (K' <= K when
            the optional convergence test stopped early).
        rmse_history: ``(B, K')`` rmse after each iteration.
        converged: ``(B,)`` bool, whether the relative rmse change fell below ``rel_tol`` (all
            False when no ``rel_tol`` was given).
    """

    transform: Tensor
    aligned: Tensor
    rmse: Tensor
    transform_history: Tensor
    rmse_history: Tensor
    converged: Tensor


def soft_correspondences(x: Tensor, neighbours: Tensor, sigma: float) -> Tensor:
    """Soft targets ``y_i = sum_j softmax_j(-||x_i - t_ij||^2 / (2 sigma^2)) t_ij``.

    Args:
        x: ``(B, N, 3)`` points.
        neighbours: ``(B, N, k, 3)`` candidate targets of each point.
        sigma: softness.

    Returns:
        ``(B, N, 3)``, differentiable in ``x`` and ``neighbours``. (A hand-written backward was
        measured no faster than autograd's here, so autograd it is.)
    """
    d2 = (x.unsqueeze(2) - neighbours).square().sum(-1)  # B N k
    w = torch.softmax(d2 * (-0.5 / (sigma * sigma)), dim=-1)  # B N k
    return (w.unsqueeze(-1) * neighbours).sum(2)  # B N 3


class _ProcrustesRotation(torch.autograd.Function):
    """``R = argmax_R tr(R M)`` over rotations, ``R = V D U^T`` for ``M = U S V^T``, with a backward
    that stays finite when singular values repeat (float64 inside).

    Autograd's SVD backward has ``1 / (s_i^2 - s_j^2)`` terms (NaN for a cloud with two equal
    principal spreads, e.g. a round cross-section); the rotation itself only needs
    ``1 / (l_i + l_j)`` with ``l = D S``. From the optimality condition ``R M = V D S V^T``
    (symmetric): ``dL/dM = R^T V (K^T - K) V^T`` with ``K_ij = (V^T G R^T V)_ij / (l_i + l_j)``
    and ``G = dL/dR``.
    """

    @staticmethod
    def forward(ctx, M: Tensor) -> Tensor:
        U, S, Vh = torch.linalg.svd(M)  # B 3 3, B 3, B 3 3
        V = Vh.transpose(1, 2)
        d = torch.sign(torch.linalg.det(V @ U.transpose(1, 2)))  # B
        d = torch.where(d == 0, torch.ones_like(d), d)
        D = torch.ones_like(S)
        D[:, 2] = d
        R = (V * D.unsqueeze(1)) @ U.transpose(1, 2)  # B 3 3
        ctx.save_for_backward(R, V, D * S)
        return R

    @staticmethod
    def backward(ctx, G: Tensor) -> Tensor:
        R, V, lam = ctx.saved_tensors
        H = V.transpose(1, 2) @ G @ R.transpose(1, 2) @ V  # B 3 3
        denom = lam.unsqueeze(2) + lam.unsqueeze(1)  # B 3 3, l_i + l_j
        tiny = 1e-12 * lam.abs().amax(dim=1, keepdim=True).unsqueeze(2).clamp_min(1e-300)
        denom = torch.where(denom.abs() < tiny, torch.where(denom < 0, -tiny, tiny), denom)
        K = H / denom
        return R.transpose(1, 2) @ V @ (K.transpose(1, 2) - K) @ V.transpose(1, 2)


def procrustes_rotation(cov: Tensor) -> Tensor:
    """The rotation maximising ``tr(R cov)`` (``cov = sum_i w_i s_i y_i^T``): ``(B, 3, 3)`` in, a
    proper rotation ``(B, 3, 3)`` out (float64), differentiable with a stable backward."""
    if cov.ndim != 3 or cov.shape[-2:] != (3, 3):
        raise ValueError(f"cov must have shape (B, 3, 3), got {tuple(cov.shape)}")
    return _ProcrustesRotation.apply(cov.double())


def weighted_procrustes(source: Tensor, target: Tensor,
                        weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Rigid transform minimising ``sum_i w_i ||R s_i + t - y_i||^2`` (Kabsch / Umeyama, no scale).

    The 3x3 cross-covariance is decomposed in float64 (cheap and better conditioned), and the
    reflection fix ``diag(1, 1, sign(det(V U^T)))`` keeps ``det(R) = +1``. Differentiable, with
    a backward that stays finite for repeated singular values (:func:`procrustes_rotation`).

    Args:
        source: ``(B, N, 3)`` points s_i.
        target: ``(B, N, 3)`` corresponding points y_i.
        weights: ``(B, N)`` non-negative weights (each cloud needs a positive sum); None = 1.

    Returns:
        ``R`` ``(B, 3, 3)`` and ``t`` ``(B, 3)``, in the dtype of ``source``.
    """
    check_points(source, "source")
    check_points(target, "target")
    if source.shape != target.shape:
        raise ValueError(f"source {tuple(source.shape)} and target {tuple(target.shape)} differ")
    B, N, _ = source.shape
    if weights is None:
        weights = source.new_ones(B, N)
    elif weights.shape != (B, N):
        raise ValueError(f"weights must have shape {(B, N)}, got {tuple(weights.shape)}")
    w = weights / weights.sum(dim=1, keepdim=True)  # B N
    mu_s = (w.unsqueeze(-1) * source).sum(1)  # B 3
    mu_t = (w.unsqueeze(-1) * target).sum(1)  # B 3
    sc = source - mu_s.unsqueeze(1)  # B N 3
    tc = target - mu_t.unsqueeze(1)  # B N 3
    cov = (sc * w.unsqueeze(-1)).transpose(1, 2) @ tc  # B 3 3 = sum_i w_i s_i y_i^T
    R = procrustes_rotation(cov).to(source.dtype)  # B 3 3
    t = mu_t - (R @ mu_s.unsqueeze(-1)).squeeze(-1)  # B 3
    return R, t


def differentiable_icp(source: Tensor, target: Tensor, init_transform: Tensor | None = None, *,
                       iterations: int = 25, sigma: float = 5e-3, neighbors: int | None = 16,
                       source_weights: Tensor | None = None,
                       rel_tol: float | None = None) -> ICPResult:
    """Align ``source`` to ``target`` by K iterations of soft ICP.

    Args:
        source: ``(B, N, 3)`` source points (e.g. the US cloud, normalised coordinates).
        target: ``(B, M, 3)`` or ``(1, M, 3)`` target points (e.g. the CT cloud).
        init_transform: ``(B, 4, 4)`` initial source -> target transform (the coarse pose); None
            starts from the identity. Gradients reach it through every iteration.
        iterations: K (0 returns the initial transform).
        sigma: correspondence softness, same units as the points.
        neighbors: soft correspondences over this many nearest targets (KD-tree); None uses all
            M targets (a dense softmax, O(N M) memory).
        source_weights: ``(B, N)`` optional non-negative per-point weights.
        rel_tol: stop early once every cloud's relative rmse change is below this; None runs all
            K iterations (training).

    Returns:
        :class:`ICPResult`.
    """
    init_transform = _checked_start(source, target, init_transform, iterations, sigma,
                                    source_weights)
    B = source.shape[0]
    R0, t0 = init_transform[:, :3, :3], init_transform[:, :3, 3]
    coarse = source @ R0.transpose(1, 2) + t0.unsqueeze(1)  # B N 3, s^c
    match = _matcher(target, B, sigma, neighbors)
    aligned = coarse  # B N 3
    transforms, rmses = [], []
    converged = torch.zeros(B, dtype=torch.bool, device=source.device)
    prev_rmse = None
    for _ in range(iterations):
        corr = match(aligned)  # B N 3
        R, t = weighted_procrustes(coarse, corr, source_weights)  # B 3 3, B 3
        aligned = coarse @ R.transpose(1, 2) + t.unsqueeze(1)  # B N 3
        rmse = _rmse(aligned, corr, source_weights)  # B
        rmses.append(rmse)
        transforms.append(make_transform(R, t) @ init_transform)
        if rel_tol is not None and prev_rmse is not None:
            converged = _settled(prev_rmse, rmse, rel_tol)
            if bool(converged.all()):
                break
        prev_rmse = rmse.detach()
    return _result(source, init_transform, aligned, transforms, rmses, converged)


def _checked_start(source: Tensor, target: Tensor, init_transform: Tensor | None,
                   iterations: int, sigma: float, source_weights: Tensor | None) -> Tensor:
    """The arguments of :func:`differentiable_icp` checked; its start ``(B, 4, 4)`` (identity
    for None)."""
    check_points(source, "source")
    check_points(target, "target")
    B, N, _ = source.shape
    if target.shape[0] not in (1, B):
        raise ValueError(f"target batch {target.shape[0]} must be 1 or the source batch {B}")
    if sigma <= 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if N < 3:
        raise ValueError(f"ICP needs at least 3 source points, got {N}")
    if init_transform is None:
        init_transform = torch.eye(4, dtype=source.dtype, device=source.device).expand(B, 4, 4)
    elif init_transform.shape != (B, 4, 4):
        raise ValueError(f"init_transform must have shape {(B, 4, 4)}, got "
                         f"{tuple(init_transform.shape)}")
    if source_weights is not None and source_weights.shape != (B, N):
        raise ValueError(f"source_weights must have shape {(B, N)}, got "
                         f"{tuple(source_weights.shape)}")
    return init_transform


def _matcher(target: Tensor, batch: int, sigma: float,
             neighbors: int | None) -> Callable[[Tensor], Tensor]:
    """``points (B, N, 3) -> soft correspondences (B, N, 3)`` in ``target`` ``(B | 1, M, 3)``:
    over the ``neighbors`` nearest targets (KD-tree, built once), or over all M (None)."""
    if neighbors is None:
        def over_all(points: Tensor) -> Tensor:
            d2 = (points.unsqueeze(2) - target.unsqueeze(1)).square().sum(-1)  # B N M
            w = torch.softmax(d2 * (-0.5 / (sigma * sigma)), dim=-1)  # B N M
            return w @ target.expand(batch, -1, -1)  # B N 3
        return over_all
    k = min(neighbors, target.shape[1])
    index = KNNIndex(target)

    def over_nearest(points: Tensor) -> Tensor:
        idx = index.query(points, k).to(points.device)  # B N k
        return soft_correspondences(points, gather_points(target, idx), sigma)  # B N 3
    return over_nearest


def _rmse(aligned: Tensor, corr: Tensor, weights: Tensor | None) -> Tensor:
    """``(B,)`` (weighted) RMS distance of ``aligned`` to ``corr``, both ``(B, N, 3)``."""
    sq = (aligned - corr).square().sum(-1)  # B N
    if weights is None:
        return sq.mean(1).clamp_min(0).sqrt()
    return ((sq * weights).sum(1) / weights.sum(1)).clamp_min(0).sqrt()


def _settled(prev_rmse: Tensor, rmse: Tensor, rel_tol: float) -> Tensor:
    """``(B,)`` bool: the relative rmse change of each cloud is below ``rel_tol``."""
    with torch.no_grad():
        return (prev_rmse - rmse).abs() / prev_rmse.clamp_min(1e-12) < rel_tol


def _result(source: Tensor, init_transform: Tensor, aligned: Tensor, transforms: list[Tensor],
            rmses: list[Tensor], converged: Tensor) -> ICPResult:
    """The :class:`ICPResult` of the iterations run (none: the start, rmse NaN)."""
    if transforms:
        return ICPResult(transforms[-1], aligned, rmses[-1], torch.stack(transforms, dim=1),
                         torch.stack(rmses, dim=1), converged)
    B = source.shape[0]
    return ICPResult(init_transform, aligned, source.new_full((B,), float("nan")),
                     init_transform.new_zeros(B, 0, 4, 4), source.new_zeros(B, 0), converged)
