"""Training data: determinism, seed namespaces, ground-truth conventions, ablation switches."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from comreg_core.io.meshes import read_mesh
from comreg_core.simulation import BoneModel, SimulationConfig, sweep_rng
from comreg_core.training.data import (SampleStream, TrainingCT, make_sample, sample_loader,
                                       validation_samples)
from comreg_core.transforms import apply_transform, invert_rigid
from tests.helpers import FIBULA_STL, assert_close


@pytest.fixture(scope="module")
def ct():
    mesh = read_mesh(FIBULA_STL)
    return TrainingCT.from_mesh(mesh.vertices, mesh.faces, 512, seed=0)


SIM = SimulationConfig(n_points=256)


def _batches(loader, n):
    it = iter(loader)
    return [next(it) for _ in range(n)]


def test_ct_normalisation_is_the_mesh_bbox(ct):
    v = ct.vertices
    assert_close(ct.normalization.center, (v.min(0) + v.max(0)) / 2, atol=1e-9)
    assert ct.normalization.scale == pytest.approx(float((v.max(0) - v.min(0)).max()))
    again = TrainingCT.from_mesh(read_mesh(FIBULA_STL).vertices, read_mesh(FIBULA_STL).faces,
                                 512, seed=0)
    assert np.array_equal(again.points, ct.points)  # the CT cloud is fixed by the seed


def test_sample_ground_truth_conventions(ct):
    bone = BoneModel((ct.vertices, ct.faces))
    s = make_sample(bone, ct, SIM, "paper", sweep_rng(3, 0))
    norm = ct.normalization
    # gt_transform = T^-1 in normalised units maps T^t back onto the CT cloud
    back = apply_transform(s.gt_transform, s.gt_points)
    assert_close(back, norm.points_to_model(ct.points), atol=1e-9)
    # ... and the source onto the CT surface (the sweep lies on the bone, up to false hits)
    src_ct = norm.points_to_mm(apply_transform(s.gt_transform, s.source))
    d = bone.distance(src_ct)
    assert np.median(d) < 1e-6
    # gt_transform is the inverse of the sampled T_us_ct, expressed in normalised units
    assert_close(norm.transform_to_mm(s.gt_transform), invert_rigid(s.T_us_ct_mm), atol=1e-9)
    # the paper sampler rotates about the CT bbox centre: the centre moves along one axis only
    shift = apply_transform(s.T_us_ct_mm, norm.center[None])[0] - norm.center
    assert np.count_nonzero(np.abs(shift) > 1e-9) <= 1 and np.abs(shift).max() <= 100.0


def test_stream_is_deterministic_for_any_worker_count_and_start(ct):
    a = _batches(sample_loader(SampleStream(ct, SIM, "paper", 5, 2), workers=0), 3)
    b = _batches(sample_loader(SampleStream(ct, SIM, "paper", 5, 2), workers=2,
                               prefetch_batches=1), 3)
    c = _batches(sample_loader(SampleStream(ct, SIM, "paper", 5, 2, start=4), workers=1), 1)
    for x, y in zip(a, b):
        for key in x:
            assert torch.equal(x[key], y[key]), key
    for key in c[0]:
        assert torch.equal(a[2][key], c[0][key]), key
    assert a[0]["index"].tolist() == [0, 1] and c[0]["index"].tolist() == [4, 5]
    assert a[0]["source"].shape == (2, 256, 3) and a[0]["gt_points"].shape == (2, 512, 3)
    assert a[0]["source"].dtype == torch.float32 and a[0]["gt_transform"].shape == (2, 4, 4)


def test_validation_set_is_fixed_and_disjoint_from_training(ct):
    v1 = validation_samples(ct, SIM, "paper", 0, 3)
    v2 = validation_samples(ct, SIM, "paper", 0, 3)
    bone = BoneModel((ct.vertices, ct.faces))
    train = [make_sample(bone, ct, SIM, "paper", sweep_rng(0, i)) for i in range(3)]
    for a, b, t in zip(v1, v2, train):
        assert np.array_equal(a.source, b.source)
        assert not np.allclose(a.T_us_ct_mm, t.T_us_ct_mm)


def test_ablation_switches(ct):
    bone = BoneModel((ct.vertices, ct.faces))
    uniform = make_sample(bone, ct, SimulationConfig(n_points=256, mode="uniform"), "full",
                          sweep_rng(0, 0))
    assert uniform.source.shape == (256, 3)
    from comreg_core.training import pretrain_preset

    cfg = pretrain_preset("cpu", {"model": {"loss": {"lambda_fine": 0.0}},
                                  "simulation": {"mode": "uniform"}, "data": {"pose": "full"}})
    assert cfg.model.loss.lambda_fine == 0.0
    assert cfg.simulation.mode == "uniform" and cfg.data.pose == "full"
