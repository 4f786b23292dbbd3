"""Model presets and config validation; the normalised-coordinate helper."""

import numpy as np
from dataclasses import replace

import pytest

from comreg_core.config import ConfigError, load_config, write_config
from comreg_core.errors import InvalidGeometryError
from comreg_core.model.config import ModelConfig
from comreg_core.training.config import model_preset
from comreg_core.normalization import Normalization
from comreg_core.transforms import apply_transform
from tests.helpers import assert_close, random_rigid


def test_paper_preset_holds_the_paper_numbers():
    cfg = model_preset("paper")
    assert cfg == ModelConfig()
    c = cfg.completion
    assert (c.input_points, c.dense_points) == (20000, 20000)
    assert (c.encoder_dim, c.encoder_depth, c.decoder_dim, c.decoder_depth) == (384, 6, 384, 8)
    assert (c.num_heads, c.graph_k, c.center_num, c.global_feature_dim) == (6, 8, (512, 256), 1024)
    assert (cfg.pose.hidden_dim, cfg.pose.num_blocks, cfg.pose.head) == (512, 5, "mlp")
    assert (cfg.icp.iterations, cfg.icp.num_points, cfg.icp.sigma) == (25, 4096, 5e-3)
    assert not cfg.icp.mesh_refine  # the paper's pipeline ends with its differentiable ICP
    assert (cfg.loss.lambda_coarse, cfg.loss.lambda_fine, cfg.loss.rho) == (1.0, 0.5, 0.1)


def test_cpu_preset_is_smaller_and_keeps_the_method_constants():
    cpu, paper = model_preset("cpu"), model_preset("paper")
    assert cpu.completion.input_points < paper.completion.input_points
    assert cpu.completion.encoder_dim < paper.completion.encoder_dim
    assert cpu.icp.sigma == paper.icp.sigma and cpu.icp.iterations == paper.icp.iterations
    assert cpu.icp.mesh_refine
    assert cpu.pose.hidden_dim == 512 and cpu.pose.num_blocks == 5
    # the loss is the paper's but for rho (the registration term's share)
    assert cpu.loss.rho == 1.0 and replace(cpu.loss, rho=paper.loss.rho) == paper.loss
    assert (paper.pose.head, cpu.pose.head) == ("mlp", "correspondence")


def test_overrides_yaml_round_trip_and_errors(tmp_path):
    cfg = model_preset("cpu", {"icp": {"sigma": 0.01}, "pose": {"head": "mlp"}})
    assert cfg.icp.sigma == 0.01 and cfg.pose.head == "mlp"
    path = write_config(cfg, tmp_path / "model.yaml")
    assert load_config(ModelConfig, path) == cfg
    with pytest.raises(ConfigError, match="Unknown model preset"):
        model_preset("gpu")
    with pytest.raises(ConfigError, match="num_heads"):
        model_preset("paper", {"completion": {"encoder_dim": 100}})
    with pytest.raises(ConfigError, match="sigma"):
        model_preset("paper", {"icp": {"sigma": 0.0}})
    with pytest.raises(ConfigError, match="Unknown config key"):
        model_preset("paper", {"icp": {"simga": 1.0}})
    with pytest.raises(ConfigError):
        model_preset("paper", {"pose": {"head": "raw"}})


def test_normalization_round_trips_points_and_transforms():
    rng = np.random.default_rng(0)
    ct = rng.uniform([-10, 0, 100], [30, 400, 140], size=(500, 3))
    norm = Normalization.from_ct(ct)
    model = norm.points_to_model(ct)
    assert_close(model.min(0) + model.max(0), np.zeros(3), atol=1e-12)
    assert abs((model.max(0) - model.min(0)).max() - 1.0) < 1e-12
    assert_close(norm.points_to_mm(model), ct, atol=1e-9)
    T_mm = random_rigid(rng, 100.0)
    T_model = norm.transform_to_model(T_mm)
    assert_close(norm.transform_to_mm(T_model), T_mm, atol=1e-9)
    assert_close(apply_transform(T_model, model),
                 norm.points_to_model(apply_transform(T_mm, ct)), atol=1e-12)
    assert_close(norm.matrix() @ np.append(ct[0], 1.0), np.append(model[0], 1.0), atol=1e-12)
    with pytest.raises(InvalidGeometryError):
        Normalization.from_ct(np.ones((5, 3)))


def test_removed_options_in_old_configs_load_when_they_hold_what_survived():
    """Old run folders and checkpoints carry the keys of removed options: the values that
    survived load (and give today's config); a removed value is a clear ConfigError."""
    from comreg_core.training.checkpoint import load_checkpoint
    from comreg_core.training.config import config_from_yaml, pretrain_preset
    from pathlib import Path

    old_cpu = {"input_frame": "ct", "pose": {"head": "correspondence", "correspondence": "rotated",
                                             "moments": True, "rotation": "quaternion",
                                             "features": "decoded"},
               "loss": {"lambda_global": 1.0}, "icp": {"mode": "soft", "trim_fraction": 0.0}}
    assert model_preset("cpu", old_cpu) == model_preset("cpu")
    old_paper = {"pose": {"correspondence": "regress", "moments": False}, "loss": {
        "lambda_global": 0.0}}
    assert model_preset("paper", old_paper) == model_preset("paper")
    for removed in ({"input_frame": "azimuth"}, {"pose": {"rotation": "6d"}},
                    {"pose": {"features": "encoded"}},
                    {"pose": {"head": "correspondence", "correspondence": "match"}},
                    {"icp": {"mode": "hard"}}, {"loss": {"lambda_global": 0.5}}):
        with pytest.raises(ConfigError, match="has been removed"):
            model_preset("cpu", removed)
    with pytest.raises(ConfigError, match="training.grad_clip"):
        pretrain_preset("cpu", {"training": {"grad_clip": 1.0}})
    # the sample's shipped model was written before the removal and its weights still fit
    from comreg_core.model import ComRegNet

    sample = Path(__file__).parents[2] / "resources" / "sample" / "fibula_cpu.pt"
    state = load_checkpoint(sample)
    assert "mode: soft" in state["config_yaml"] and "features: decoded" in state["config_yaml"]
    ComRegNet(config_from_yaml(state["config_yaml"]).model).load_state_dict(state["model"])
