"""The whole ComReg network: cpu preset forward/backward, eval determinism, target caching,
the "w/o completion" switch, input errors, and one training step of the paper preset."""

import numpy as np
import pytest
import torch

from comreg_core.errors import InvalidGeometryError
from comreg_core.io.meshes import read_mesh
from comreg_core.model import ComRegNet, comreg_loss, output_loss
from comreg_core.training.config import model_preset
from comreg_core.normalization import Normalization
from tests.helpers import FIBULA_STL, assert_close, random_rigid


def fibula_batch(n_source, n_target, batch, seed=0):
    """Normalised fibula clouds: partial, moved sources; the full CT cloud; ground truths."""
    mesh = read_mesh(FIBULA_STL).to_trimesh()
    ct = np.asarray(mesh.sample(n_target, seed=seed))
    norm = Normalization.from_ct(ct)
    rng = np.random.default_rng(seed)
    sources, gts, gt_points = [], [], []
    for b in range(batch):
        pts = np.asarray(mesh.sample(2 * n_source, seed=seed + 1 + b))
        keep = (pts - pts.mean(0)) @ rng.normal(size=3)
        pts = pts[np.argsort(keep)[-n_source:]]  # the half facing one side
        T = random_rigid(rng, 50.0)  # CT -> US frame, mm
        sources.append(norm.points_to_model(pts @ T[:3, :3].T + T[:3, 3]))
        T_model = norm.transform_to_model(T)
        gts.append(np.linalg.inv(T_model))  # US -> CT: what the network predicts
        gt_points.append(norm.points_to_model(ct) @ T_model[:3, :3].T + T_model[:3, 3])
    f32 = torch.float32
    return (torch.tensor(np.stack(sources), dtype=f32),
            torch.tensor(norm.points_to_model(ct), dtype=f32)[None],
            torch.tensor(np.stack(gts), dtype=f32), torch.tensor(np.stack(gt_points), dtype=f32))


@pytest.fixture(scope="module")
def cpu_batch(shared_data):
    cfg = model_preset("cpu")
    n = max(cfg.completion.input_points, cfg.icp.num_points)
    return fibula_batch(n, n, 4)


def test_cpu_preset_forward_backward_on_cpu(cpu_batch):
    torch.manual_seed(0)
    cfg = model_preset("cpu")
    net = ComRegNet(cfg).train()
    source, target, gt, gt_points = cpu_batch
    out = net(source, target)
    c = cfg.completion
    assert out.completion.centres.shape == (4, c.num_query, 3)
    assert out.completion.dense.shape == (4, c.dense_points, 3)
    assert out.coarse_transform.shape == out.fine_transform.shape == (4, 4, 4)
    assert out.icp.transform_history.shape == (4, cfg.icp.iterations, 4, 4)
    R = out.fine_transform[:, :3, :3].detach()
    assert_close(R @ R.transpose(1, 2), np.tile(np.eye(3), (4, 1, 1)), atol=1e-5)
    assert_close(out.quaternion.detach().norm(dim=-1), np.ones(4), atol=1e-6)
    terms = output_loss(out, gt_points, gt, cfg.loss)
    assert all(torch.isfinite(v).all() for v in terms)
    terms.total.backward()
    no_grad = {n for n, p in net.named_parameters() if p.grad is None}
    # AdaPoinTr's query ranking only orders candidates (argsort): it never receives a gradient.
    assert no_grad == {n for n, _ in net.named_parameters() if ".query_ranking." in n}
    grads = [p.grad for n, p in net.named_parameters() if p.grad is not None]
    assert all(torch.isfinite(g).all() for g in grads)
    assert sum(bool(g.abs().max() > 0) for g in grads) >= len(grads) - 2
    # the pose head is reached through the ICP as well as through the coarse term
    assert float(net.pose_head.out.weight.grad.abs().max()) > 0


