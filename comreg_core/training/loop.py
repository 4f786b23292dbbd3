"""The training loop of one process, in named steps.

:class:`TrainingLoop` sets up (network, optimisers, a resumed run's state, the held-out set, the
bookkeeping of :mod:`.bookkeeping`); :meth:`~TrainingLoop.validate_untrained` writes epoch 0;
:meth:`~TrainingLoop.epochs` runs steps until the last epoch or the time budget ends, closing
each epoch with its log row, its validation and its checkpoint when due. Rank 0 alone validates
and writes; every process steps.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from comreg_core import runs
from comreg_core.io.meshes import SurfaceMesh
from comreg_core.model.comreg import ComRegNet
from comreg_core.progress import Progress
from comreg_core.registration.geometry.surface import CTSurface
from comreg_core.training.bookkeeping import Clock, EpochLog, Tally, progress_note
from comreg_core.training.checkpoint import save_checkpoint
from comreg_core.training.config import PretrainConfig, config_to_yaml
from comreg_core.training.data import SampleStream, TrainingCT, sample_loader, validation_samples
from comreg_core.training.distributed import World, wrap_model
from comreg_core.training.step import LOSS_TERMS, build_optimizers, train_step
from comreg_core.training.validation import identity_errors, validate

log = logging.getLogger(__name__)


class TrainingLoop:
    """One process's training: the network, its optimisers, the data, the validation set, the
    bookkeeping (:mod:`.bookkeeping`); set up from a checkpoint's ``state`` when resuming."""

    def __init__(self, cfg: PretrainConfig, state: dict | None, ct: TrainingCT,
                 mesh: SurfaceMesh, fingerprint: dict, run_dir: Path, world: World,
                 dev: torch.device, command_start: float):
        """Set up from scratch (``state`` None) or from a checkpoint's ``state``; ``mesh`` is the
        CT mesh as read (mm), ``command_start`` the ``time.monotonic()`` the budget counts from."""
        self.cfg, self.ct, self.mesh, self.fingerprint = cfg, ct, mesh, fingerprint
        self.run_dir, self.world, self.dev = run_dir, world, dev
        tc = cfg.training
        torch.manual_seed(cfg.seed)
        self.norm = ct.normalization
        self.net = ComRegNet(cfg.model).to(dev)
        self.net.train()
        self.optimizers, self.schedulers = build_optimizers(self.net, tc)
        self.tally = Tally() if state is None else self._resume(state)
        self.model = wrap_model(self.net, world, dev)  # what the step calls (DDP when launched)
        self.ct_points_n = torch.from_numpy(
            self.norm.points_to_model(ct.points)).float().to(dev)  # M 3
        self.steps_per_epoch = tc.samples_per_epoch // tc.batch_size
        validating = bool(tc.validation_every) and world.is_main  # rank 0 validates, alone
        self.val_set = validation_samples(ct, cfg.simulation, cfg.data.pose, cfg.seed,
                                          tc.validation_sweeps) if validating else []
        self.initial = identity_errors(self.val_set, self.norm) if self.val_set else {}
        self.surface = CTSurface((ct.vertices, ct.faces)) if self.val_set else None
        if self.initial:
            log.info("Validation set: %d sweeps, initial misalignment median RTE %.1f mm, RRE "
                     "%.1f deg", len(self.val_set), self.initial["RTE_mm_median"],
                     self.initial["RRE_deg_median"])
        self.epoch_log = EpochLog(run_dir / runs.TRAINING_LOG,
                                  None if state is None else self.tally.epoch,
                                  enabled=world.is_main)
        self.ckpt_path = run_dir / runs.CHECKPOINT
        self.clock = Clock(command_start, tc.max_minutes, self.tally.elapsed_s)

    def _resume(self, state: dict) -> Tally:
        """Load the checkpoint's weights, optimisers, schedulers and CT cloud; its tally."""
        self.net.load_state_dict(state["model"])
        for opt, key in zip(self.optimizers, ("optimizer_backbone", "optimizer_head")):
            opt.load_state_dict(state[key])
        for sch, key in zip(self.schedulers, ("scheduler_backbone", "scheduler_head")):
            sch.load_state_dict(state[key])
        tally = Tally.from_checkpoint(state)
        self.ct.points = state["ct_points"].numpy()  # the run's own cloud, bit for bit
        log.info("Resuming '%s' at epoch %d, step %d (%d samples, %.1f min; %d processes, "
                 "before %s)", self.run_dir, tally.epoch, tally.step, tally.samples_seen,
                 tally.elapsed_s / 60, self.world.size, state.get("world_size", 1))
        return tally

    def validate_untrained(self) -> None:
        """Row ``epoch 0`` of the log (the untrained network's validation), and a checkpoint."""
        tc = self.cfg.training
        row: dict[str, Any] = {"epoch": 0, "samples": 0, "world_size": self.world.size,
                               "time_s": 0.0, "lr_backbone": tc.lr_backbone,
                               "lr_head": tc.lr_head}
        if self.val_set:
            row.update(self._validate())
        self.epoch_log.write(row)
        self.checkpoint()

    def epochs(self, progress: Progress | None) -> str:
        """Steps until the last epoch ends (``"epochs"``) or the budget would be overrun
        (``"time"``); checkpoints at least every ``training.checkpoint_minutes``."""
        tc, tally, clock = self.cfg.training, self.tally, self.clock
        clock.start_epochs()
        if tally.epoch >= tc.epochs:
            return "epochs"
        loader = self._loader()
        batches = iter(loader)
        try:
            while tally.epoch < tc.epochs:
                if self._out_of_time(tally.step + 1 == self.steps_per_epoch):
                    return "time"
                with clock.timed("step"):
                    info = self._step(next(batches))
                if tally.step == self.steps_per_epoch:
                    self._end_epoch(info)
                if clock.checkpoint_due(tc.checkpoint_minutes):
                    self.checkpoint()  # rank 0 alone: the state it saves is the same everywhere
                    clock.checkpointed()
                if progress is not None and self.world.is_main:
                    progress(tally.epoch * self.steps_per_epoch + tally.step,
                             tc.epochs * self.steps_per_epoch, progress_note(info))
        finally:
            batches = loader = None  # shuts the data workers down
        return "epochs"

    def _loader(self):
        """The training samples from where the run is, this process's part of each batch."""
        cfg, world, dev = self.cfg, self.world, self.dev
        stream = SampleStream(self.ct, cfg.simulation, cfg.data.pose, cfg.seed,
                              cfg.training.batch_size, start=self.tally.samples_seen,
                              rank=world.rank, processes=world.size)
        workers = cfg.data.workers if cfg.data.workers is not None else int(dev.type == "cuda")
        return sample_loader(stream, workers, cfg.data.prefetch_batches,
                             pin_memory=dev.type == "cuda")

    def _out_of_time(self, ends_epoch: bool) -> bool:
        """Whether the next step would end after the budget: rank 0's clock decides for every
        process."""
        runs_out = self.clock.runs_out(ends_epoch)
        return self.world.main_decides(self.world.is_main and runs_out, self.dev)

    def _step(self, batch: dict[str, torch.Tensor]) -> dict[str, Any]:
        """One optimisation step on ``batch``, counted; its progress info."""
        tally = self.tally
        losses, applied = train_step(self.model, batch, self.ct_points_n, self.cfg,
                                     self.optimizers, self.world, self.dev)
        if not applied:
            log.warning("Non-finite loss at epoch %d step %d; step skipped", tally.epoch,
                        tally.step)
        tally.add_step(losses, applied, self.cfg.training.batch_size)
        for sch in self.schedulers:
            sch.step()
        return {"epoch": tally.epoch + 1, "loss": losses["total"],
                "completion": losses["completion"], "registration": losses["registration"]}

    def _end_epoch(self, info: dict[str, Any]) -> None:
        """The epoch's log row, with a validation when one is due; a checkpoint when due."""
        tc, tally, clock = self.cfg.training, self.tally, self.clock
        skipped = tally.close_epoch()
        lrs = [s.get_last_lr()[0] for s in self.schedulers]
        means = tally.losses
        row = {"epoch": tally.epoch, "samples": tally.samples_seen,
               "world_size": self.world.size, "time_s": clock.elapsed(),
               "epoch_s": clock.epoch_seconds(), "lr_backbone": lrs[0], "lr_head": lrs[1],
               "loss": means["total"], **{k: means[k] for k in LOSS_TERMS[1:]},
               "skipped_steps": skipped}
        if self.val_set and tally.epoch % tc.validation_every == 0:
            row.update(self._validate())
            info["val_RTE_mm"] = tally.validation["val_RTE_mm_median"]
            info["val_RRE_deg"] = tally.validation["val_RRE_deg_median"]
        self.epoch_log.write(row)
        if self.world.is_main:
            log.info("epoch %d: loss %.4f (completion %.4f, registration %.4f)%s", tally.epoch,
                     means["total"], means["completion"], means["registration"],
                     "" if "val_RTE_mm" not in info else
                     f"; validation median RTE {info['val_RTE_mm']:.2f} mm, RRE "
                     f"{info['val_RRE_deg']:.2f} deg")
        clock.start_epoch()
        if tally.epoch % tc.checkpoint_epochs == 0 or tally.epoch == tc.epochs:
            self.checkpoint()
            clock.checkpointed()

    def _validate(self) -> dict[str, float]:
        """The network's errors on the held-out sweeps, as the tally's last validation."""
        with self.clock.timed("validation"):
            figures = validate(self.net, self.ct_points_n, self.val_set, self.norm,
                               loss=self.cfg.model.loss, surface=self.surface)
        self.tally.validation, self.tally.validation_epoch = figures, self.tally.epoch
        return figures

    def checkpoint(self) -> None:
        """Write ``checkpoint.pt`` (rank 0 alone; :mod:`.checkpoint` lists its keys)."""
        if not self.world.is_main:
            return
        tally, opts, scheds = self.tally, self.optimizers, self.schedulers
        with self.clock.timed("checkpoint"):
            payload = {
                "config_yaml": config_to_yaml(self.cfg),
                "ct_fingerprint": self.fingerprint["sha256"], "ct_space": self.mesh.space,
                "ct_vertices": torch.from_numpy(np.asarray(self.mesh.vertices, dtype=np.float64)),
                "ct_faces": torch.from_numpy(np.asarray(self.mesh.faces, dtype=np.int64)),
                "ct_points": torch.from_numpy(np.asarray(self.ct.points, dtype=np.float64)),
                "norm_center": torch.from_numpy(np.asarray(self.norm.center, dtype=np.float64)),
                "norm_scale": float(self.norm.scale), "model": self.net.state_dict(),
                "optimizer_backbone": opts[0].state_dict(), "optimizer_head": opts[1].state_dict(),
                "scheduler_backbone": scheds[0].state_dict(),
                "scheduler_head": scheds[1].state_dict(),
                "epoch": tally.epoch, "step": tally.step, "samples_seen": tally.samples_seen,
                "elapsed_s": self.clock.elapsed(), "epoch_sums": dict(tally.sums),
                "world_size": self.world.size,
            }
            if tally.validation is not None:
                payload["validation"] = {k: float(v) for k, v in tally.validation.items()}
                payload["validation_epoch"] = int(tally.validation_epoch)
                payload["initial_error"] = {k: float(v) for k, v in self.initial.items()}
            save_checkpoint(payload, self.ckpt_path)
        log.debug("Checkpoint at epoch %d step %d", tally.epoch, tally.step)
