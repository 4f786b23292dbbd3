"""The ComReg network: completion ``f`` + coarse pose ``g`` + differentiable ICP, end to end.

``ComRegNet(config)(source, target)`` takes the (transformed, partial) US cloud ``S^t`` and the CT
cloud ``T``, both in the CT's normalised coordinates (:mod:`comreg_core.model.normalization`),
and returns the completion of ``S^t``, the coarse transform ``T_coarse^-1`` (source -> target)
predicted from ``H(S^t) (+) H(T)``, and its ICP refinement ``T_fine^-1``.

``encode_target`` runs the target half once (e.g. at inference, where the CT is fixed); its
result can be passed as ``target``. In training the CT goes through ``f`` every step (with
gradients), as in the paper; pass it with batch 1 to run it once per step for the whole batch.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from comreg_core.errors import InvalidGeometryError
from comreg_core.model.adapointr import AdaPoinTr, CompletionOutput
from comreg_core.model.config import ModelConfig
from comreg_core.model.diff_icp import ICPResult, differentiable_icp
from comreg_core.model.ops import check_points, subsample
from comreg_core.model.pose_head import PoseHead


class TargetEncoding(NamedTuple):
    """The target (CT) half of the network.

    Attributes:
        tokens: ``(Bt, T, C)`` pose-head tokens (H, or V in the "encoded" ablation).
        positions: ``(Bt, T, 3)`` their positions (query centres, or proxies).
        icp_points: ``(Bt, N_c, 3)`` the ICP subset of the target cloud.
    """

    tokens: Tensor
    positions: Tensor
    icp_points: Tensor


class ComRegOutput(NamedTuple):
    """What :class:`ComRegNet` returns (normalised coordinates throughout).

    Attributes:
        completion: :class:`CompletionOutput` of the source (centres C, dense completion, H, V).
        coarse_transform: ``(B, 4, 4)`` ``T_coarse^-1``: source -> target, from the pose head.
        fine_transform: ``(B, 4, 4)`` ``T_fine^-1``: after the differentiable ICP.
        quaternion: ``(B, 4)`` unit quaternion (w, x, y, z) of the coarse rotation.
        translation: ``(B, 3)`` coarse translation.
        icp: :class:`ICPResult` (per-iteration history, rmse, aligned ICP points).
    """

    completion: CompletionOutput
    coarse_transform: Tensor
    fine_transform: Tensor
    quaternion: Tensor
    translation: Tensor
    icp: ICPResult


class ComRegNet(nn.Module):
    """Completion + registration network.

    Args:
        config: :class:`ModelConfig` (e.g. ``model_preset("cpu")``).
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        self.completion = AdaPoinTr(config.completion)
        c = config.completion
        feature_dim = c.decoder_dim if config.pose.features == "decoded" else c.encoder_dim
        self.pose_head = PoseHead(feature_dim, config.pose)

    def _start(self) -> int | None:
        return None if self.training else 0

    def _check_cloud(self, points: Tensor, name: str) -> None:
        check_points(points, name)
        need = max(self.completion.min_points, 3)
        if points.shape[1] < need:
            raise InvalidGeometryError(
                f"The {name} cloud has {points.shape[1]} points; the network needs at least "
                f"{need}.", "Use a denser bone surface (more points) or a smaller model preset.")

    def _tokens(self, out: CompletionOutput) -> tuple[Tensor, Tensor]:
        if self.config.pose.features == "decoded":
            return out.decoded, out.centres
        return out.encoded, out.proxies

    def encode_target(self, target: Tensor) -> TargetEncoding:
        """Run the target half: ``f(T)`` up to the decoded features, and its ICP subset.

        Args:
            target: ``(Bt, M, 3)`` CT clouds (normalised).

        Returns:
            :class:`TargetEncoding`.
        """
        self._check_cloud(target, "target")
        net_in = subsample(target, self.config.completion.input_points, self._start())
        tokens, positions = self._tokens(self.completion(net_in, rebuild=False))
        icp_points = subsample(target, self.config.icp.num_points, self._start())
        return TargetEncoding(tokens, positions, icp_points)

    def forward(self, source: Tensor, target: Tensor | TargetEncoding) -> ComRegOutput:
        """Complete the source and register it to the target.

        Args:
            source: ``(B, N, 3)`` partial US clouds ``S^t`` (normalised with the CT's centre and
                scale). Clouds above ``completion.input_points`` are reduced by FPS for ``f``;
                ICP uses an FPS subset of ``icp.num_points``.
            target: ``(B | 1, M, 3)`` CT clouds ``T``, or a :class:`TargetEncoding`.

        Returns:
            :class:`ComRegOutput`.
        """
        self._check_cloud(source, "source")
        cfg = self.config
        B = source.shape[0]
        start = self._start()
        src_in = subsample(source, cfg.completion.input_points, start)  # B n 3
        if isinstance(target, TargetEncoding):
            encoding = target
            completion = self.completion(src_in)
        else:
            self._check_cloud(target, "target")
            if target.shape[0] not in (1, B):
                raise ValueError(f"target batch {target.shape[0]} must be 1 or {B}")
            tgt_in = subsample(target, cfg.completion.input_points, start)  # Bt n' 3
            if tgt_in.shape[0] == B and tgt_in.shape[1] == src_in.shape[1]:
                # One pass of f over source and target clouds together (per-sample maths).
                both = self.completion(torch.cat([src_in, tgt_in]), rebuild=False)
                src_part = CompletionOutput(*(None if x is None else x[:B] for x in both))
                tgt_part = CompletionOutput(*(None if x is None else x[B:] for x in both))
                dense = self.completion.rebuild_head(src_part.decoded, src_part.centres)
                completion = src_part._replace(dense=dense)
                tokens, positions = self._tokens(tgt_part)
            else:
                completion = self.completion(src_in)
                tokens, positions = self._tokens(self.completion(tgt_in, rebuild=False))
            encoding = TargetEncoding(tokens, positions,
                                      subsample(target, cfg.icp.num_points, start))
        src_tokens, src_positions = self._tokens(completion)
        coarse, quaternion, translation = self.pose_head(src_tokens, src_positions,
                                                         encoding.tokens, encoding.positions)
        icp_source = subsample(source, cfg.icp.num_points, start)  # B N_c 3
        icp = differentiable_icp(icp_source, encoding.icp_points, coarse,
                                 iterations=cfg.icp.iterations, sigma=cfg.icp.sigma,
                                 neighbors=cfg.icp.neighbors, mode=cfg.icp.mode,
                                 trim_fraction=cfg.icp.trim_fraction)
        return ComRegOutput(completion, coarse, icp.transform, quaternion, translation, icp)
