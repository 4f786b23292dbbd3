"""AdaPoinTr's transformer blocks, channels-last ``(B, N, C)`` tokens: self-, cross- and kNN
graph attention, the encoder and decoder blocks, their MLP and initialisation.

A linear layer on the concatenation ``[a, b]`` is evaluated as ``W1 a + W2 b``
(:func:`split_pair_linear`), the same function at a fraction of the cost, with the reference
layer's shape.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from comreg_core.model.ops import gather_points


def split_pair_linear(linear: nn.Linear, split: int) -> tuple[Tensor, Tensor]:
    """Weights ``(W1, W2)`` of a linear layer on ``[a (split channels), b]``."""
    return linear.weight[:, :split], linear.weight[:, split:]


class Mlp(nn.Module):
    """Linear -> GELU -> Linear."""

    def __init__(self, dim: int, hidden: int, out: int | None = None):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, out or dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class SelfAttention(nn.Module):
    """Multi-head self-attention over the tokens of each cloud."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=False)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, C // self.num_heads)
        q, k, v = qkv.permute(2, 0, 3, 1, 4)  # each B H N C/H
        out = F.scaled_dot_product_attention(q, k, v)  # B H N C/H
        return self.proj(out.transpose(1, 2).reshape(B, N, C))


class CrossAttention(nn.Module):
    """Multi-head attention of queries ``(B, N, C)`` to a memory ``(B, M, C)``."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.q_map = nn.Linear(dim, dim, bias=False)
        self.k_map = nn.Linear(dim, dim, bias=False)
        self.v_map = nn.Linear(dim, dim, bias=False)
        self.proj = nn.Linear(dim, dim)

    def forward(self, q: Tensor, v: Tensor) -> Tensor:
        B, N, C = q.shape
        M = v.shape[1]
        h, d = self.num_heads, C // self.num_heads
        qh = self.q_map(q).reshape(B, N, h, d).transpose(1, 2)  # B h N d
        kh = self.k_map(v).reshape(B, M, h, d).transpose(1, 2)  # B h M d
        vh = self.v_map(v).reshape(B, M, h, d).transpose(1, 2)  # B h M d
        out = F.scaled_dot_product_attention(qh, kh, vh)  # B h N d
        return self.proj(out.transpose(1, 2).reshape(B, N, C))


class GraphAttention(nn.Module):
    """AdaPoinTr's kNN graph attention: ``W_m max_j LeakyReLU(W [v_j - q_i, q_i] + b)`` over the k
    nearest tokens j (by position) of each query token i."""

    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim
        self.knn_map = nn.Linear(2 * dim, dim)
        self.merge_map = nn.Linear(dim, dim)

    def forward(self, q: Tensor, v: Tensor, idx: Tensor) -> Tensor:
        """Args: q ``(B, N, C)``, v ``(B, M, C)``, idx ``(B, N, k)`` into v.
        Returns: ``(B, N, C)``."""
        w_nb, w_self = split_pair_linear(self.knn_map, self.dim)
        per_v = v @ w_nb.T  # B M C
        per_q = q @ (w_self - w_nb).T + self.knn_map.bias  # B N C
        edges = gather_points(per_v, idx) + per_q.unsqueeze(2)  # B N k C
        return self.merge_map(F.leaky_relu(edges, 0.2).amax(dim=2))  # B N C


class EncoderBlock(nn.Module):
    """Pre-norm transformer block; with ``graph`` its attention is ``[self-attn, graph-attn]``
    merged by a linear layer (AdaPoinTr's "attn-graph" block, concat combine style)."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, graph: bool):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = SelfAttention(dim, num_heads)
        self.graph = GraphAttention(dim) if graph else None
        self.merge_map = nn.Linear(2 * dim, dim) if graph else None
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: Tensor, idx: Tensor) -> Tensor:
        """Args: x ``(B, N, C)``; idx ``(B, N, k)`` kNN of each token among the tokens."""
        h = self.norm1(x)
        f = self.attn(h)
        if self.graph is not None:
            f = self.merge_map(torch.cat([f, self.graph(h, h, idx)], dim=-1))
        x = x + f
        return x + self.mlp(self.norm2(x))


class DecoderBlock(nn.Module):
    """Query self-attention, then cross-attention to the encoder memory, then an MLP; with
    ``graph`` both attentions get a kNN graph-attention branch (AdaPoinTr "attn-graph")."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, graph: bool):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.self_attn = SelfAttention(dim, num_heads)
        self.self_graph = GraphAttention(dim) if graph else None
        self.self_merge = nn.Linear(2 * dim, dim) if graph else None
        self.norm_q = nn.LayerNorm(dim)
        self.norm_v = nn.LayerNorm(dim)
        self.cross_attn = CrossAttention(dim, num_heads)
        self.cross_graph = GraphAttention(dim) if graph else None
        self.cross_merge = nn.Linear(2 * dim, dim) if graph else None
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, q: Tensor, v: Tensor, self_idx: Tensor, cross_idx: Tensor) -> Tensor:
        """Args: q ``(B, N, C)`` queries, v ``(B, M, C)`` memory, self_idx ``(B, N, k)`` kNN among
        the queries, cross_idx ``(B, N, k)`` kNN of each query among the memory tokens."""
        h = self.norm1(q)
        f = self.self_attn(h)
        if self.self_graph is not None:
            f = self.self_merge(torch.cat([f, self.self_graph(h, h, self_idx)], dim=-1))
        q = q + f
        hq, hv = self.norm_q(q), self.norm_v(v)
        f = self.cross_attn(hq, hv)
        if self.cross_graph is not None:
            f = self.cross_merge(torch.cat([f, self.cross_graph(hq, hv, cross_idx)], dim=-1))
        q = q + f
        return q + self.mlp(self.norm2(q))


def init_transformer_weights(module: nn.Module) -> None:
    """AdaPoinTr's initialisation (``module.apply``): truncated-normal linear weights (std 0.02),
    zero biases, unit LayerNorms."""
    if isinstance(module, nn.Linear):
        nn.init.trunc_normal_(module.weight, std=0.02)
        if module.bias is not None:
            nn.init.zeros_(module.bias)
    elif isinstance(module, nn.LayerNorm):
        nn.init.ones_(module.weight)
        nn.init.zeros_(module.bias)
