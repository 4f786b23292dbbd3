"""Per-patient pretraining of the ComReg network on simulated sweeps of one CT.

``pretrain(ct_mesh, run_dir)`` writes into ``run_dir``:

* ``config.yaml``: the :class:`~comreg_core.training.config.PretrainConfig` (seed included);
  ``pretrain_preset(...)`` + this file reproduce the run.
* ``ct_fingerprint.json``: sha256 of the mesh's vertices, faces and bounding box (+ sizes, bbox).
* ``checkpoint.pt``: the latest checkpoint (:mod:`.checkpoint`), written atomically at the end
  of every ``training.checkpoint_epochs`` epochs, at least every ``training.checkpoint_minutes``
  minutes (also mid-epoch), and when the run stops. A killed run resumed with ``resume=True``
  continues from it (same data stream, optimiser and scheduler state; every step seeds its own
  random numbers) and loses at most one checkpoint interval.
* ``training_log.csv``: one row per epoch (:data:`LOG_COLUMNS`): losses (epoch means), learning
  rates, times, the number of processes, and validation errors on the fixed held-out set when
  validated. Row ``epoch 0`` is the untrained network's validation.

Started by ``torchrun``, every process runs this function on its own device and its part of each
global batch (:mod:`.distributed`); rank 0 alone writes the files above, validates and reports
progress. The others wait for it at the next step.

Validation: ``training.validation_sweeps`` held-out samples (their own seed namespace, see
:mod:`.data`) after every ``training.validation_every`` epochs (:mod:`.validation`).

Progress (:class:`~comreg_core.progress.Progress`): ``progress(done, total, note)`` after every
step, ``done``/``total`` in steps over all epochs, ``note`` like ``"epoch 3, loss 0.412"`` (with
the last validation's median RTE/RRE once there is one).
"""

from __future__ import annotations

import csv
import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from comreg_core.progress import Progress
from comreg_core import runs
from comreg_core.config import ConfigError, deep_merge, from_dict, to_dict
from comreg_core.errors import ComRegError
from comreg_core.io._files import atomic_output, check_output_folder, require_input_file
from comreg_core.model.comreg import ComRegNet
from comreg_core.registration.geometry.surface import CTSurface
from comreg_core.training.checkpoint import (CheckpointError,
                                             check_fingerprint, load_checkpoint,
                                             mesh_fingerprint, save_checkpoint,
                                             write_fingerprint)
from comreg_core.training.config import (PretrainConfig, config_from_yaml, config_to_yaml,
                                         load_overrides, pretrain_preset)
from comreg_core.training.data import SampleStream, TrainingCT, sample_loader, validation_samples
from comreg_core.training.distributed import (World, peer_failures_reported, start, stop,
                                              wrap_model)
from comreg_core.training.step import LOSS_TERMS, train_step
from comreg_core.training.validation import identity_errors, validate

log = logging.getLogger(__name__)

#: Columns of ``training_log.csv`` (losses are epoch means; ``val_*`` empty when not validated).
LOG_COLUMNS = (
    "epoch", "samples", "world_size", "time_s", "epoch_s", "lr_backbone", "lr_head", "loss",
    "completion", "sparse", "dense", "registration", "reg_coarse", "reg_fine", "correspondence",
    "skipped_steps", "val_RTE_mm_median", "val_RRE_deg_median", "val_RTE_mm_mean", "val_RRE_deg_mean",
    "val_coarse_RTE_mm_median", "val_coarse_RRE_deg_median", "val_coarse_improved_share",
    "val_success_rate", "val_flip_rate", "val_loss", "val_completion",
    "val_completion_CD_mm_median", "val_s",
)

