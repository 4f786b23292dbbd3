"""Typed configuration of the ComReg network; its defaults are the ``paper`` preset.

``ModelConfig`` has four sections: ``completion`` (AdaPoinTr), ``pose`` (the coarse registration
MLP), ``icp`` (the differentiable ICP) and ``loss``. The defaults are the ``paper`` preset: the
ComReg paper's numbers (20,000 points, sigma = 5e-3, K = 25, N_c = 4096, lambda_coarse = 1,
lambda_fine = 0.5, rho = 0.1, a five-block 512-wide pose MLP) and AdaPoinTr's PCN sizes for
everything the paper takes from AdaPoinTr (384-wide encoder of depth 6 and decoder of depth 8,
6 heads, k = 8 graph attention in the first block, proxies 512 -> 256, 1024-d global feature).
The ``cpu`` preset (:data:`comreg_core.training.config.PRESETS`) shrinks the completion network
and the point counts; it was chosen by measuring forward + backward time at batch 4 on 2 CPU
cores (see ``tests/benchmarks/bench_model.py``).

All lengths (sigma) are in the network's normalised coordinates (see
:mod:`comreg_core.normalization`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar, Literal

from comreg_core.config import RetiredCheck, require


@dataclass(frozen=True)
class CompletionConfig:
    """AdaPoinTr completion module ``f``.

    Attributes:
        input_points: clouds with more points are reduced to this many by FPS before ``f``.
        center_num: point proxies after the first and second DGCNN down-sampling (FPS).
        dgcnn_k: neighbours of the DGCNN edge convolutions.
        encoder_dim, encoder_depth: width and number of blocks of the geometry-aware encoder.
        decoder_dim, decoder_depth: the same for the decoder.
        num_heads: attention heads (encoder and decoder).
        mlp_ratio: hidden width of each block's MLP, as a multiple of its width.
        graph_k: neighbours of the kNN graph attention.
        graph_blocks: how many leading blocks (encoder, decoder self- and cross-attention) add
            kNN graph attention to global attention (AdaPoinTr: 1, "attn-graph" then "attn").
        global_feature_dim: width of the max-pooled global feature feeding the query generator.
        mlp_hidden: hidden width of the query generator MLPs and the rebuild head's global feature.
        num_query: queries (coarse centres C). The query generator predicts ``num_query`` centres
            of missing regions, adds ``num_query // 2`` FPS centres of the input, and keeps the
            ``num_query`` best ranked.
        fold_grid: rows x columns of the 2-D folding seed: points per centre in the dense output.
        fold_hidden: hidden width of the folding MLPs.
    """

    input_points: int = 20000
    center_num: tuple[int, int] = (512, 256)
    dgcnn_k: int = 16
    encoder_dim: int = 384
    encoder_depth: int = 6
    decoder_dim: int = 384
    decoder_depth: int = 8
    num_heads: int = 6
    mlp_ratio: float = 2.0
    graph_k: int = 8
    graph_blocks: int = 1
    global_feature_dim: int = 1024
    mlp_hidden: int = 1024
    num_query: int = 500
    fold_grid: tuple[int, int] = (5, 8)
    fold_hidden: int = 256

    def __post_init__(self) -> None:
        p = "completion."
        require(self.center_num[0] >= self.center_num[1] >= 1, p + "center_num",
                "must be two decreasing positive proxy counts")
        require(self.input_points >= self.center_num[0], p + "input_points",
                "must be at least center_num[0]")
        require(self.dgcnn_k >= 1 and self.dgcnn_k <= self.center_num[1], p + "dgcnn_k",
                "must be between 1 and center_num[1]")
        for name in ("encoder_dim", "decoder_dim"):
            dim = getattr(self, name)
            require(dim >= 1 and dim % self.num_heads == 0, p + name,
                    f"must be a positive multiple of num_heads ({self.num_heads})")
        require(self.num_heads >= 1, p + "num_heads", "must be at least 1")
        require(self.encoder_depth >= 1 and self.decoder_depth >= 1, p + "encoder/decoder_depth",
                "must be at least 1")
        require(self.mlp_ratio > 0, p + "mlp_ratio", "must be positive")
        require(self.num_query >= 2, p + "num_query", "must be at least 2")
        require(1 <= self.graph_k <= min(self.center_num[1], self.num_query), p + "graph_k",
                "must be between 1 and the number of proxies and of queries")
        require(0 <= self.graph_blocks <= min(self.encoder_depth, self.decoder_depth),
                p + "graph_blocks", "must be between 0 and the encoder and decoder depths")
        require(self.global_feature_dim >= 1 and self.mlp_hidden % 8 == 0 and self.mlp_hidden > 0,
                p + "global_feature_dim/mlp_hidden",
                "must be positive (mlp_hidden a multiple of 8)")
        require(self.fold_grid[0] >= 1 and self.fold_grid[1] >= 1, p + "fold_grid",
                "must be two positive numbers")
        require(self.fold_hidden >= 16 and self.fold_hidden % 16 == 0, p + "fold_hidden",
                "must be a multiple of 16")

    @property
    def points_per_centre(self) -> int:
        return self.fold_grid[0] * self.fold_grid[1]

    @property
    def dense_points(self) -> int:
        """Size of the dense completion: ``num_query`` patches of ``points_per_centre`` points."""
        return self.num_query * self.points_per_centre


@dataclass(frozen=True)
class PoseHeadConfig:
    """Registration module ``g``: the decoded query features ``H`` of both clouds -> coarse pose.

    Attributes:
        head: ``"mlp"`` (the paper): pooled tokens -> MLP -> quaternion + translation.
            ``"correspondence"``: every source token predicts where its query centre lies on
            the CT as a global rotation and translation applied to the centre plus a per-token
            offset, and a weight; the coarse pose is the weighted Procrustes fit of the centres
            to those points (see :mod:`.pose_head`). Not in the paper; the ``cpu`` preset uses
            it because it learns within a CPU budget (docs/results.md).
        token_dim: width of the shared per-token layer applied before pooling.
        hidden_dim, num_blocks: the MLP: ``num_blocks`` x (Linear + GroupNorm + GELU).
        norm_groups: GroupNorm groups in the MLP.
    """

    head: Literal["mlp", "correspondence"] = "mlp"

    #: removed options (docs/results.md): what survived, or any value where the head ignored it
    RETIRED_KEYS: ClassVar[dict[str, RetiredCheck]] = {
        "rotation": lambda value, section: value == "quaternion",
        "correspondence": lambda value, section: (value == "rotated"
                                                  or section.get("head", "mlp") == "mlp"),
        "moments": lambda value, section: value is True or section.get("head", "mlp") == "mlp",
        "features": lambda value, section: value == "decoded",
    }
    token_dim: int = 512
    hidden_dim: int = 512
    num_blocks: int = 5
    norm_groups: int = 8

    def __post_init__(self) -> None:
        require(self.token_dim >= 1, "pose.token_dim", "must be positive")
        require(self.num_blocks >= 1, "pose.num_blocks", "must be at least 1")
        require(self.norm_groups >= 1 and self.hidden_dim % self.norm_groups == 0,
                "pose.hidden_dim", "must be a positive multiple of pose.norm_groups")


@dataclass(frozen=True)
class ICPConfig:
    """Differentiable ICP refinement.

    Attributes:
        iterations: K.
        num_points: N_c, points per cloud (FPS subset of source and target).
        sigma: softness of the correspondences, normalised units.
        neighbors: soft correspondences are restricted to this many nearest targets.
        mesh_refine: outside training (validation, ``register``, ``evaluate``), refine the
            ICP's result by trimmed point-to-plane ICP against the CT mesh
            (:func:`comreg_core.registration.geometry.icp.refine_on_mesh`). Not in the paper; used by
            ``cpu``. Why: on the fibula's simulated validation sweeps this differentiable ICP
            (2,048 points of a 4,096-point CT cloud) keeps only 33 % of them within 2 mm /
            2 deg when started at the truth itself; the mesh refinement keeps 100 %
            (docs/results.md).
    """

    iterations: int = 25
    num_points: int = 4096
    sigma: float = 5e-3
    neighbors: int = 32
    mesh_refine: bool = False

    #: removed options (docs/results.md): the soft, untrimmed ICP survived
    RETIRED_KEYS: ClassVar[dict[str, RetiredCheck]] = {
        "mode": lambda value, section: value == "soft",
        "trim_fraction": lambda value, section: value == 0,
    }

    def __post_init__(self) -> None:
        require(self.iterations >= 0, "icp.iterations", "must be 0 or more")
        require(self.num_points >= 3, "icp.num_points", "must be at least 3")
        require(self.sigma > 0, "icp.sigma", "must be positive")
        require(self.neighbors >= 1, "icp.neighbors", "must be at least 1")


@dataclass(frozen=True)
class LossConfig:
    """Loss weights: ``L = L_completion + lambda_reg * L_registration`` with
    ``L_registration = lambda_coarse * L_reg(coarse) + lambda_fine * L_reg(fine)`` and the
    adaptive ``lambda_reg = rho * L_completion / L_registration`` (weight detached).

    Attributes:
        fine_gate_deg, fine_gate_translation: a sample's fine term counts only when its coarse
            estimate is within this rotation (degrees) and translation (normalised units, i.e.
            a fraction of the CT's largest extent: 0.025 = 10 mm on a 400 mm fibula) of the
            truth; the others contribute 0 to the batch mean. ICP's result is flat in its start
            inside its basin and erratic outside it, so the gradient reaching the coarse head
            through ICP from a start outside the basin is noise. Trained literally (no gate),
            the fine term drove the ``cpu`` preset's coarse head to a constant pose after one
            epoch (validation coarse RRE ~125 deg, RTE ~660 mm); gated on rotation alone
            (30 deg) the coarse translation still diverged (225 mm after one epoch); with
            the fine term off it learned (median 16.6 deg after 6 minutes). Not in the paper:
            ``fine_gate_deg: 180`` and ``fine_gate_translation: .inf`` give the paper's loss.
        lambda_correspondence: weight of the correspondence terms (``pose.head:
            correspondence`` only): the mean distance (normalised units) of each token's
            predicted CT point from where the true transform puts its query centre, plus the
            pose loss of the head's global rotation and translation against the truth (so the
            rotation is trained directly, not only through the per-token points, which the
            per-token offsets can fit without it).
    """

    lambda_coarse: float = 1.0
    lambda_fine: float = 0.5
    lambda_correspondence: float = 1.0
    rho: float = 0.1
    fine_gate_deg: float = 10.0
    fine_gate_translation: float = 0.025

    #: removed option (docs/results.md): the global pose term now has the correspondence
    #: term's weight (0: the paper preset's MLP head, which ignored it)
    RETIRED_KEYS: ClassVar[dict[str, RetiredCheck]] = {
        "lambda_global": lambda value, section: value in (0, section.get(
            "lambda_correspondence", 1.0)),
    }

    def __post_init__(self) -> None:
        for name in ("lambda_coarse", "lambda_fine", "lambda_correspondence", "rho"):
            require(getattr(self, name) >= 0, f"loss.{name}", "must be 0 or more")
        require(0 < self.fine_gate_deg <= 180, "loss.fine_gate_deg",
                "must lie in (0, 180] degrees (180 = no gate, the paper's loss)")
        require(self.fine_gate_translation > 0, "loss.fine_gate_translation",
                "must be positive (.inf = no gate, the paper's loss)")

    @property
    def fine_gated(self) -> bool:
        """Whether the fine term is restricted to near coarse estimates."""
        return self.fine_gate_deg < 180 or math.isfinite(self.fine_gate_translation)


@dataclass(frozen=True)
class ModelConfig:
    """The whole network: completion, pose head, ICP, losses (defaults = ``paper`` preset).

    The source enters ``f`` and ``g`` in the CT's normalised coordinates, as in the paper
    (the trials of other input frames are in docs/results.md).
    """

    #: removed option (docs/results.md): the CT's frame survived
    RETIRED_KEYS: ClassVar[dict[str, RetiredCheck]] = {
        "input_frame": lambda value, section: value == "ct",
    }

    completion: CompletionConfig = field(default_factory=CompletionConfig)
    pose: PoseHeadConfig = field(default_factory=PoseHeadConfig)
    icp: ICPConfig = field(default_factory=ICPConfig)
    loss: LossConfig = field(default_factory=LossConfig)
