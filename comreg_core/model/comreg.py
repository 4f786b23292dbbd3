"""The ComReg network: completion ``f`` + coarse pose ``g`` + differentiable ICP, end to end.

``ComRegNet(config)(source, target)`` takes the (transformed, partial) US cloud ``S^t`` and the CT
cloud ``T``, both in the CT's normalised coordinates (:mod:`comreg_core.normalization`),
and returns the completion of ``S^t``, the coarse transform ``T_coarse^-1`` (source -> target)
predicted from ``H(S^t) (+) H(T)``, and its ICP refinement ``T_fine^-1``.

``encode_target`` runs the target half once (e.g. at inference, where the CT is fixed); its
result can be passed as ``target``. In training the CT goes through ``f`` every step (with
gradients), as in the paper; pass it with batch 1 to run it once per step for the whole batch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor, nn

from comreg_core.errors import InvalidGeometryError
from comreg_core.model.adapointr import AdaPoinTr, CompletionOutput
from comreg_core.model.config import ModelConfig
from comreg_core.model.diff_icp import ICPResult, differentiable_icp
from comreg_core.model.ops import (check_points, matrix_to_quaternion, subsample,
                                   transform_points)
from comreg_core.model.pose_head import Correspondences, PoseOutput, build_pose_head


class TargetEncoding(NamedTuple):
    """The target (CT) half of the network.

    Attributes:
        tokens: ``(Bt, Q, D)`` pose-head tokens: the decoded query features H.
        positions: ``(Bt, Q, 3)`` their positions, the query centres.
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
        correspondences: the correspondence head's :class:`Correspondences` (positions in the
            source frame), or None for the MLP head.
    """

    completion: CompletionOutput
    coarse_transform: Tensor
    fine_transform: Tensor
    quaternion: Tensor
    translation: Tensor
    icp: ICPResult
    correspondences: Correspondences | None = None


class ComRegNet(nn.Module):
    """Completion + registration network.

    Args:
        config: :class:`ModelConfig` (e.g.
                :func:`comreg_core.training.config.model_preset` ``("cpu")``).
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        self.completion = AdaPoinTr(config.completion)
        self.pose_head = build_pose_head(config.completion.decoder_dim, config.pose)

    def _start(self) -> int | None:
        return None if self.training else 0

    def _check_cloud(self, points: Tensor, name: str) -> None:
        check_points(points, name)
        need = max(self.completion.min_points, 3)
        if points.shape[1] < need:
            raise InvalidGeometryError(
                f"The {name} cloud has {points.shape[1]} points; the network needs at least "
                f"{need}.", "Use a denser bone surface (more points) or a smaller model preset.")

    def _coarse(self, completion: CompletionOutput, encoding: TargetEncoding) -> PoseOutput:
        """The pose head on a completion against the encoded target (quaternion taken from the
        transform's rotation, for both heads)."""
        pose = self.pose_head(completion.decoded, completion.centres, encoding.tokens,
                              encoding.positions)
        return pose._replace(quaternion=matrix_to_quaternion(pose.transform[:, :3, :3].detach()))

    def coarse_pose(self, source: Tensor, target: TargetEncoding
                    ) -> tuple[CompletionOutput, PoseOutput]:
        """Completion and coarse pose of sources against an encoded target (no ICP).

        Args:
            source: ``(B, N, 3)`` partial US clouds (normalised).
            target: :meth:`encode_target` of the CT.

        Returns:
            the completion (source frame) and the :class:`PoseOutput` (source -> target).
        """
        self._check_cloud(source, "source")
        src_in = subsample(source, self.config.completion.input_points, self._start())
        completion = self.completion(src_in)
        return completion, self._coarse(completion, target)

    def encode_target(self, target: Tensor) -> TargetEncoding:
        """Run the target half: ``f(T)`` up to the decoded features, and its ICP subset.

        Args:
            target: ``(Bt, M, 3)`` CT clouds (normalised).

        Returns:
            :class:`TargetEncoding`.
        """
        self._check_cloud(target, "target")
        net_in = subsample(target, self.config.completion.input_points, self._start())
        encoded = self.completion(net_in, rebuild=False)
        icp_points = subsample(target, self.config.icp.num_points, self._start())
        return TargetEncoding(encoded.decoded, encoded.centres, icp_points)

    def forward(self, source: Tensor, target: Tensor | TargetEncoding,
                refine_only: Callable[[Tensor], Tensor] | None = None) -> ComRegOutput:
        """Complete the source and register it to the target.

        Args:
            source: ``(B, N, 3)`` partial US clouds ``S^t`` (normalised with the CT's centre and
                scale). Clouds above ``completion.input_points`` are reduced by FPS for ``f``;
                ICP uses an FPS subset of ``icp.num_points``.
            target: ``(B | 1, M, 3)`` CT clouds ``T``, or a :class:`TargetEncoding`.
            refine_only: optional ``coarse (B, 4, 4) -> (B,) bool``: ICP runs only on the
                samples it selects; the others' fine transform is their coarse one. Training
                passes the fine-loss gate (:func:`~comreg_core.model.losses.in_fine_gate`):
                outside it the fine term is 0 whatever ICP returns, so the result and the
                gradients are the same, for less work.

        Returns:
            :class:`ComRegOutput`.
        """
        self._check_cloud(source, "source")
        cfg = self.config
        B = source.shape[0]
        start = self._start()
        if isinstance(target, TargetEncoding):  # inference: the CT half is encoded once
            encoding = target
            completion, pose = self.coarse_pose(source, encoding)
        else:  # training: one pass of f over source and target clouds together
            src_in = subsample(source, cfg.completion.input_points, start)  # B n 3
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
            else:
                completion = self.completion(src_in)
                tgt_part = self.completion(tgt_in, rebuild=False)
            encoding = TargetEncoding(tgt_part.decoded, tgt_part.centres,
                                      subsample(target, cfg.icp.num_points, start))
            pose = self._coarse(completion, encoding)
        icp_source = subsample(source, cfg.icp.num_points, start)  # B N_c 3
        if refine_only is None:
            icp = self.refine(icp_source, encoding, pose.transform)
        else:
            icp = self._refine_some(icp_source, encoding, pose.transform, refine_only)
        return ComRegOutput(completion, pose.transform, icp.transform, pose.quaternion,
                            pose.translation, icp, pose.correspondences)

    def _refine_some(self, icp_source: Tensor, target: TargetEncoding, coarse: Tensor,
                     select: Callable[[Tensor], Tensor]) -> ICPResult:
        """:meth:`refine` on the samples ``select(coarse)`` picks; the rest keep ``coarse``
        (history: ``coarse`` repeated, rmse NaN, aligned points: the coarse-moved source)."""
        chosen = select(coarse.detach())  # B
        idx = chosen.nonzero().squeeze(1)
        part = None
        if len(idx):
            tgt = target if target.icp_points.shape[0] == 1 else target._replace(
                icp_points=target.icp_points[idx])
            part = self.refine(icp_source[idx], tgt, coarse[idx])
        B = coarse.shape[0]
        K = self.config.icp.iterations if part is None else part.transform_history.shape[1]
        transform = coarse.clone()
        aligned = transform_points(coarse, icp_source)
        rmse = coarse.new_full((B,), float("nan"))
        history = coarse.unsqueeze(1).expand(B, K, 4, 4).clone()
        rmse_history = coarse.new_full((B, K), float("nan"))
        converged = torch.zeros(B, dtype=torch.bool, device=coarse.device)
        if part is not None:
            transform = transform.index_put((idx,), part.transform)
            aligned = aligned.index_put((idx,), part.aligned)
            rmse = rmse.index_put((idx,), part.rmse.to(rmse.dtype))
            history = history.index_put((idx,), part.transform_history)
            rmse_history = rmse_history.index_put((idx,), part.rmse_history.to(rmse.dtype))
            converged = converged.index_put((idx,), part.converged)
        return ICPResult(transform, aligned, rmse, history, rmse_history, converged)

    def refine(self, icp_source: Tensor, target: TargetEncoding, coarse: Tensor) -> ICPResult:
        """The differentiable ICP from ``coarse`` ``(B, 4, 4)``: ``icp_source`` ``(B, N_c, 3)``
        onto the target's ICP subset, with this model's ICP settings."""
        icp = self.config.icp
        return differentiable_icp(icp_source, target.icp_points, coarse,
                                  iterations=icp.iterations, sigma=icp.sigma,
                                  neighbors=icp.neighbors)
