"""Typed configuration of a pretraining run: model, simulation, data, training schedule.

A run is fully described by :class:`PretrainConfig` (written as ``RUN_DIR/config.yaml``): the
model (:class:`~comreg_core.model.ModelConfig`), the simulator
(:class:`~comreg_core.simulation.SimulationConfig`), how samples are drawn (:class:`DataConfig`),
the schedule (:class:`TrainingConfig`), the seed and the CT mesh path.

Presets (:func:`pretrain_preset`):

* ``paper``: the ComReg paper's implementation details: 20,000 points per cloud (US and CT),
  2048 samples per epoch, batch 4, 500 epochs, AdamW (lr 1e-4, weight decay 5e-4) on the
  completion backbone, Adam (lr 1e-4) on the registration head, both decayed x0.9 every 20 epochs
  (LambdaLR), rho = 0.1, lambda_coarse = 1, lambda_fine = 0.5.
* ``cpu``: the model's ``cpu`` preset (2048 input points) with 2048-point simulated sweeps, a
  4096-point CT cloud and 256 samples per epoch (64 steps of batch 4, about a minute on 2 cores)
  so that the epoch log shows progress within a 30-minute budget; outside training the ICP's
  pose is refined on the CT mesh (``model.icp.mesh_refine``). Everything else as ``paper``.

Ablations reachable from the config (paper, Table 3): ``model.loss.lambda_fine: 0``,
``simulation.mode: uniform`` (uniform surface sampling instead of simulated sweeps).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

from comreg_core.config import (ConfigError, RetiredCheck, deep_merge, from_dict,
                                parse_yaml_mapping, read_yaml_mapping, require, to_dict)
from comreg_core.model.config import ModelConfig
from comreg_core.simulation.config import SimulationConfig


@dataclass(frozen=True)
class DataConfig:
    """How training samples are drawn.

    Attributes:
        pose: initial-pose sampler, ``"paper"`` (one axis, +-90 deg, +-100 mm) or ``"full"``
            (any rotation up to 180 deg, translation up to 500 mm); see
            :func:`comreg_core.simulation.sample_initial_pose`. Rotations turn about the CT
            bounding-box centre.
        ct_points: points of the CT cloud ``T`` (area-uniform samples of the mesh, drawn once per
            run from the seed and stored in the checkpoint).
        workers: background processes generating samples (0 = in the training process; None =
            auto: 0 when training on the CPU, 1 on CUDA). Measured on 2 shared CPU cores with the
            ``cpu`` preset (25 steps of batch 4, median of two runs each): inline 0.636 s per
            step (0.075 s of it simulating), one worker 0.681 s: the worker hides the simulation
            but its CPU use slows the step more than it saves. On a GPU the CPU is otherwise
            idle, so a worker keeps the simulator off the critical path.
        prefetch_batches: batches each worker keeps ready.
    """

    pose: Literal["paper", "full"] = "paper"
    ct_points: int = 20_000
    workers: int | None = None
    prefetch_batches: int = 4

    def __post_init__(self) -> None:
        require(self.ct_points >= 16, "data.ct_points", "must be at least 16")
        require(self.workers is None or 0 <= self.workers <= 16, "data.workers",
                "must lie in [0, 16] (or be null for auto)")
        require(self.prefetch_batches >= 1, "data.prefetch_batches", "must be at least 1")


@dataclass(frozen=True)
class TrainingConfig:
    """The optimisation schedule (paper defaults).

    Attributes:
        epochs: epochs to train (a run stops earlier when its time budget is spent).
        samples_per_epoch: simulated samples per epoch (a multiple of ``batch_size``).
        batch_size: samples per step (the CT cloud goes through the network once per step).
        lr_backbone, weight_decay_backbone: AdamW on the completion network.
        lr_head: Adam on the registration head.
        lr_decay, lr_decay_epochs: both learning rates are multiplied by ``lr_decay`` every
            ``lr_decay_epochs`` epochs (LambdaLR, stepped after every training step).
        warmup_steps: the learning rates rise linearly from ``1 / warmup_steps`` of their value
            to it over the first ``warmup_steps`` steps (0 = none, the paper).
        validation_every: validate every this many epochs (0 = never).
        validation_sweeps: held-out simulated sweeps in the validation set.
        checkpoint_minutes: write a checkpoint at least this often (also mid-epoch).
        checkpoint_epochs: and at the end of every this many epochs.
        max_minutes: time budget of one invocation of ``pretrain`` (0 = none); the run stops
            after the step that crosses it and writes a checkpoint.
        device: ``"auto"`` (CUDA if available), ``"cpu"`` or ``"cuda"``.

    Under torchrun, ``batch_size`` is the global batch of a step, split evenly over the
    processes, and the learning rates are those of the global batch
    (:mod:`comreg_core.training.distributed`).
    """

    epochs: int = 500
    samples_per_epoch: int = 2048
    batch_size: int = 4
    lr_backbone: float = 1e-4
    weight_decay_backbone: float = 5e-4
    lr_head: float = 1e-4
    lr_decay: float = 0.9
    lr_decay_epochs: int = 20
    warmup_steps: int = 0
    validation_every: int = 1
    validation_sweeps: int = 32
    checkpoint_minutes: float = 5.0
    checkpoint_epochs: int = 1
    max_minutes: float = 0.0
    device: Literal["auto", "cpu", "cuda"] = "auto"

    #: removed options (docs/results.md): no clipping survived; the number of processes is
    #: torchrun's (checkpoints and the epoch log record it), whatever the file says
    RETIRED_KEYS: ClassVar[dict[str, RetiredCheck]] = {
        "grad_clip": lambda value, section: value == 0,
        "world_size": lambda value, section: True,
    }

    def __post_init__(self) -> None:
        require(self.epochs >= 1, "training.epochs", "must be at least 1")
        require(self.batch_size >= 1, "training.batch_size", "must be at least 1")
        require(self.samples_per_epoch >= self.batch_size
                and self.samples_per_epoch % self.batch_size == 0,
                "training.samples_per_epoch", "must be a positive multiple of batch_size")
        for name in ("lr_backbone", "lr_head"):
            require(getattr(self, name) > 0, f"training.{name}", "must be positive")
        require(self.weight_decay_backbone >= 0, "training.weight_decay_backbone",
                "must be 0 or more")
        require(0 < self.lr_decay <= 1, "training.lr_decay", "must lie in (0, 1]")
        require(self.lr_decay_epochs >= 1, "training.lr_decay_epochs", "must be at least 1")
        require(self.warmup_steps >= 0, "training.warmup_steps", "must be 0 or more")
        require(self.validation_every >= 0, "training.validation_every", "must be 0 or more")
        require(self.validation_sweeps >= 1, "training.validation_sweeps", "must be at least 1")
        require(self.checkpoint_minutes > 0, "training.checkpoint_minutes", "must be positive")
        require(self.checkpoint_epochs >= 1, "training.checkpoint_epochs", "must be at least 1")
        require(self.max_minutes >= 0, "training.max_minutes", "must be 0 (none) or more")


@dataclass(frozen=True)
class PretrainConfig:
    """Everything needed to reproduce a pretraining run (``RUN_DIR/config.yaml``).

    Attributes:
        ct_mesh: the CT bone mesh the run trains for (as given; informational, the fingerprint
            in ``ct_fingerprint.json`` identifies the CT).
        preset: the preset the run started from (``paper`` or ``cpu``).
        seed: training sweeps use ``sweep_rng(seed, i)``; the validation set and the CT cloud use
            their own spawn-key namespaces (see :mod:`comreg_core.training.data`).
    """

    ct_mesh: str = ""
    preset: str = "paper"
    seed: int = 0
    model: ModelConfig = field(default_factory=ModelConfig)
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    data: DataConfig = field(default_factory=DataConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)

    def __post_init__(self) -> None:
        require(self.seed >= 0, "seed", "must be a non-negative integer")
        require(self.preset in PRESETS, "preset", f"must be one of {', '.join(PRESETS)}")


#: The presets (names: :data:`comreg_core.choices.PRESETS`), as differences from the defaults
#: (which are the paper's values), one nested dict per preset with the sections of
#: :class:`PretrainConfig`.
#:
#: The ``cpu`` model was chosen by timing one training step (forward + backward + full loss,
#: batch 4, CT through ``f`` once per step) on 2 shared CPU cores, torch 2.13, 2 threads;
#: minimum of 5 runs: this preset 0.53 s (6.7 M parameters); the same with ICP on 4096 points 0.85 s, with 4096
#: input points 0.79 s, 256 queries 0.68 s, 32 ICP neighbours 0.72 s, a 256-wide depth-4
#: transformer 0.66 s, depth 2 0.53 s, a 128-wide depth-2 net on 1024 points 0.38 s; the
#: ``paper`` preset 8.2 s. ICP has no weights, so inference may use ``icp.num_points = 4096``
#: with a model trained at 2048 (inference at batch 1: 0.08 s with 2048, 0.15 s with 4096).
PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "cpu": {
        "model": {
            "completion": {
                "input_points": 2048,
                "center_num": [256, 128],
                "encoder_dim": 192,
                "encoder_depth": 3,
                "decoder_dim": 192,
                "decoder_depth": 3,
                "num_heads": 6,
                "global_feature_dim": 512,
                "mlp_hidden": 512,
                "num_query": 128,
                "fold_grid": [4, 4],
                "fold_hidden": 128,
            },
            # the correspondence head (trials W and GM in docs/results.md)
            "pose": {"token_dim": 256, "head": "correspondence"},
            "loss": {"rho": 1.0},
            "icp": {"num_points": 2048, "neighbors": 16, "mesh_refine": True},
        },
        "simulation": {"n_points": 2048},
        "data": {"ct_points": 4096},
        "training": {"samples_per_epoch": 256, "validation_sweeps": 24,
                     "checkpoint_minutes": 2.0, "lr_backbone": 5e-4, "lr_head": 5e-4,
                     "warmup_steps": 64, "lr_decay_epochs": 4},
    },
}


def model_preset(name: str = "paper", overrides: dict | None = None) -> ModelConfig:
    """The model section of the named preset, optionally updated by a nested dict."""
    if name not in PRESETS:
        raise ConfigError(f"Unknown model preset '{name}'.", f"Use one of: {', '.join(PRESETS)}.")
    return from_dict(ModelConfig, deep_merge(PRESETS[name].get("model", {}), overrides or {}),
                     "model")


def pretrain_preset(name: str = "paper", overrides: dict | None = None) -> PretrainConfig:
    """The named preset (``"paper"`` or ``"cpu"``), updated by a nested dict of overrides."""
    if name not in PRESETS:
        raise ConfigError(f"Unknown preset '{name}'.", f"Use one of: {', '.join(PRESETS)}.")
    base = deep_merge(PRESETS[name], {"preset": name})
    return from_dict(PretrainConfig, deep_merge(base, overrides or {}), "")


def config_to_yaml(config: PretrainConfig) -> str:
    import yaml

    return yaml.safe_dump(to_dict(config), sort_keys=False)


def config_from_yaml(text: str, where: str = "config") -> PretrainConfig:
    data = parse_yaml_mapping(text, f"The {where}")
    return from_dict(PretrainConfig, data, "")


def load_overrides(config: dict | str | Path | None) -> dict:
    """A nested override dict from a dict, a YAML file path, or None."""
    if config is None:
        return {}
    if isinstance(config, dict):
        return config
    return read_yaml_mapping(config)