def test_eval_outputs_are_bitwise_identical_across_calls(cpu_batch):
    torch.manual_seed(1)
    net = ComRegNet(model_preset("cpu")).eval()
    source, target, _, _ = cpu_batch
    with torch.no_grad():
        first = net(source[:2], target)
        second = net(source[:2], target)

    def flat(out):
        return [*out.completion, out.coarse_transform, out.fine_transform, out.quaternion,
                out.translation, *out.icp]

    for a, b in zip(flat(first), flat(second), strict=True):
        assert torch.equal(a, b)


def test_cached_target_and_shared_target_batch_agree(cpu_batch):
    torch.manual_seed(2)
    net = ComRegNet(model_preset("cpu")).eval()
    source, target, _, _ = cpu_batch
    with torch.no_grad():
        direct = net(source[:2], target)  # target batch 1: f(T) run once
        cached = net(source[:2], net.encode_target(target))
        paired = net(source[:2], target.expand(2, -1, -1))  # f over [S, T] in one batch
    assert torch.equal(direct.coarse_transform, cached.coarse_transform)
    assert_close(paired.coarse_transform, direct.coarse_transform, atol=1e-4)
    assert_close(paired.completion.dense, direct.completion.dense, atol=1e-5)


def test_input_errors():
    net = ComRegNet(model_preset("cpu")).eval()
    with pytest.raises(InvalidGeometryError, match="needs at least"):
        net(torch.rand(1, 100, 3), torch.rand(1, 3000, 3))
    with pytest.raises(ValueError):
        net(torch.rand(1, 3000, 2), torch.rand(1, 3000, 3))
    with pytest.raises(ValueError):
        net(torch.rand(2, 3000, 3), torch.rand(3, 3000, 3))


def test_paper_preset_builds_and_trains_one_step_at_batch_1(shared_data):
    """The paper sizes (20,000 points, AdaPoinTr PCN widths) on CPU: one AdamW step."""
    torch.manual_seed(4)
    cfg = model_preset("paper")
    net = ComRegNet(cfg).train()
    assert 30e6 < sum(p.numel() for p in net.parameters()) < 40e6
    source, target, gt, gt_points = fibula_batch(20000, 20000, 1)
    assert net.completion.config.dense_points == 20000
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4, weight_decay=5e-4)
    before = net.pose_head.out.weight.detach().clone()
    out = net(source, target)
    assert out.completion.dense.shape == (1, 20000, 3)
    assert out.icp.aligned.shape == (1, 4096, 3)
    terms = comreg_loss(out.completion.centres, out.completion.dense, gt_points,
                        out.coarse_transform, out.fine_transform, gt, cfg.loss)
    terms.total.backward()
    opt.step()
    assert torch.isfinite(terms.total) and not torch.equal(before, net.pose_head.out.weight)


def test_gpu_code_paths_run_on_cpu(cpu_batch, monkeypatch):
    """No GPU here: force the torch FPS loop and the chunked-cdist kNN (what CUDA tensors use)
    and check they give the same ICP and a working, deterministic network."""
    from comreg_core.model import differentiable_icp, ops

    source, target, gt, _ = cpu_batch
    src = source[:2, :1500].double()
    init = gt[:2].double()
    kd = differentiable_icp(src, target[:, :1800].double(), init, iterations=5, neighbors=16)
    monkeypatch.setattr(ops, "FORCE_TORCH_BACKENDS", True)
    monkeypatch.setattr(ops, "_CHUNK_PAIRS", 1 << 20)  # several chunks
    dense = differentiable_icp(src, target[:, :1800].double(), init, iterations=5, neighbors=16)
    assert_close(dense.transform, kd.transform, atol=1e-12, what="cdist-kNN ICP vs KD-tree ICP")
    torch.manual_seed(5)
    net = ComRegNet(model_preset("cpu", {"icp": {"num_points": 1024}})).eval()
    with torch.no_grad():
        a = net(source[:1], target)
        b = net(source[:1], target)
    assert torch.isfinite(a.fine_transform).all()
    assert torch.equal(a.fine_transform, b.fine_transform)
