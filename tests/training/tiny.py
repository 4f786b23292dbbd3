"""A tiny pretraining configuration for fast tests (about a second per step on 2 busy CPU cores),
and one shared tiny run (trained once per test session)."""

from __future__ import annotations

from pathlib import Path

TINY = {
    "model": {
        "completion": {"input_points": 256, "center_num": [64, 32], "dgcnn_k": 8,
                       "encoder_dim": 48, "encoder_depth": 1, "decoder_dim": 48,
                       "decoder_depth": 1, "num_heads": 3, "graph_k": 8,
                       "global_feature_dim": 128, "mlp_hidden": 128, "num_query": 32,
                       "fold_grid": [2, 4], "fold_hidden": 32},
        "pose": {"token_dim": 64, "hidden_dim": 64, "num_blocks": 2, "norm_groups": 8},
        "icp": {"num_points": 256, "iterations": 5, "neighbors": 8},
    },
    "simulation": {"n_points": 256},
    "data": {"ct_points": 512, "workers": 1, "prefetch_batches": 2},
    "training": {"samples_per_epoch": 16, "batch_size": 4, "validation_sweeps": 4,
                 "lr_backbone": 1e-3, "lr_head": 1e-3, "warmup_steps": 2},
}

#: Epochs of the shared tiny run.
TINY_EPOCHS = 4

_RUNS: dict[str, object] = {}


def tiny_run(tmp_path_factory):
    """The shared tiny run on the fibula: ``(TrainResult, run_dir)`` (trained on first use)."""
    if "run" not in _RUNS:
        from comreg_core.training import pretrain
        from tests.helpers import FIBULA_STL

        run_dir = Path(tmp_path_factory.mktemp("tiny_run")) / "run"
        result = pretrain(FIBULA_STL, run_dir, preset="cpu", config=TINY, epochs=TINY_EPOCHS,
                          seed=0, device="cpu")
        _RUNS["run"] = (result, run_dir)
    return _RUNS["run"]