@dataclass
class TrainResult:
    """What :func:`pretrain` did.

    Attributes:
        run_dir, checkpoint, log_csv: the run folder, its checkpoint and epoch log.
        epochs: completed epochs (in total, over all resumed invocations).
        samples_seen: training samples consumed in total.
        elapsed_s: training time in total (all invocations).
        stopped: ``"epochs"`` (all epochs done) or ``"time"`` (budget spent).
        device: the torch device used (this process's).
        rank, world_size: this process and the number of processes (1 for a plain run).
        losses: epoch-mean losses of the last completed epoch (empty if none).
        validation: the last validation (``val_*`` keys of :data:`LOG_COLUMNS`), or None.
        initial_error: validation-set errors of doing nothing (identity): median RTE/RRE.
    """

    run_dir: Path
    checkpoint: Path
    log_csv: Path
    epochs: int
    samples_seen: int
    elapsed_s: float
    stopped: str
    device: str
    losses: dict[str, float] = field(default_factory=dict)
    validation: dict[str, float] | None = None
    initial_error: dict[str, float] = field(default_factory=dict)
    rank: int = 0
    world_size: int = 1


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``"auto"``/None -> CUDA if available else CPU; ``"cuda"`` without CUDA is an error."""
    if isinstance(device, torch.device):
        return device
    name = (device or "auto").lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigError("CUDA was requested but no CUDA device is available.",
                              "Use --device cpu or --device auto.")
        return torch.device(name)
    if name == "cpu":
        return torch.device("cpu")
    raise ConfigError(f"Unknown device '{device}'.", "Use auto, cpu or cuda.")


def build_optimizers(model: ComRegNet, training) -> tuple[list, list]:
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


def _fmt(value) -> str:
    if value is None or value == "":
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


class _EpochLog:
    """``training_log.csv``, appended one row per epoch and flushed."""

    def __init__(self, path: Path, keep_until_epoch: int | None, enabled: bool = True):
        self.path, self.enabled = path, enabled
        if not enabled:  # a process other than rank 0: writes nothing
            return
        rows: list[dict] = []
        if keep_until_epoch is not None and path.is_file():
            with path.open(newline="", encoding="utf-8") as f:
                rows = [r for r in csv.DictReader(f) if int(r["epoch"]) <= keep_until_epoch]
        with atomic_output(path) as tmp:
            with tmp.open("w", newline="", encoding="utf-8") as f:
                writer = csv.DictWriter(f, LOG_COLUMNS)
                writer.writeheader()
                writer.writerows(rows)

    def write(self, row: dict[str, Any]) -> None:
        if not self.enabled:
            return
        with self.path.open("a", newline="", encoding="utf-8") as f:
            csv.DictWriter(f, LOG_COLUMNS).writerow({k: _fmt(row.get(k)) for k in LOG_COLUMNS})


def _prepare_config(ct_mesh: Path, run_dir: Path, preset: str, config, seed, resume: bool
                    ) -> tuple[PretrainConfig, dict | None]:
    ckpt_path = run_dir / runs.CHECKPOINT
    if resume:
        if not ckpt_path.is_file():
            raise CheckpointError(f"Cannot resume: '{run_dir}' holds no {runs.CHECKPOINT}.",
                                  "Start a new run without --resume, or pass the folder of an "
                                  "interrupted run.")
        state = load_checkpoint(ckpt_path)
        if "optimizer_backbone" not in state:
            raise CheckpointError(f"'{ckpt_path}' is an exported model (weights only); it cannot "
                                  "be resumed.", "Resume the original run folder, or start a "
                                  "new run.")
        cfg = config_from_yaml(state["config_yaml"], f"config stored in '{ckpt_path}'")
        if seed is not None and seed != cfg.seed:
            raise ConfigError(f"The run was started with seed {cfg.seed}, not {seed}.",
                              "Leave --seed out when resuming (or pass the same seed).")
        return cfg, state
    if ckpt_path.exists():
        raise CheckpointError(f"'{run_dir}' already holds a training run ({runs.CHECKPOINT}).",
                              "Pass --resume to continue it, or choose an empty --out folder.")
    overrides = load_overrides(config)
    extra: dict[str, Any] = {"ct_mesh": str(ct_mesh)}
    if seed is not None:
        extra["seed"] = int(seed)
    return pretrain_preset(preset, deep_merge(overrides, extra)), None


def pretrain(ct_mesh_path: str | Path, run_dir: str | Path, *, preset: str = "paper",
             config: dict | str | Path | None = None, max_minutes: float | None = None,
             epochs: int | None = None, resume: bool = False, seed: int | None = None,
             device: str | None = None, progress: Progress | None = None) -> TrainResult:
    """Pretrain ComReg for one CT on simulated sweeps; see the module docstring.

    Args:
        ct_mesh_path: the CT bone mesh (mm), closed surface.
        run_dir: output folder (created); must not hold a run unless ``resume``.
        preset: ``"paper"`` or ``"cpu"`` (ignored when resuming: the run's config is used).
        config: nested overrides of the preset (dict or YAML file with sections ``model``,
            ``simulation``, ``data``, ``training``).
        max_minutes: time budget of this invocation (overrides ``training.max_minutes``).
        epochs: total epochs (overrides ``training.epochs``; when resuming, may extend the run).
        resume: continue the run in ``run_dir`` from its checkpoint (implied for a process that
            torchrun restarted, when the folder holds a checkpoint).
        seed: run seed (default 0; when resuming it must match the run's).
        device: ``"auto"``, ``"cpu"`` or ``"cuda"`` (overrides ``training.device``).
        progress: ``progress(done_steps, total_steps, note)`` callback.

    Raises:
        InputFileNotFoundError, CorruptFileError, InvalidGeometryError: unusable CT mesh.
        ConfigError: invalid settings. CheckpointError: resume problems, CT mismatch on resume.
        DistributedError: under torchrun, a batch that does not split over the processes, too
            few GPUs, or a process of the job lost (:class:`~.distributed.JobStoppedError`).
    """
    command_start = time.monotonic()  # the budget covers the whole call, set-up included
    world = World.from_environment()
    ct_mesh_path = require_input_file(ct_mesh_path, "CT mesh file")
    # --- set-up checks: everything is validated before the run folder is made or touched ---
    run_dir = check_output_folder(run_dir, inputs=[ct_mesh_path, config], what="run folder",
                                  run_folder_ok=True)
    if world.restart and not resume and (run_dir / runs.CHECKPOINT).is_file():
        log.info("torchrun restart %d: resuming '%s' from its checkpoint", world.restart, run_dir)
        resume, seed = True, None  # the restarted job continues its own run
    if (not resume and (run_dir / runs.CONFIG).exists()
            and not (run_dir / runs.CHECKPOINT).exists()):
        raise ComRegError(f"'{run_dir}' already holds a {runs.CONFIG} but no {runs.CHECKPOINT} "
                          "(another command's output, or a run stopped before its first "
                          "checkpoint).", "Choose an empty --out folder, so nothing is "
                          "overwritten.")
    from comreg_core.io.meshes import read_mesh

    mesh = read_mesh(ct_mesh_path)
    fingerprint = mesh_fingerprint(mesh)
    cfg, state = _prepare_config(ct_mesh_path, run_dir, preset, config, seed, resume)
    if state is not None:
        check_fingerprint(state["ct_fingerprint"], fingerprint, f" in '{run_dir}'")
    # the simulator's checks of the mesh (closed, millimetres, a volume) before any file is made
    ct = TrainingCT.from_mesh(mesh.vertices, mesh.faces, cfg.data.ct_points, cfg.seed)
    training_overrides: dict[str, Any] = {"world_size": world.size}
    if epochs is not None:
        training_overrides["epochs"] = int(epochs)
    if max_minutes is not None:
        training_overrides["max_minutes"] = float(max_minutes)
    if device is not None:
        training_overrides["device"] = device
    cfg = replace(cfg, training=from_dict(type(cfg.training), deep_merge(
        to_dict(cfg.training), training_overrides), "training"))
    tc = cfg.training
    world.check_batch(tc.batch_size)
    dev = world.device(resolve_device(tc.device))
    try:
        with peer_failures_reported():
            start(world, dev)  # every process has passed the checks before rank 0 writes
            return _train(cfg, state, ct, mesh, fingerprint, run_dir, world, dev, command_start,
                          progress)
    finally:
        stop(world)


def _train(cfg: PretrainConfig, state: dict | None, ct: TrainingCT, mesh, fingerprint: dict,
           run_dir: Path, world: World, dev: torch.device, command_start: float,
           progress: Progress | None) -> TrainResult:
    """The training loop of :func:`pretrain` (after its checks), on this process."""
    tc = cfg.training
    if world.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
        with atomic_output(run_dir / runs.CONFIG) as tmp:
            tmp.write_text(config_to_yaml(cfg), encoding="utf-8")
        write_fingerprint(fingerprint, run_dir)

    torch.manual_seed(cfg.seed)
    norm = ct.normalization
    net = ComRegNet(cfg.model).to(dev)
    net.train()
    optimizers, schedulers = build_optimizers(net, tc)
    epoch = step = samples_seen = 0
    elapsed = 0.0
    sums: dict[str, float] = {}
    if state is not None:
        net.load_state_dict(state["model"])
        for opt, key in zip(optimizers, ("optimizer_backbone", "optimizer_head")):
            opt.load_state_dict(state[key])
        for sch, key in zip(schedulers, ("scheduler_backbone", "scheduler_head")):
            sch.load_state_dict(state[key])
        epoch, step = int(state["epoch"]), int(state["step"])
        samples_seen, elapsed = int(state["samples_seen"]), float(state["elapsed_s"])
        sums = {k: float(v) for k, v in state["epoch_sums"].items()}
        ct.points = state["ct_points"].numpy()  # the run's own cloud, bit for bit
        log.info("Resuming '%s' at epoch %d, step %d (%d samples, %.1f min; %d processes, "
                 "before %s)", run_dir, epoch, step, samples_seen, elapsed / 60, world.size,
                 state.get("world_size", 1))
    model = wrap_model(net, world, dev)  # what the training step calls (DDP when launched)
    ct_points_n = torch.from_numpy(norm.points_to_model(ct.points)).float().to(dev)  # M 3

    steps_per_epoch = tc.samples_per_epoch // tc.batch_size
    total_steps = tc.epochs * steps_per_epoch
    validating = bool(tc.validation_every) and world.is_main  # rank 0 validates, alone
    val_set = validation_samples(ct, cfg.simulation, cfg.data.pose, cfg.seed,
                                 tc.validation_sweeps) if validating else []
    initial = identity_errors(val_set, norm) if val_set else {}
    surface = CTSurface((ct.vertices, ct.faces)) if val_set else None
    if initial:
        log.info("Validation set: %d sweeps, initial misalignment median RTE %.1f mm, RRE "
                 "%.1f deg", len(val_set), initial["RTE_mm_median"], initial["RRE_deg_median"])
    epoch_log = _EpochLog(run_dir / runs.TRAINING_LOG, epoch if state is not None else None,
                          enabled=world.is_main)
    ckpt_path = run_dir / runs.CHECKPOINT

    def checkpoint() -> None:
        if not world.is_main:
            return
        mark = time.monotonic()
        payload = {
            "config_yaml": config_to_yaml(cfg), "ct_fingerprint": fingerprint["sha256"],
            "ct_space": mesh.space,
            "ct_vertices": torch.from_numpy(np.asarray(mesh.vertices, dtype=np.float64)),
            "ct_faces": torch.from_numpy(np.asarray(mesh.faces, dtype=np.int64)),
            "ct_points": torch.from_numpy(np.asarray(ct.points, dtype=np.float64)),
            "norm_center": torch.from_numpy(np.asarray(norm.center, dtype=np.float64)),
            "norm_scale": float(norm.scale), "model": net.state_dict(),
            "optimizer_backbone": optimizers[0].state_dict(),
            "optimizer_head": optimizers[1].state_dict(),
            "scheduler_backbone": schedulers[0].state_dict(),
            "scheduler_head": schedulers[1].state_dict(),
            "epoch": epoch, "step": step, "samples_seen": samples_seen,
            "elapsed_s": elapsed_now(), "epoch_sums": dict(sums), "world_size": world.size,
        }
        if last_validation is not None:
            payload["validation"] = {k: float(v) for k, v in last_validation.items()}
            payload["validation_epoch"] = int(last_validation_epoch)
            payload["initial_error"] = {k: float(v) for k, v in initial.items()}
        save_checkpoint(payload, ckpt_path)
        cost["checkpoint"] = time.monotonic() - mark
        log.debug("Checkpoint at epoch %d step %d", epoch, step)

    t0 = time.monotonic()

    def elapsed_now() -> float:
        return elapsed + (time.monotonic() - t0)

    budget_s = tc.max_minutes * 60.0 if tc.max_minutes > 0 else math.inf
    cost = {"step": 0.0, "validation": 0.0, "checkpoint": 0.0}  # latest durations, seconds

    def out_of_time(ends_epoch: bool) -> bool:
        """Whether the next step (and the validation and checkpoint it may trigger) would end
        after the budget: rank 0's clock decides for every process."""
        left = budget_s - (time.monotonic() - command_start)
        need = cost["step"] + cost["checkpoint"] + (cost["validation"] if ends_epoch else 0.0)
        return world.main_decides(world.is_main and left < need, dev)
    last_validation: dict[str, float] | None = None
    last_validation_epoch = 0
    if state is not None and "validation" in state:
        last_validation = {k: float(v) for k, v in state["validation"].items()}
        last_validation_epoch = int(state["validation_epoch"])
    last_losses: dict[str, float] = {}
    if state is None:
        row: dict[str, Any] = {"epoch": 0, "samples": 0, "world_size": world.size,
                               "time_s": 0.0, "lr_backbone": tc.lr_backbone,
                               "lr_head": tc.lr_head}
        if val_set:
            mark = time.monotonic()
            last_validation = validate(net, ct_points_n, val_set, norm, loss=cfg.model.loss,
                                       surface=surface)
            cost["validation"] = time.monotonic() - mark
            row.update(last_validation)
        epoch_log.write(row)
        checkpoint()

    stopped = "epochs"
    last_ckpt = time.monotonic()
    epoch_start = time.monotonic()
    loader = batches = None
    if epoch < tc.epochs:
        stream = SampleStream(ct, cfg.simulation, cfg.data.pose, cfg.seed, tc.batch_size,
                              start=samples_seen, rank=world.rank, processes=world.size)
        workers = cfg.data.workers if cfg.data.workers is not None else int(dev.type == "cuda")
        loader = sample_loader(stream, workers, cfg.data.prefetch_batches,
                               pin_memory=dev.type == "cuda")
        batches = iter(loader)
    try:
        while epoch < tc.epochs:
            if out_of_time(step + 1 == steps_per_epoch):
                stopped = "time"
                break
            step_start = time.monotonic()
            losses, applied = train_step(model, next(batches), ct_points_n, cfg, optimizers,
                                          world, dev)
            if applied:
                for name in LOSS_TERMS:
                    sums[name] = sums.get(name, 0.0) + losses[name]
                sums["steps"] = sums.get("steps", 0.0) + 1
            else:
                log.warning("Non-finite loss at epoch %d step %d; step skipped", epoch, step)
                sums["skipped"] = sums.get("skipped", 0.0) + 1
            for sch in schedulers:
                sch.step()
            cost["step"] = time.monotonic() - step_start
            step += 1
            samples_seen += tc.batch_size
            info: dict[str, Any] = {"epoch": epoch + 1, "loss": losses["total"],
                                    "completion": losses["completion"],
                                    "registration": losses["registration"]}
            if step == steps_per_epoch:
                epoch += 1
                step = 0
                lrs = [s.get_last_lr()[0] for s in schedulers]
                n = max(sums.get("steps", 0.0), 1.0)
                last_losses = {k: sums.get(k, 0.0) / n for k in LOSS_TERMS}
                row = {"epoch": epoch, "samples": samples_seen, "world_size": world.size,
                       "time_s": elapsed_now(),
                       "epoch_s": time.monotonic() - epoch_start, "lr_backbone": lrs[0],
                       "lr_head": lrs[1], "loss": last_losses["total"],
                       **{k: last_losses[k] for k in LOSS_TERMS[1:]},
                       "skipped_steps": int(sums.get("skipped", 0))}
                if val_set and epoch % tc.validation_every == 0:
                    mark = time.monotonic()
                    last_validation = validate(net, ct_points_n, val_set, norm,
                                               loss=cfg.model.loss, surface=surface)
                    cost["validation"] = time.monotonic() - mark
                    last_validation_epoch = epoch
                    row.update(last_validation)
                    info["val_RTE_mm"] = last_validation["val_RTE_mm_median"]
                    info["val_RRE_deg"] = last_validation["val_RRE_deg_median"]
                epoch_log.write(row)
                if world.is_main:
                    log.info("epoch %d: loss %.4f (completion %.4f, registration %.4f)%s",
                             epoch, last_losses["total"], last_losses["completion"],
                             last_losses["registration"],
                             "" if "val_RTE_mm" not in info else
                             f"; validation median RTE {info['val_RTE_mm']:.2f} mm, RRE "
                             f"{info['val_RRE_deg']:.2f} deg")
                sums = {}
                epoch_start = time.monotonic()
                if epoch % tc.checkpoint_epochs == 0 or epoch == tc.epochs:
                    checkpoint()
                    last_ckpt = time.monotonic()
            if time.monotonic() - last_ckpt >= tc.checkpoint_minutes * 60.0:
                checkpoint()  # rank 0 alone: the state it saves is the same on every process
                last_ckpt = time.monotonic()
            if progress is not None and world.is_main:
                progress(epoch * steps_per_epoch + step, total_steps, _progress_note(info))
    finally:
        batches = loader = None  # shuts the data workers down
    checkpoint()
    log.info("Training stopped (%s) after %d epochs, %d samples, %.1f min", stopped, epoch,
             samples_seen, elapsed_now() / 60)
    result = TrainResult(run_dir, ckpt_path, run_dir / runs.TRAINING_LOG, epoch, samples_seen,
                         elapsed_now(), stopped, str(dev), last_losses, last_validation, initial,
                         world.rank, world.size)
    if epoch == 0:
        raise BudgetTooShortError(
            f"The time budget ended before the first epoch ({step} of {steps_per_epoch} steps "
            f"done in {(time.monotonic() - command_start) / 60:.1f} min): '{ckpt_path}' holds "
            f"a network that has not learned.",
            "Give more minutes (--max-minutes), or continue this run with --resume.", result)
    return result


class BudgetTooShortError(ComRegError):
    """:func:`pretrain` stopped by its time budget before completing one epoch. ``result`` is
    the :class:`TrainResult` (the run folder is valid and can be resumed)."""

    def __init__(self, message: str, hint: str, result: TrainResult):
        super().__init__(message, hint)
        self.result = result


def _progress_note(info: dict[str, Any]) -> str:
    """The progress note of a step: epoch, loss, and the last validation's medians."""
    note = f"epoch {info.get('epoch', '?')}"
    if "loss" in info:
        note += f", loss {info['loss']:.3g}"
    if "val_RTE_mm" in info:
        note += f", validation {info['val_RTE_mm']:.1f} mm / {info['val_RRE_deg']:.1f} deg"
    return note
