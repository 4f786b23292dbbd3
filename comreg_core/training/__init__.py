"""Per-patient pretraining: simulated training data, the trainer, checkpoints.

``pretrain(ct_mesh, run_dir, preset="cpu")`` trains ComReg on simulated sweeps of one CT and
writes a run folder (``config.yaml``, ``ct_fingerprint.json``, ``checkpoint.pt``,
``training_log.csv``); :class:`comreg_core.register.Registrar` loads it.
"""

from comreg_core.training.checkpoint import (CheckpointError, ct_fingerprint, export_model,
                                             load_checkpoint,
                                             mesh_fingerprint, run_ct_mesh)
from comreg_core.training.config import (PRESETS, DataConfig, PretrainConfig,
                                         TrainingConfig, model_preset,
                                         pretrain_preset)
from comreg_core.training.data import (SampleStream, TrainingCT, make_sample, sample_loader,
                                       validation_rng, validation_samples)
from comreg_core.training.bookkeeping import LOG_COLUMNS
from comreg_core.training.trainer import TrainResult, pretrain, resolve_device

__all__ = [
    "CheckpointError", "ct_fingerprint", "export_model", "load_checkpoint", "mesh_fingerprint", "run_ct_mesh",
    "PRESETS", "DataConfig", "PretrainConfig", "TrainingConfig", "model_preset", "pretrain_preset",
    "SampleStream", "TrainingCT", "make_sample", "sample_loader", "validation_rng",
    "validation_samples", "LOG_COLUMNS", "TrainResult", "pretrain", "resolve_device",
]
