"""AdaPoinTr building blocks against naive (unfactorised) references, and the module's contract."""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from comreg_core.model.adapointr import AdaPoinTr, EdgeConv, FoldingHead, GroupNormLast
from comreg_core.model.transformer import GraphAttention
from comreg_core.model.config import CompletionConfig
from comreg_core.model.ops import gather_points, knn
from tests.helpers import assert_close

TINY = CompletionConfig(input_points=256, center_num=(64, 32), dgcnn_k=8, encoder_dim=48,
                        encoder_depth=2, decoder_dim=48, decoder_depth=2, num_heads=4, graph_k=4,
                        global_feature_dim=64, mlp_hidden=64, num_query=24, fold_grid=(2, 3),
                        fold_hidden=32)


def test_group_norm_last_equals_nn_group_norm():
    torch.manual_seed(0)
    x = torch.randn(3, 7, 5, 16, dtype=torch.float64)
    gn = GroupNormLast(4, 16).double()
    ref = nn.GroupNorm(4, 16).double()
    with torch.no_grad():
        gn.weight.normal_()
        gn.bias.normal_()
        ref.weight.copy_(gn.weight)
        ref.bias.copy_(gn.bias)
    assert_close(gn(x).detach(), ref(x.permute(0, 3, 1, 2)).permute(0, 2, 3, 1).detach(),
                 atol=1e-12)
    assert_close(gn(x[:, 0, 0]).detach(), ref(x[:, 0, 0]).detach(), atol=1e-12)  # (B, C)


def test_edge_conv_equals_concatenated_reference():
    torch.manual_seed(1)
    conv = EdgeConv(6, 16).double()
    fq, fr = torch.randn(2, 10, 6, dtype=torch.float64), torch.randn(2, 30, 6, dtype=torch.float64)
    idx = torch.randint(0, 30, (2, 10, 5))
    nb = gather_points(fr, idx)  # B Nq k C
    centre = fq.unsqueeze(2).expand_as(nb)
    edges = torch.cat([nb - centre, centre], dim=-1) @ conv.linear.weight.T
    ref = F.leaky_relu(conv.norm(edges), 0.2).max(dim=2).values
    assert_close(conv(fq, fr, idx).detach(), ref.detach(), atol=1e-12)


def test_graph_attention_equals_concatenated_reference():
    torch.manual_seed(2)
    att = GraphAttention(12).double()
    q, v = torch.randn(2, 9, 12, dtype=torch.float64), torch.randn(2, 20, 12, dtype=torch.float64)
    idx = torch.randint(0, 20, (2, 9, 4))
    nb = gather_points(v, idx)
    centre = q.unsqueeze(2).expand_as(nb)
    ref = att.merge_map(F.leaky_relu(att.knn_map(torch.cat([nb - centre, centre], -1)), 0.2)
                        .max(dim=2).values)
    assert_close(att(q, v, idx).detach(), ref.detach(), atol=1e-12)


def test_folding_head_equals_concatenated_reference():
    torch.manual_seed(3)
    head = FoldingHead(10, grid=(2, 3), hidden=32).double()
    feat = torch.randn(5, 10, dtype=torch.float64)
    seed = head.seed.double()  # S 2
    assert seed.shape == (6, 2) and seed.min() == -1 and seed.max() == 1
    f = feat.unsqueeze(1).expand(-1, 6, -1)
    x = head.fold1_in(torch.cat([seed.expand(5, -1, -1), f], -1))
    p1 = FoldingHead._tail(head.fold1, x)
    p2 = FoldingHead._tail(head.fold2, head.fold2_in(torch.cat([p1, f], -1)))
    assert_close(head(feat).detach(), p2.detach(), atol=1e-12)


def test_adapointr_contract_and_eval_determinism():
    torch.manual_seed(4)
    net = AdaPoinTr(TINY).eval()
    xyz = torch.rand(2, 300, 3) - 0.5
    out = net(xyz)
    assert out.centres.shape == (2, 24, 3)
    assert out.dense.shape == (2, 24 * 6, 3)
    assert out.decoded.shape == (2, 24, 48)
    assert out.encoded.shape == (2, 32, 48) and out.proxies.shape == (2, 32, 3)
    assert out.global_feature.shape == (2, 64)
    # proxies are input points; at most num_query // 2 centres are observed (input) points
    exact = (out.proxies.unsqueeze(2) - xyz.unsqueeze(1)).abs().sum(-1).min(-1).values
    assert float(exact.max()) == 0.0
    observed = (out.centres.unsqueeze(2) - xyz.unsqueeze(1)).abs().sum(-1).min(-1).values == 0
    assert int(observed.sum(1).max()) <= 12
    again = net(xyz)
    for a, b in zip(out, again, strict=True):
        assert torch.equal(a, b)
    assert net(xyz, rebuild=False).dense is None
    # dense patches sit around their centres
    patches = out.dense.reshape(2, 24, 6, 3)
    assert torch.isfinite(patches).all()
    with pytest.raises(ValueError):
        net(torch.rand(1, 40, 3))
    net.train()
    torch.manual_seed(0)
    a = net(xyz)
    torch.manual_seed(0)
    b = net(xyz)
    assert torch.equal(a.dense, b.dense)  # random FPS starts are reproducible under a seed
    assert knn(out.centres, out.centres, 1).shape == (2, 24, 1)
