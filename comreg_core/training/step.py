"""One optimisation step of pretraining, the same in one process and in several (DDP).

:func:`train_step` seeds torch's generator for the step (:func:`~comreg_core.training.data.
step_torch_seed`), runs the network on this process's part of the global batch, averages the
loss terms over the processes (:meth:`~comreg_core.training.distributed.World.mean`), and
back-propagates the loss weighted as for the global batch. :func:`build_optimizers` makes the
optimisers it steps and their learning-rate schedules.
"""

from __future__ import annotations

import torch

from comreg_core.model.comreg import ComRegNet
from comreg_core.model.losses import balance_weight, in_fine_gate, output_loss
from comreg_core.training.config import PretrainConfig, TrainingConfig
from comreg_core.training.data import step_torch_seed
from comreg_core.training.distributed import World

#: The logged loss terms (batch means): ``total`` and the terms of
#: :class:`~comreg_core.model.losses.LossTerms` it is made of.
LOSS_TERMS = ("total", "completion", "sparse", "dense", "registration", "reg_coarse",
              "reg_fine", "correspondence")


def build_optimizers(model: ComRegNet, training: TrainingConfig) -> tuple[list, list]:
    """AdamW on the completion backbone, Adam on the registration head, each with a LambdaLR
    stepped after every training step: a linear warm-up over ``warmup_steps`` steps, then the
    learning rate multiplied by ``lr_decay`` every ``lr_decay_epochs`` epochs."""
    backbone = list(model.completion.parameters())
    head = list(model.pose_head.parameters())
    assert len(backbone) + len(head) == len(list(model.parameters())), "unassigned parameters"
    opt_b = torch.optim.AdamW(backbone, lr=training.lr_backbone,
                              weight_decay=training.weight_decay_backbone)
    opt_h = torch.optim.Adam(head, lr=training.lr_head)
    decay, warmup = training.lr_decay, training.warmup_steps
    every = training.lr_decay_epochs * (training.samples_per_epoch // training.batch_size)

    def factor(step: int) -> float:
        warm = min(1.0, (step + 1) / warmup) if warmup else 1.0
        return warm * decay ** (step // every)

    scheds = [torch.optim.lr_scheduler.LambdaLR(o, factor) for o in (opt_b, opt_h)]
    return [opt_b, opt_h], scheds


def train_step(model: torch.nn.Module, batch: dict[str, torch.Tensor], ct_points_n: torch.Tensor,
                cfg: PretrainConfig, optimizers: list, world: World, dev: torch.device
                ) -> tuple[dict[str, float], bool]:
    """One optimisation step on this process's part of the global batch.

    The loss terms are averaged over the processes before the backward pass: the adaptive
    weight of the registration term comes from the global batch's means (as in one process),
    and every process sees the same total, so all of them apply or all skip a non-finite step.
    Every process runs the backward pass (DDP averages the gradients in it).

    Returns:
        The loss terms of :data:`LOSS_TERMS`, means over the global batch, and whether the
        step was applied (False: a non-finite loss, weights left unchanged).
    """
    torch.manual_seed(step_torch_seed(cfg.seed, int(batch["index"][0])))
    source = batch["source"].to(dev, non_blocking=True)  # b N 3
    gt_points = batch["gt_points"].to(dev, non_blocking=True)  # b M 3
    gt_transform = batch["gt_transform"].to(dev, non_blocking=True)  # b 4 4
    for opt in optimizers:
        opt.zero_grad(set_to_none=True)
    loss_cfg = cfg.model.loss
    out = model(source, ct_points_n[None], refine_only=lambda coarse: in_fine_gate(
        coarse, gt_transform, loss_cfg))
    terms = output_loss(out, gt_points, gt_transform, loss_cfg)
    means = world.mean(torch.stack([getattr(terms, name) for name in LOSS_TERMS[1:]]))
    completion, registration = means[0], means[3]
    weight = balance_weight(completion, registration, loss_cfg)
    total = completion + weight * registration
    (terms.completion + weight * terms.registration).backward()
    applied = bool(torch.isfinite(means).all()) and bool(torch.isfinite(total))
    if applied:
        for opt in optimizers:
            opt.step()
    values = dict(zip(LOSS_TERMS[1:], means.tolist()))
    return {"total": float(total), **values}, applied
