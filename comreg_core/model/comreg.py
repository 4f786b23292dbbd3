"""The ComReg network: completion ``f`` + coarse pose ``g`` + differentiable ICP, end to end.

``ComRegNet(config)(source, target)`` takes the (transformed, partial) US cloud ``S^t`` and the CT
cloud ``T``, both in the CT's normalised coordinates (:mod:`comreg_core.model.normalization`),
and returns the completion of ``S^t``, the coarse transform ``T_coarse^-1`` (source -> target)
predicted from ``H(S^t) (+) H(T)``, and its ICP refinement ``T_fine^-1``.

With ``input_frame: centroid`` the source is shifted so the centroid of its network input is at
0 before ``f`` and ``g`` (``principal``: also turned onto its principal axes; ``azimuth``:
turned about the CT's long axis until that centroid lies at azimuth 0); the completion
and the coarse transform are mapped back, so every output is in the same frame as with
``input_frame: ct``.

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


def invert_frame(frame: Tensor) -> Tensor:
    """Inverse of rigid ``(B, 4, 4)`` transforms: ``[R^T | -R^T t]``."""
    R_t = frame[:, :3, :3].transpose(1, 2)
    inverse = torch.zeros_like(frame)
    inverse[:, :3, :3] = R_t
    inverse[:, :3, 3] = -(R_t @ frame[:, :3, 3:]).squeeze(-1)
    inverse[:, 3, 3] = 1
    return inverse


class TargetEncoding(NamedTuple):
    """The target (CT) half of the network.

    Attributes:
        tokens: ``(Bt, T, C)`` pose-head tokens (H, or V in the "encoded" ablation).
        positions: ``(Bt, T, 3)`` their positions (query centres, or proxies).
        icp_points: ``(Bt, N_c, 3)`` the ICP subset of the target cloud.
        axes: ``(3, 3)`` the CT's principal axes (rows, largest spread first; ``input_frame:
            azimuth``), None otherwise.
    """

    tokens: Tensor
    positions: Tensor
    icp_points: Tensor
    axes: Tensor | None = None


def principal_axes(cloud: Tensor) -> Tensor:
    """``(3, 3)`` principal axes (rows, largest spread first, right-handed) of an ``(M, 3)``
    cloud, each axis' largest component made positive, so the same cloud (or a subset of it)
    always gives the same signs. No gradient."""
    x = cloud.detach().double()
    x = x - x.mean(dim=0)
    _, vectors = torch.linalg.eigh(x.T @ x)  # ascending
    axes = vectors.flip(-1).T  # 3 3
    pick = axes.abs().argmax(dim=1)
    axes = axes * torch.sign(axes[torch.arange(3), pick]).unsqueeze(1)
    axes[2] = torch.cross(axes[0], axes[1], dim=0)
    return axes


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
        c = config.completion
        feature_dim = c.decoder_dim if config.pose.features == "decoded" else c.encoder_dim
        self.pose_head = build_pose_head(feature_dim, config.pose,
                                         2 if config.input_frame == "azimuth" else 0)

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

    def _input_frame(self, src_in: Tensor, ct_axes: Tensor | None = None
                     ) -> tuple[Tensor, Tensor | None]:
        """``(B, 4, 4)`` the rigid map ``F`` applied to the source before ``f`` and ``g``
        (``model.input_frame``): identity (``ct``), the shift of the input's centroid to 0
        (``centroid``), that shift followed by the rotation onto the input's principal axes
        (``principal``: largest spread first, each axis pointed where the cloud's third moment
        along it is positive, right-handed), or the turn about the CT's long axis
        ``ct_axes[0]`` (through the CT's centre, the origin) that brings the input's centroid
        to azimuth 0, measured from ``ct_axes[1]`` (``azimuth``); and the pose head's context:
        ``(B, 2)`` the azimuth's cosine and sine (``azimuth``), else None. No gradient flows
        through ``F``."""
        B = src_in.shape[0]
        F = torch.eye(4, dtype=src_in.dtype, device=src_in.device).repeat(B, 1, 1)
        if self.config.input_frame == "ct":
            return F, None
        if self.config.input_frame == "azimuth":
            return self._azimuth_frame(src_in, ct_axes)
        x = src_in.detach().double()
        centre = x.mean(dim=1, keepdim=True)  # B 1 3
        R = torch.eye(3, dtype=x.dtype, device=x.device).repeat(B, 1, 1)
        if self.config.input_frame == "principal":
            centred = x - centre
            _, vectors = torch.linalg.eigh(centred.transpose(1, 2) @ centred)  # ascending
            axes = vectors.flip(-1).transpose(1, 2)  # B 3 3, rows: axes, largest spread first
            skew = ((centred @ axes.transpose(1, 2)) ** 3).mean(dim=1)  # B 3
            axes = axes * torch.where(skew < 0, -1.0, 1.0).unsqueeze(-1)
            axes[:, 2] = torch.cross(axes[:, 0], axes[:, 1], dim=-1)  # right-handed
            R = axes
        F[:, :3, :3] = R.to(F.dtype)
        F[:, :3, 3] = -(R @ centre.transpose(1, 2)).squeeze(-1).to(F.dtype)
        return F, None

    @staticmethod
    def _azimuth_frame(src_in: Tensor, ct_axes: Tensor | None) -> tuple[Tensor, Tensor]:
        """``input_frame: azimuth`` (see :meth:`_input_frame`)."""
        if ct_axes is None:
            raise ValueError("input_frame 'azimuth' needs the CT's axes (TargetEncoding.axes)")
        axes = ct_axes.to(src_in.device).double()  # 3 3
        centre = src_in.detach().double().mean(dim=1)  # B 3
        psi = torch.atan2(centre @ axes[2], centre @ axes[1])  # B
        c, s = torch.cos(psi), torch.sin(psi)
        # In the axes' basis the turn by -psi about axis 0 is [[1,0,0],[0,c,s],[0,-s,c]].
        turn = torch.zeros(len(psi), 3, 3, dtype=axes.dtype, device=axes.device)
        turn[:, 0, 0] = 1
        turn[:, 1, 1] = turn[:, 2, 2] = c
        turn[:, 1, 2], turn[:, 2, 1] = s, -s
        R = axes.T @ turn @ axes  # B 3 3
        F = torch.eye(4, dtype=src_in.dtype, device=src_in.device).repeat(len(psi), 1, 1)
        F[:, :3, :3] = R.to(F.dtype)
        return F, torch.stack([c, s], dim=-1).to(src_in.dtype)

    def _coarse(self, completion: CompletionOutput, frame: Tensor,
                encoding: TargetEncoding, context: Tensor | None) -> PoseOutput:
        """The pose head on a completion made in the input frame, composed with the frame:
        ``T = T' F``; correspondence positions moved back to the source frame."""
        tokens, positions = self._tokens(completion)
        extra = {} if context is None else {"context": context}
        pose = self.pose_head(tokens, positions, encoding.tokens, encoding.positions, **extra)
        transform = pose.transform @ frame  # B 4 4
        corr = pose.correspondences
        if corr is not None:
            corr = corr._replace(positions=transform_points(invert_frame(frame),
                                                            corr.positions))
            if corr.global_transform is not None:
                corr = corr._replace(global_transform=corr.global_transform @ frame)
        return PoseOutput(transform, matrix_to_quaternion(transform[:, :3, :3].detach()),
                          transform[:, :3, 3], corr)

    @staticmethod
    def _unframe(completion: CompletionOutput, frame: Tensor) -> CompletionOutput:
        """The completion's points moved from the input frame back to the source frame."""
        back = invert_frame(frame)
        return completion._replace(
            centres=transform_points(back, completion.centres),
            proxies=transform_points(back, completion.proxies),
            dense=None if completion.dense is None else transform_points(back, completion.dense))

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
        frame, context = self._input_frame(src_in, target.axes)  # B 4 4
        completion = self.completion(transform_points(frame, src_in))
        pose = self._coarse(completion, frame, target, context)
        return self._unframe(completion, frame), pose

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
        return TargetEncoding(tokens, positions, icp_points, self._ct_axes(target))

    def _ct_axes(self, target: Tensor) -> Tensor | None:
        """The CT's :func:`principal_axes` (from ``target[0]``, ``(Bt, M, 3)``) where the input
        frame needs them, else None."""
        return principal_axes(target[0]) if self.config.input_frame == "azimuth" else None

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
            ct_axes = self._ct_axes(target)
            frame, context = self._input_frame(src_in, ct_axes)  # B 4 4
            src_in = transform_points(frame, src_in)
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
                                      subsample(target, cfg.icp.num_points, start), ct_axes)
            pose = self._coarse(completion, frame, encoding, context)
            completion = self._unframe(completion, frame)
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
                                  neighbors=icp.neighbors, mode=icp.mode,
                                  trim_fraction=icp.trim_fraction)
