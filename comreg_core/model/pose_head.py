"""Registration module ``g``: ``MLP(pool(H(S^t)) (+) pool(H(T))) -> coarse inverse transform``.

Pooling. ``H`` is a set of per-query features whose order is set by AdaPoinTr's query ranking (and
whose count may differ between clouds, or be the proxy count when ``V`` is fed instead), so the
head pools it to a fixed size with a symmetric function, PointNet style: every token's feature is
concatenated with its 3-D position (query centre for ``H``, proxy position for ``V``), passed
through one shared Linear + GELU layer, then max- and mean-pooled. Reasons:

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
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from comreg_core.model.config import PoseHeadConfig
from comreg_core.model.ops import make_transform, quaternion_to_matrix


class PoseHead(nn.Module):
    """Coarse source -> target pose from two token sets.

    Args:
        feature_dim: width of the tokens (decoder width for H, encoder width for V).
        config: :class:`PoseHeadConfig`.
    """

    def __init__(self, feature_dim: int, config: PoseHeadConfig):
        super().__init__()
        self.config = config
        self.token = nn.Linear(feature_dim + 3, config.token_dim)
        layers: list[nn.Module] = []
        width = 4 * config.token_dim  # [max, mean] x [source, target]
        for _ in range(config.num_blocks):
            layers += [nn.Linear(width, config.hidden_dim),
                       nn.GroupNorm(config.norm_groups, config.hidden_dim), nn.GELU()]
            width = config.hidden_dim
        self.mlp = nn.Sequential(*layers)
        self.out = nn.Linear(config.hidden_dim, 7)
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.trunc_normal_(module.weight, std=0.02)
                nn.init.zeros_(module.bias)
        with torch.no_grad():
            self.out.bias[0] = 1.0  # quaternion (1, 0, 0, 0): identity rotation at the start

    def pool(self, tokens: Tensor, positions: Tensor) -> Tensor:
        """Args: tokens ``(B, T, C)``, positions ``(B, T, 3)``. Returns ``(B, 2 * token_dim)``."""
        h = F.gelu(self.token(torch.cat([tokens, positions], dim=-1)))  # B T P
        return torch.cat([h.amax(dim=1), h.mean(dim=1)], dim=-1)  # B 2P

    def forward(self, source_tokens: Tensor, source_positions: Tensor, target_tokens: Tensor,
                target_positions: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Predict the coarse transform taking the source cloud onto the target cloud.

        Args:
            source_tokens: ``(B, Ts, C)`` features of the source cloud; source_positions
                ``(B, Ts, 3)``.
            target_tokens: ``(B | 1, Tt, C)`` features of the target cloud; target_positions
                ``(B | 1, Tt, 3)`` (a batch of 1 is shared).

        Returns:
            transform ``(B, 4, 4)``, unit quaternion ``(B, 4)`` (w, x, y, z) and translation
            ``(B, 3)``.
        """
        for name, tok, pos in (("source", source_tokens, source_positions),
                               ("target", target_tokens, target_positions)):
            if tok.ndim != 3 or pos.shape != (*tok.shape[:2], 3):
                raise ValueError(f"{name} tokens {tuple(tok.shape)} and positions "
                                 f"{tuple(pos.shape)} must be (B, T, C) and (B, T, 3)")
        B = source_tokens.shape[0]
        if target_tokens.shape[0] not in (1, B):
            raise ValueError(f"target batch {target_tokens.shape[0]} must be 1 or {B}")
        src = self.pool(source_tokens, source_positions)  # B 2P
        tgt = self.pool(target_tokens, target_positions).expand(B, -1)  # B 2P
        out = self.out(self.mlp(torch.cat([src, tgt], dim=-1)))  # B 7
        quaternion = out[:, :4] / out[:, :4].norm(dim=-1, keepdim=True).clamp_min(1e-12)  # B 4
        translation = out[:, 4:]  # B 3
        transform = make_transform(quaternion_to_matrix(quaternion), translation)  # B 4 4
        return transform, quaternion, translation
