"""Shape completion module ``f``: AdaPoinTr (Yu et al., PoinTr / AdaPoinTr) in pure PyTorch.

Pipeline (one cloud ``(B, N, 3)`` in, ComReg's quantities out)::

    xyz --DGCNN grouper (edge convs, FPS to center_num[0] then center_num[1])--> proxies P, F
    F + pos(P) --geometry-aware encoder (kNN graph attention + self-attention)--> V
    V --max-pool--> global g --MLP--> num_query predicted centres of missing regions
      + num_query // 2 FPS centres of the input --ranking MLP, keep num_query--> centres C
    [g, C] --MLP--> queries Q --decoder (self + cross attention, kNN graph parts)--> H = M_D(Q, V)
    [max-pool(H), H, C] --FoldingNet rebuild head--> a dense patch around each centre

The encoder and decoder blocks are in :mod:`.transformer`.

Differences from the reference implementation, all chosen so the model runs on CPU and CUDA with
the same code and is deterministic in eval mode:

* GroupNorm replaces every BatchNorm (batch size 4); the DGCNN keeps its GroupNorm(4).
* FPS, kNN and gathers come from :mod:`comreg_core.model.ops` (no CUDA extensions); FPS starts
  at a fixed index in eval mode, at a random one in training.
* 1x1 convolutions are ``nn.Linear`` on channels-last tensors. Layers applied to concatenations
  of a per-point and a per-neighbour (or per-seed) term are evaluated as a sum of two smaller
  products (``W [a - b, b] = W1 a + (W2 - W1) b``), which is the same function at a fraction of
  the cost; the parameters keep the reference layer shapes.
* The training-only denoising queries of AdaPoinTr are not used: the ComReg paper trains the
  completion with L_sparse + L_dense only.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from comreg_core.model.config import CompletionConfig
from comreg_core.model.ops import check_points, furthest_point_sample, gather_points, knn
from comreg_core.model.transformer import (DecoderBlock, EncoderBlock, Mlp,
                                          init_transformer_weights, split_pair_linear)


class CompletionOutput(NamedTuple):
    """What ``f`` returns for a batch of clouds.

    Attributes:
        centres: ``(B, Q, 3)`` coarse centres C (predicted + observed, ranked).
        dense: ``(B, Q * S, 3)`` dense completion (S points per centre), or None when not rebuilt.
        decoded: ``(B, Q, D)`` decoded query features H = M_D(Q, V).
        encoded: ``(B, P, E)`` encoder features V of the point proxies.
        proxies: ``(B, P, 3)`` proxy positions (the second FPS level of the input).
        global_feature: ``(B, G)`` max-pooled encoder feature.
    """

    centres: Tensor
    dense: Tensor | None
    decoded: Tensor
    encoded: Tensor
    proxies: Tensor
    global_feature: Tensor


class GroupNormLast(nn.Module):
    """GroupNorm for channels-last tensors ``(B, ..., C)``: statistics per sample and channel group
    over every other position, i.e. ``nn.GroupNorm`` applied to the ``(B, C, ...)`` layout."""

    def __init__(self, num_groups: int, num_channels: int, eps: float = 1e-5):
        super().__init__()
        if num_channels % num_groups:
            raise ValueError(f"{num_channels} channels cannot form {num_groups} groups")
        self.num_groups = num_groups
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(num_channels))
        self.bias = nn.Parameter(torch.zeros(num_channels))

    def forward(self, x: Tensor) -> Tensor:
        # A channels-last view handed to the native kernel (8x faster than composing var_mean).
        y = F.group_norm(x.movedim(-1, 1), self.num_groups, self.weight, self.bias, self.eps)
        return y.movedim(1, -1)


class EdgeConv(nn.Module):
    """DGCNN edge convolution: ``max_j LeakyReLU(GN(W [f_j - f_i, f_i]))`` over the k neighbours j.

    Evaluated as ``W1 f_j + (W2 - W1) f_i`` so the linear layer runs once per point, not per edge.
    """

    def __init__(self, in_dim: int, out_dim: int, groups: int = 4):
        super().__init__()
        self.in_dim = in_dim
        self.linear = nn.Linear(2 * in_dim, out_dim, bias=False)
        self.norm = GroupNormLast(groups, out_dim)

    def forward(self, f_query: Tensor, f_ref: Tensor, idx: Tensor) -> Tensor:
        """Args: f_query ``(B, Nq, C)``, f_ref ``(B, Nr, C)``, idx ``(B, Nq, k)`` into f_ref.
        Returns: ``(B, Nq, C_out)``."""
        w_nb, w_self = split_pair_linear(self.linear, self.in_dim)
        per_ref = f_ref @ w_nb.T  # B Nr Co
        per_query = f_query @ (w_self - w_nb).T  # B Nq Co
        edges = gather_points(per_ref, idx) + per_query.unsqueeze(2)  # B Nq k Co
        return F.leaky_relu(self.norm(edges), 0.2).amax(dim=2)  # B Nq Co


class DGCNNGrouper(nn.Module):
    """AdaPoinTr's DGCNN point-proxy extractor: four edge convolutions on coordinate kNN graphs,
    with FPS down-sampling to ``center_num[0]`` after the first and ``center_num[1]`` after the
    third. Output: proxies ``(B, P, 3)`` and features ``(B, P, 128)``."""

    num_features = 128

    def __init__(self, k: int = 16, center_num: tuple[int, int] = (512, 256)):
        super().__init__()
        self.k = k
        self.center_num = tuple(center_num)
        self.input_trans = nn.Linear(3, 8)
        self.layer1 = EdgeConv(8, 32)
        self.layer2 = EdgeConv(32, 64)
        self.layer3 = EdgeConv(64, 64)
        self.layer4 = EdgeConv(64, 128)

    def forward(self, xyz: Tensor, start_index: int | None = 0) -> tuple[Tensor, Tensor]:
        """Args: xyz ``(B, N, 3)``, ``N >= center_num[0]``; start_index as in FPS.
        Returns: proxies ``(B, P, 3)`` and features ``(B, P, 128)``, P = center_num[1]."""
        k = self.k
        f = self.input_trans(xyz)  # B N 8
        f = self.layer1(f, f, knn(xyz, xyz, k))  # B N 32
        sel = furthest_point_sample(xyz, self.center_num[0], start_index)  # B P0
        coor_q, f_q = gather_points(xyz, sel), gather_points(f, sel)  # B P0 3, B P0 32
        f = self.layer2(f_q, f, knn(coor_q, xyz, k))  # B P0 64
        coor = coor_q
        f = self.layer3(f, f, knn(coor, coor, k))  # B P0 64
        sel = furthest_point_sample(coor, self.center_num[1], start_index)  # B P1
        coor_q, f_q = gather_points(coor, sel), gather_points(f, sel)  # B P1 3, B P1 64
        f = self.layer4(f_q, f, knn(coor_q, coor, k))  # B P1 128
        return coor_q, f


class FoldingHead(nn.Module):
    """FoldingNet patch generator: two folds of a 2-D grid conditioned on a token feature.

    ``fold1([seed, feature]) -> p1``, ``fold2([p1, feature]) -> p2`` with each fold
    Linear -> GroupNorm -> ReLU -> Linear -> GroupNorm -> ReLU -> Linear (3). GroupNorm takes
    statistics per token over the patch, replacing the reference's BatchNorm.
    """

    def __init__(self, in_dim: int, grid: tuple[int, int] = (5, 8), hidden: int = 256):
        super().__init__()
        rows, cols = grid
        a = torch.linspace(-1.0, 1.0, cols).view(1, cols).expand(rows, cols).reshape(-1)
        b = torch.linspace(-1.0, 1.0, rows).view(rows, 1).expand(rows, cols).reshape(-1)
        self.register_buffer("seed", torch.stack([a, b], dim=-1), persistent=False)  # S 2
        self.in_dim = in_dim
        groups = 8
        self.fold1_in = nn.Linear(2 + in_dim, hidden)
        self.fold1 = nn.ModuleList([GroupNormLast(groups, hidden), nn.Linear(hidden, hidden // 2),
                                    GroupNormLast(groups, hidden // 2), nn.Linear(hidden // 2, 3)])
        self.fold2_in = nn.Linear(3 + in_dim, hidden)
        self.fold2 = nn.ModuleList([GroupNormLast(groups, hidden), nn.Linear(hidden, hidden // 2),
                                    GroupNormLast(groups, hidden // 2), nn.Linear(hidden // 2, 3)])

    @staticmethod
    def _tail(layers: nn.ModuleList, x: Tensor) -> Tensor:
        norm1, lin2, norm2, lin3 = layers
        x = F.relu(norm1(x))
        x = F.relu(norm2(lin2(x)))
        return lin3(x)

    def forward(self, feature: Tensor) -> Tensor:
        """Args: feature ``(T, C)`` one vector per token. Returns ``(T, S, 3)`` patch offsets."""
        seed = self.seed.to(feature.dtype)  # S 2
        w_seed, w_feat = split_pair_linear(self.fold1_in, 2)
        per_token = feature @ w_feat.T + self.fold1_in.bias  # T H
        x = per_token.unsqueeze(1) + (seed @ w_seed.T).unsqueeze(0)  # T S H
        p1 = self._tail(self.fold1, x)  # T S 3
        w_p, w_feat = split_pair_linear(self.fold2_in, 3)
        per_token = feature @ w_feat.T + self.fold2_in.bias  # T H
        x = per_token.unsqueeze(1) + p1 @ w_p.T  # T S H
        return self._tail(self.fold2, x)  # T S 3


class RebuildHead(nn.Module):
    """AdaPoinTr's rebuild head: ``[max-pool(MLP(H)), H, C] -> Linear -> FoldingHead``, patches
    added to their centres."""

    def __init__(self, dim: int, width: int, grid: tuple[int, int], hidden: int):
        super().__init__()
        self.increase_dim = nn.Sequential(nn.Linear(dim, width), GroupNormLast(32 if width % 32 == 0
                                                                               else 1, width),
                                          nn.LeakyReLU(0.2), nn.Linear(width, width))
        self.reduce_map = nn.Linear(dim + width + 3, dim)
        self.fold = FoldingHead(dim, grid, hidden)

    def forward(self, decoded: Tensor, centres: Tensor) -> Tensor:
        """Args: decoded ``(B, Q, D)``, centres ``(B, Q, 3)``. Returns dense ``(B, Q * S, 3)``."""
        B, Q, _ = decoded.shape
        g = self.increase_dim(decoded).amax(dim=1)  # B W
        feat = torch.cat([g.unsqueeze(1).expand(-1, Q, -1), decoded, centres], dim=-1)  # B Q W+D+3
        feat = self.reduce_map(feat)  # B Q D
        offsets = self.fold(feat.reshape(B * Q, -1)).reshape(B, Q, -1, 3)  # B Q S 3
        return (offsets + centres.unsqueeze(2)).reshape(B, -1, 3)  # B Q*S 3


class AdaPoinTr(nn.Module):
    """The completion module ``f``; see the module docstring.

    Args:
        config: :class:`CompletionConfig`.
    """

    def __init__(self, config: CompletionConfig):
        super().__init__()
        self.config = c = config
        E, D = c.encoder_dim, c.decoder_dim
        self.grouper = DGCNNGrouper(c.dgcnn_k, c.center_num)
        self.pos_embed = Mlp(3, 128, E)
        self.input_proj = Mlp(DGCNNGrouper.num_features, 512, E)
        self.encoder = nn.ModuleList([EncoderBlock(E, c.num_heads, c.mlp_ratio, i < c.graph_blocks)
                                      for i in range(c.encoder_depth)])
        self.increase_dim = Mlp(E, c.mlp_hidden, c.global_feature_dim)
        self.coarse_pred = Mlp(c.global_feature_dim, c.mlp_hidden, 3 * c.num_query)
        self.mlp_query = nn.Sequential(
            nn.Linear(c.global_feature_dim + 3, c.mlp_hidden), nn.GELU(),
            nn.Linear(c.mlp_hidden, c.mlp_hidden), nn.GELU(), nn.Linear(c.mlp_hidden, D))
        self.mem_link = nn.Identity() if E == D else nn.Linear(E, D)
        self.query_ranking = nn.Sequential(nn.Linear(3, 256), nn.GELU(), nn.Linear(256, 256),
                                           nn.GELU(), nn.Linear(256, 1), nn.Sigmoid())
        self.decoder = nn.ModuleList([DecoderBlock(D, c.num_heads, c.mlp_ratio, i < c.graph_blocks)
                                      for i in range(c.decoder_depth)])
        # As in AdaPoinTr: truncated-normal init for the transformer and query parts; the DGCNN
        # and the rebuild head (convolutions in the reference) keep PyTorch's default init.
        for module in (self.pos_embed, self.input_proj, self.encoder, self.increase_dim,
                       self.coarse_pred, self.mlp_query, self.mem_link, self.query_ranking,
                       self.decoder):
            module.apply(init_transformer_weights)
        self.rebuild_head = RebuildHead(D, c.mlp_hidden, c.fold_grid, c.fold_hidden)

    @property
    def min_points(self) -> int:
        """Fewest input points the module accepts."""
        return max(self.config.center_num[0], self.config.num_query // 2, self.config.dgcnn_k)

    def forward(self, xyz: Tensor, rebuild: bool = True) -> CompletionOutput:
        """Complete a batch of partial clouds.

        Args:
            xyz: ``(B, N, 3)`` partial clouds in normalised coordinates, ``N >= min_points``.
            rebuild: build the dense completion (False skips the folding head, e.g. for the CT
                cloud, whose decoded features are all the pose head needs).

        Returns:
            :class:`CompletionOutput`.
        """
        check_points(xyz, "xyz")
        if xyz.shape[1] < self.min_points:
            raise ValueError(f"the completion network needs at least {self.min_points} points per "
                             f"cloud, got {xyz.shape[1]}")
        c = self.config
        B = xyz.shape[0]
        start = None if self.training else 0
        proxies, feats = self.grouper(xyz, start)  # B P 3, B P 128
        x = self.input_proj(feats) + self.pos_embed(proxies)  # B P E
        idx = knn(proxies, proxies, c.graph_k)  # B P k
        for block in self.encoder:
            x = block(x, idx)  # B P E
        encoded = x
        g = self.increase_dim(x).amax(dim=1)  # B G
        predicted = self.coarse_pred(g).reshape(B, -1, 3)  # B Q 3
        fps_idx = furthest_point_sample(xyz, c.num_query // 2, start)  # B Q/2
        observed = gather_points(xyz, fps_idx)  # B Q/2 3
        candidates = torch.cat([predicted, observed], dim=1)  # B 3Q/2 3
        score = self.query_ranking(candidates).squeeze(-1)  # B 3Q/2
        order = torch.argsort(score, dim=1, descending=True, stable=True)[:, :c.num_query]  # B Q
        centres = gather_points(candidates, order)  # B Q 3
        q = self.mlp_query(torch.cat([g.unsqueeze(1).expand(-1, c.num_query, -1), centres], -1))
        memory = self.mem_link(encoded)  # B P D
        self_idx = knn(centres, centres, c.graph_k)  # B Q k
        cross_idx = knn(centres, proxies, c.graph_k)  # B Q k
        for block in self.decoder:
            q = block(q, memory, self_idx, cross_idx)  # B Q D
        dense = self.rebuild_head(q, centres) if rebuild else None  # B Q*S 3
        return CompletionOutput(centres, dense, q, encoded, proxies, g)
