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

:func:`pretrain` checks everything before it writes, then runs the loop (:mod:`.loop`, its
bookkeeping in :mod:`.bookkeeping`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from comreg_core import runs
from comreg_core.config import ConfigError, deep_merge, from_dict, to_dict
from comreg_core.errors import ComRegError
from comreg_core.io._files import atomic_output, check_output_folder, require_input_file
from comreg_core.io.meshes import SurfaceMesh, read_mesh
from comreg_core.progress import Progress
from comreg_core.training.bookkeeping import LOG_COLUMNS
from comreg_core.training.checkpoint import (CheckpointError, check_fingerprint,
                                             load_checkpoint, mesh_fingerprint,
                                             write_fingerprint)
from comreg_core.training.config import (PretrainConfig, config_from_yaml, config_to_yaml,
                                         load_overrides, pretrain_preset)
from comreg_core.training.data import TrainingCT
from comreg_core.training.distributed import World, peer_failures_reported, start, stop
from comreg_core.training.loop import TrainingLoop

log = logging.getLogger(__name__)

__all__ = ["LOG_COLUMNS", "BudgetTooShortError", "TrainResult", "pretrain", "resolve_device"]


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
    resume, seed = _check_run_folder(run_dir, world, resume, seed)
    mesh = read_mesh(ct_mesh_path)
    fingerprint = mesh_fingerprint(mesh)
    cfg, state = _prepare_config(ct_mesh_path, run_dir, preset, config, seed, resume)
    if state is not None:
        check_fingerprint(state["ct_fingerprint"], fingerprint, f" in '{run_dir}'")
    # the simulator's checks of the mesh (closed, millimetres, a volume) before any file is made
    ct = TrainingCT.from_mesh(mesh.vertices, mesh.faces, cfg.data.ct_points, cfg.seed)
    cfg = _with_invocation(cfg, epochs, max_minutes, device)
    world.check_batch(cfg.training.batch_size)
    dev = world.device(resolve_device(cfg.training.device))
    try:
        with peer_failures_reported():
            start(world, dev)  # every process has passed the checks before rank 0 writes
            return _train(cfg, state, ct, mesh, fingerprint, run_dir, world, dev, command_start,
                          progress)
    finally:
        stop(world)


def _check_run_folder(run_dir: Path, world: World, resume: bool, seed: int | None
                      ) -> tuple[bool, int | None]:
    """``(resume, seed)``: a process that torchrun restarted resumes its run; a folder holding
    another command's output is refused."""
    if world.restart and not resume and (run_dir / runs.CHECKPOINT).is_file():
        log.info("torchrun restart %d: resuming '%s' from its checkpoint", world.restart, run_dir)
        return True, None  # the restarted job continues its own run
    if (not resume and (run_dir / runs.CONFIG).exists()
            and not (run_dir / runs.CHECKPOINT).exists()):
        raise ComRegError(f"'{run_dir}' already holds a {runs.CONFIG} but no {runs.CHECKPOINT} "
                          "(another command's output, or a run stopped before its first "
                          "checkpoint).", "Choose an empty --out folder, so nothing is "
                          "overwritten.")
    return resume, seed


def _prepare_config(ct_mesh: Path, run_dir: Path, preset: str, config, seed, resume: bool
                    ) -> tuple[PretrainConfig, dict | None]:
    """The run's config and, when resuming, its checkpoint: a new run's preset with the
    overrides and seed, or a resumed run's own config (the seed, if given, must match)."""
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


def _with_invocation(cfg: PretrainConfig, epochs: int | None, max_minutes: float | None,
                     device: str | None) -> PretrainConfig:
    """``cfg`` with this invocation's epochs, time budget and device, where given."""
    overrides: dict[str, Any] = {}
    if epochs is not None:
        overrides["epochs"] = int(epochs)
    if max_minutes is not None:
        overrides["max_minutes"] = float(max_minutes)
    if device is not None:
        overrides["device"] = device
    return replace(cfg, training=from_dict(type(cfg.training), deep_merge(
        to_dict(cfg.training), overrides), "training"))


def _train(cfg: PretrainConfig, state: dict | None, ct: TrainingCT, mesh: SurfaceMesh,
           fingerprint: dict, run_dir: Path, world: World, dev: torch.device,
           command_start: float, progress: Progress | None) -> TrainResult:
    """The training of :func:`pretrain` on this process, after its checks: the run folder, the
    set-up, epoch 0 (a new run), the epochs, the last checkpoint."""
    if world.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
        with atomic_output(run_dir / runs.CONFIG) as tmp:
            tmp.write_text(config_to_yaml(cfg), encoding="utf-8")
        write_fingerprint(fingerprint, run_dir)
    loop = TrainingLoop(cfg, state, ct, mesh, fingerprint, run_dir, world, dev, command_start)
    if state is None:
        loop.validate_untrained()
    stopped = loop.epochs(progress)
    loop.checkpoint()
    return _result(loop, stopped)


def _result(loop: TrainingLoop, stopped: str) -> TrainResult:
    """What the run did; a budget that ended before the first epoch raises
    :class:`BudgetTooShortError`."""
    tally, clock = loop.tally, loop.clock
    log.info("Training stopped (%s) after %d epochs, %d samples, %.1f min", stopped,
             tally.epoch, tally.samples_seen, clock.elapsed() / 60)
    result = TrainResult(loop.run_dir, loop.ckpt_path, loop.run_dir / runs.TRAINING_LOG,
                         tally.epoch, tally.samples_seen, clock.elapsed(), stopped,
                         str(loop.dev), tally.losses, tally.validation, loop.initial,
                         loop.world.rank, loop.world.size)
    if tally.epoch == 0:
        raise BudgetTooShortError(
            f"The time budget ended before the first epoch ({tally.step} of "
            f"{loop.steps_per_epoch} steps done in {clock.since_command() / 60:.1f} min): "
            f"'{loop.ckpt_path}' holds a network that has not learned.",
            "Give more minutes (--max-minutes), or continue this run with --resume.", result)
    return result


class BudgetTooShortError(ComRegError):
    """:func:`pretrain` stopped by its time budget before completing one epoch. ``result`` is
    the :class:`TrainResult` (the run folder is valid and can be resumed)."""

    def __init__(self, message: str, hint: str, result: TrainResult):
        super().__init__(message, hint)
        self.result = result
