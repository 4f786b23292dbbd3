"""Registration module ``g``: ``MLP(pool(H(S^t)) (+) pool(H(T))) -> coarse inverse transform``.

Pooling. ``H`` is a set of per-query features whose order is set by AdaPoinTr's query ranking (and
whose count may differ between clouds), so the head pools it to a fixed size with a symmetric
function, PointNet style: every token's feature is concatenated with its 3-D position (its query
centre), passed through one shared Linear + GELU layer, then max- and mean-pooled. Reasons:

* permutation invariant and independent of the number of tokens (flattening would tie MLP weights
  to arbitrary ranking slots and fix the query count);
* the positions make the pooled vector say *where* each feature sits; the pose is a relation
  between where things are in the two clouds, which pooled features alone cannot express;
* max keeps the most salient local parts (the bone ends, whose asymmetry disambiguates
  near-symmetric long bones); mean keeps the overall layout (centroid, extent), which gives the
  translation.

The two pooled vectors are concatenated (source first) and fed to ``num_blocks`` blocks of
Linear + GroupNorm + GELU (width 512 in the paper) and a last Linear to 7 numbers: a quaternion
(w, x, y, z), normalised, and a translation. The last layer's quaternion bias starts at the identity
rotation.

``CorrespondencePoseHead`` (``head: correspondence``, not in the paper; the ``cpu`` preset's)
predicts the pose through the points instead: each source token (query centre ``c_i``, feature
``H_i``) gets the pooled source and target vectors appended, and a per-token MLP (the same
blocks) predicts an offset ``d_i`` and a weight logit. A global MLP on the pooled vectors and
the tokens' centroid and covariance directions predicts a rotation ``R`` (6-D representation of
Zhou et al. 2019) and translation ``t``; token ``i`` lies on the CT at ``y_i = R c_i + t + d_i``
(normalised CT coordinates). The coarse transform is the weighted Procrustes fit ``c_i -> y_i``
(weights: softmax over the tokens), differentiable. Every token is supervised (``y_i`` against
``T^-1 c_i``) and so is ``R, t``: each sample gives ``Q`` targets instead of one pose, a dense
signal that learns within a CPU budget, where the pooled MLP's rotation had not moved from the
initial poses' error after 30 minutes (docs/results.md).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from comreg_core.model.config import PoseHeadConfig
from comreg_core.model.diff_icp import weighted_procrustes
from comreg_core.model.ops import (make_transform, matrix_to_quaternion, quaternion_to_matrix,
                                   rotation_6d_to_matrix)


class Correspondences(NamedTuple):
    """The correspondence head's per-token prediction (normalised units).

    Attributes:
        positions: ``(B, T, 3)`` the source tokens' positions (query centres), source frame.
        predicted: ``(B, T, 3)`` where each lies on the CT, CT frame.
        weights: ``(B, T)`` Procrustes weights (sum 1 per sample).
        global_transform: ``(B, 4, 4)`` the head's global rotation and translation (source ->
            CT).
    """

    positions: Tensor
    predicted: Tensor
    weights: Tensor
    global_transform: Tensor


class PoseOutput(NamedTuple):
    """A pose head's output: ``transform`` ``(B, 4, 4)`` source -> target, its unit quaternion
    ``(B, 4)`` (w, x, y, z), translation ``(B, 3)``, and the :class:`Correspondences` (None for
    the MLP head)."""

    transform: Tensor
    quaternion: Tensor
    translation: Tensor
    correspondences: Correspondences | None


def _check_tokens(source_tokens, source_positions, target_tokens, target_positions) -> None:
    for name, tok, pos in (("source", source_tokens, source_positions),
                           ("target", target_tokens, target_positions)):
        if tok.ndim != 3 or pos.shape != (*tok.shape[:2], 3):
            raise ValueError(f"{name} tokens {tuple(tok.shape)} and positions "
                             f"{tuple(pos.shape)} must be (B, T, C) and (B, T, 3)")
    if target_tokens.shape[0] not in (1, source_tokens.shape[0]):
        raise ValueError(f"target batch {target_tokens.shape[0]} must be 1 or "
                         f"{source_tokens.shape[0]}")


def _mlp_blocks(width: int, config: PoseHeadConfig) -> nn.Sequential:
    """``num_blocks`` x (Linear + GroupNorm + GELU), ``width`` -> ``hidden_dim``."""
    layers: list[nn.Module] = []
    for _ in range(config.num_blocks):
        layers += [nn.Linear(width, config.hidden_dim),
                   nn.GroupNorm(config.norm_groups, config.hidden_dim), nn.GELU()]
        width = config.hidden_dim
    return nn.Sequential(*layers)


def _init_linear(module: nn.Module) -> None:
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.trunc_normal_(m.weight, std=0.02)
            nn.init.zeros_(m.bias)


def position_moments(positions: Tensor) -> Tensor:
    """``(B, T, 3)`` -> ``(B, 9)``: the positions' centroid and the six distinct entries of their
    covariance divided by its trace (the spread's directions, not its size; invariant to
    which way an axis points, so it carries no sign the network has to undo)."""
    centroid = positions.mean(dim=1)  # B 3
    d = positions - centroid[:, None]
    cov = d.transpose(1, 2) @ d / positions.shape[1]  # B 3 3
    cov = cov / cov.diagonal(dim1=1, dim2=2).sum(-1).clamp_min(1e-12)[:, None, None]
    i, j = torch.triu_indices(3, 3)
    return torch.cat([centroid, cov[:, i, j]], dim=-1)


def build_pose_head(feature_dim: int, config: PoseHeadConfig) -> nn.Module:
    """The head ``config.head`` names: :class:`PoseHead` or :class:`CorrespondencePoseHead`."""
    if config.head == "correspondence":
        return CorrespondencePoseHead(feature_dim, config)
    return PoseHead(feature_dim, config)


class PoseHead(nn.Module):
    """Coarse source -> target pose from two token sets.

    Args:
        feature_dim: width of the tokens H (the decoder's width).
        config: :class:`PoseHeadConfig`.
    """

    def __init__(self, feature_dim: int, config: PoseHeadConfig):
        super().__init__()
        self.config = config
        self.token = nn.Linear(feature_dim + 3, config.token_dim)
        self.mlp = _mlp_blocks(4 * config.token_dim, config)  # [max, mean] x [source, target]
        self.out = nn.Linear(config.hidden_dim, 7)  # quaternion + translation
        _init_linear(self)
        with torch.no_grad():  # identity rotation at the start
            self.out.bias[0] = 1.0  # (1, 0, 0, 0)

    def pool(self, tokens: Tensor, positions: Tensor) -> Tensor:
        """Args: tokens ``(B, T, C)``, positions ``(B, T, 3)``. Returns ``(B, 2 * token_dim)``."""
        h = F.gelu(self.token(torch.cat([tokens, positions], dim=-1)))  # B T P
        return torch.cat([h.amax(dim=1), h.mean(dim=1)], dim=-1)  # B 2P

    def forward(self, source_tokens: Tensor, source_positions: Tensor, target_tokens: Tensor,
                target_positions: Tensor) -> PoseOutput:
        """Predict the coarse transform taking the source cloud onto the target cloud.

        Args:
            source_tokens: ``(B, Ts, C)`` features of the source cloud; source_positions
                ``(B, Ts, 3)``.
            target_tokens: ``(B | 1, Tt, C)`` features of the target cloud; target_positions
                ``(B | 1, Tt, 3)`` (a batch of 1 is shared).

        Returns:
            :class:`PoseOutput` (no correspondences).
        """
        _check_tokens(source_tokens, source_positions, target_tokens, target_positions)
        B = source_tokens.shape[0]
        src = self.pool(source_tokens, source_positions)  # B 2P
        tgt = self.pool(target_tokens, target_positions).expand(B, -1)  # B 2P
        out = self.out(self.mlp(torch.cat([src, tgt], dim=-1)))  # B 7
        translation = out[:, 4:]  # B 3
        quaternion = out[:, :4] / out[:, :4].norm(dim=-1, keepdim=True).clamp_min(1e-12)
        transform = make_transform(quaternion_to_matrix(quaternion), translation)  # B 4 4
        return PoseOutput(transform, quaternion, translation, None)


class CorrespondencePoseHead(nn.Module):
    """Coarse pose as the weighted Procrustes fit of the source tokens' positions to predicted
    CT points (see the module docstring).

    Args:
        feature_dim: width of the tokens.
        config: :class:`PoseHeadConfig` (``token_dim``, ``hidden_dim``, ``num_blocks``).
    """

    def __init__(self, feature_dim: int, config: PoseHeadConfig):
        super().__init__()
        self.config = config
        P = config.token_dim
        self.token = nn.Linear(feature_dim + 3, P)
        self.mlp = _mlp_blocks(5 * P, config)  # [token, source max, mean, target max, mean]
        self.out = nn.Linear(config.hidden_dim, 4)  # CT point offset (3) + weight logit
        self.global_mlp = _mlp_blocks(4 * P + 9, config)  # pooled + position moments
        self.global_out = nn.Linear(config.hidden_dim, 9)  # 6-D rotation + translation
        _init_linear(self)
        with torch.no_grad():  # identity rotation at the start
            self.global_out.bias[0] = self.global_out.bias[4] = 1.0

    def forward(self, source_tokens: Tensor, source_positions: Tensor, target_tokens: Tensor,
                target_positions: Tensor) -> PoseOutput:
        """Same arguments as :meth:`PoseHead.forward`; returns :class:`PoseOutput` with the
        :class:`Correspondences`."""
        _check_tokens(source_tokens, source_positions, target_tokens, target_positions)
        B, T, _ = source_tokens.shape
        h_src = F.gelu(self.token(torch.cat([source_tokens, source_positions], -1)))  # B T P
        h_tgt = F.gelu(self.token(torch.cat([target_tokens, target_positions], -1)))  # Bt T' P
        pooled = torch.cat([h_src.amax(1), h_src.mean(1), h_tgt.amax(1).expand(B, -1),
                            h_tgt.mean(1).expand(B, -1)], dim=-1)  # B 4P
        x = torch.cat([h_src, pooled.unsqueeze(1).expand(-1, T, -1)], dim=-1)  # B T 5P
        out = self.out(self.mlp(x.reshape(B * T, -1))).reshape(B, T, 4)  # B T 4
        positions = source_positions.detach()
        inputs = torch.cat([pooled, position_moments(positions)], -1)  # B 4P+9
        pose = self.global_out(self.global_mlp(inputs))  # B 9
        rotation = rotation_6d_to_matrix(pose[:, :6])  # B 3 3
        global_transform = make_transform(rotation, pose[:, 6:])  # B 4 4
        predicted = positions @ rotation.transpose(1, 2) + pose[:, None, 6:] + out[..., :3]  # B T 3
        weights = torch.softmax(out[..., 3], dim=1)  # B T
        R, t = weighted_procrustes(positions, predicted, weights)  # B 3 3, B 3
        transform = make_transform(R, t)  # B 4 4
        return PoseOutput(transform, matrix_to_quaternion(R.detach()), t,
                          Correspondences(positions, predicted, weights, global_transform))
