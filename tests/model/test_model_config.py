"""Model presets and config validation; the normalised-coordinate helper."""

import numpy as np
from dataclasses import replace

import pytest

from comreg_core.config import ConfigError, load_config, write_config
from comreg_core.errors import InvalidGeometryError
from comreg_core.model.config import ModelConfig
from comreg_core.training.config import model_preset
from comreg_core.model.normalization import Normalization
from comreg_core.transforms import apply_transform
from tests.helpers import assert_close, random_rigid


def test_paper_preset_holds_the_paper_numbers():
    cfg = model_preset("paper")
    assert cfg == ModelConfig()
    c = cfg.completion
    assert (c.input_points, c.dense_points) == (20000, 20000)
    assert (c.encoder_dim, c.encoder_depth, c.decoder_dim, c.decoder_depth) == (384, 6, 384, 8)
    assert (c.num_heads, c.graph_k, c.center_num, c.global_feature_dim) == (6, 8, (512, 256), 1024)
    assert (cfg.pose.hidden_dim, cfg.pose.num_blocks, cfg.pose.features) == (512, 5, "decoded")
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
    # the loss is the paper's but for rho (the registration term's share) and the global pose term
    assert cpu.loss.rho == 1.0 and cpu.loss.lambda_global == 1.0 and paper.loss.lambda_global == 0
    assert replace(cpu.loss, rho=paper.loss.rho, lambda_global=0.0) == paper.loss
    assert cpu.pose.moments and not paper.pose.moments
    assert (paper.input_frame, paper.pose.head, paper.pose.rotation) == ("ct", "mlp",
                                                                         "quaternion")
    assert (cpu.input_frame, cpu.pose.head, cpu.pose.correspondence) == ("ct", "correspondence",
                                                                         "rotated")


def test_overrides_yaml_round_trip_and_errors(tmp_path):
    cfg = model_preset("cpu", {"icp": {"mode": "hard"}, "pose": {"features": "encoded"}})
    assert cfg.icp.mode == "hard" and cfg.pose.features == "encoded"
    path = write_config(cfg, tmp_path / "model.yaml")
    assert load_config(ModelConfig, path) == cfg
    with pytest.raises(ConfigError, match="Unknown model preset"):
        model_preset("gpu")
    with pytest.raises(ConfigError, match="num_heads"):
        model_preset("paper", {"completion": {"encoder_dim": 100}})
    with pytest.raises(ConfigError, match="trim_fraction"):
        model_preset("paper", {"icp": {"trim_fraction": 1.0}})
    with pytest.raises(ConfigError, match="Unknown config key"):
        model_preset("paper", {"icp": {"simga": 1.0}})
    with pytest.raises(ConfigError):
        model_preset("paper", {"pose": {"features": "raw"}})


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
