"""The pose heads and what makes the ``cpu`` preset learn: rotation representations, the
correspondence pose head and its loss terms, ICP only inside the fine-loss gate, and a few
training steps lowering the losses on a tiny bone."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from comreg_core.model import ComRegNet, output_loss
from comreg_core.training.config import model_preset
from comreg_core.model.losses import correspondence_loss, in_fine_gate
from comreg_core.model.ops import (make_transform, matrix_to_quaternion, rotation_6d_to_matrix,
                                   transform_points)
from comreg_core.model.pose_head import (CorrespondencePoseHead, Correspondences, PoseHead,
                                         build_pose_head)
from tests.helpers import assert_close
from tests.model.test_comreg import fibula_batch
from tests.training.tiny import TINY


def tiny_model(**changes) -> ComRegNet:
    overrides = {**TINY["model"], **changes}
    return ComRegNet(model_preset("cpu", overrides))


@pytest.fixture(scope="module")
def tiny_batch(shared_data):
    return fibula_batch(256, 512, 4, seed=3)


def test_rotation_6d_gives_proper_rotations_and_recovers_known_ones():
    R = Rotation.random(8, random_state=0).as_matrix()
    x = torch.tensor(np.concatenate([R[:, :, 0], R[:, :, 1]], axis=1) * 3.0)  # scaled columns
    assert_close(rotation_6d_to_matrix(x).numpy(), R, atol=1e-12)
    M = rotation_6d_to_matrix(torch.randn(100, 6, generator=torch.Generator().manual_seed(0),
                                          dtype=torch.float64))
    assert_close((M @ M.transpose(1, 2)).numpy(), np.tile(np.eye(3), (100, 1, 1)), atol=1e-6)
    assert_close(torch.linalg.det(M).numpy(), np.ones(100), atol=1e-6)


def test_matrix_to_quaternion_matches_scipy():
    rot = Rotation.random(200, random_state=1)
    quat = matrix_to_quaternion(torch.tensor(rot.as_matrix())).numpy()  # w x y z
    expected = rot.as_quat()[:, [3, 0, 1, 2]]  # scipy: x y z w
    expected *= np.sign(expected[:, :1])
    assert_close(quat, expected, atol=1e-9)
    # 180-degree turns (w = 0), where the trace-based formula alone fails
    half = Rotation.from_rotvec(np.pi * np.eye(3)).as_matrix()
    assert_close(np.abs(matrix_to_quaternion(torch.tensor(half)).numpy()),
                 np.hstack([np.zeros((3, 1)), np.eye(3)]), atol=1e-9)


def test_heads_by_config_give_proper_rotations():
    cfg = model_preset("cpu").pose
    assert isinstance(build_pose_head(32, cfg), CorrespondencePoseHead)
    mlp = build_pose_head(32, model_preset("paper").pose)
    assert isinstance(mlp, PoseHead) and mlp.out.out_features == 7
    tokens, pos = torch.randn(2, 10, 32), torch.randn(2, 10, 3)
    with torch.no_grad():
        mlp.out.bias.normal_()  # a rotation away from the identity
    out = mlp(tokens, pos, tokens[:1], pos[:1])
    assert out.correspondences is None
    R = out.transform[:, :3, :3].detach()
    assert_close((R @ R.transpose(1, 2)).numpy(), np.tile(np.eye(3), (2, 1, 1)), atol=1e-5)
    assert_close(out.quaternion.detach().norm(dim=-1).numpy(), np.ones(2), atol=1e-6)


def test_correspondence_head_fits_its_own_predictions():
    torch.manual_seed(0)
    head = CorrespondencePoseHead(32, model_preset("cpu").pose)
    tokens, pos = torch.randn(3, 20, 32), torch.randn(3, 20, 3)
    out = head(tokens, pos, torch.randn(1, 15, 32), torch.randn(1, 15, 3))
    c = out.correspondences
    assert c.predicted.shape == (3, 20, 3) and c.weights.shape == (3, 20)
    assert_close(c.weights.sum(1).detach().numpy(), np.ones(3), atol=1e-6)
    # the transform is the weighted least-squares fit: its residual is no larger than that of
    # the identity or of random rotations with the optimal translation
    moved = transform_points(out.transform, pos).detach()
    w = c.weights.detach()
    best = (w * ((moved - c.predicted.detach()) ** 2).sum(-1)).sum(1)
    for seed in range(5):
        R = torch.tensor(Rotation.random(3, random_state=seed).as_matrix(), dtype=torch.float32)
        rotated = pos @ R.transpose(1, 2)
        t = ((c.predicted.detach() - rotated) * w.unsqueeze(-1)).sum(1)
        other = (w * ((rotated + t.unsqueeze(1) - c.predicted.detach()) ** 2).sum(-1)).sum(1)
        assert bool((best <= other + 1e-5).all())


def test_correspondence_loss_is_zero_for_the_truth_and_grows_with_error():
    gt = make_transform(torch.tensor(Rotation.random(2, random_state=2).as_matrix(),
                                     dtype=torch.float32), torch.tensor([[0.1, 0, 0], [0, 0.2, 0]]))
    pos = torch.randn(2, 30, 3)
    truth = transform_points(gt, pos)
    w = torch.full((2, 30), 1 / 30)
    assert float(correspondence_loss(Correspondences(pos, truth, w, gt), gt)) < 1e-6
    off = Correspondences(pos, truth + torch.tensor([0.03, 0.0, 0.04]), w, gt)
    assert float(correspondence_loss(off, gt)) == pytest.approx(0.05, rel=1e-5)
    assert float(correspondence_loss(None, gt)) == 0.0


def test_icp_only_inside_the_gate_gives_the_same_fine_poses_and_loss(tiny_batch):
    source, target, gt, gt_points = tiny_batch
    net = tiny_model().train()
    cfg = net.config.loss
    chosen = torch.tensor([True, False, True, False])
    results = {}
    for name, select in (("all", None), ("some", lambda coarse: chosen)):
        torch.manual_seed(1)
        out = net(source, target, refine_only=select)
        results[name] = out
    full, some = results["all"], results["some"]
    assert_close(some.fine_transform[chosen].detach().numpy(),
                 full.fine_transform[chosen].detach().numpy(), atol=1e-5)
    assert_close(some.fine_transform[~chosen].detach().numpy(),
                 full.coarse_transform[~chosen].detach().numpy(), atol=1e-6)
    # with the real gate the loss is the same either way
    torch.manual_seed(1)
    gated = net(source, target, refine_only=lambda c: in_fine_gate(c, gt, cfg))
    a = output_loss(full, gt_points, gt, cfg)
    b = output_loss(gated, gt_points, gt, cfg)
    assert float(a.total.detach()) == pytest.approx(float(b.total.detach()), rel=1e-5)


def test_a_few_steps_lower_the_completion_and_pose_losses_on_a_tiny_bone(tiny_batch):
    """Twenty Adam steps on one batch of the fibula with the tiny network: completion, coarse
    pose and correspondence losses all fall (this is the training maths working, not a
    learning-speed figure, which is the benchmark's). The bounds hold with margin on any
    machine: over network seeds 0-4 the pose terms fell to 0.34-0.47x (bound 0.7x) and the
    completion, which has to learn where as well as what, to 0.85-0.91x (bound: it falls at all;
    the old bound, 0.9x, lay within 0.01 of seed 0's own figure)."""
    source, target, gt, gt_points = tiny_batch
    torch.manual_seed(0)
    net = tiny_model().train()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    history = []
    for _ in range(20):
        opt.zero_grad()
        out = net(source, target)
        terms = output_loss(out, gt_points, gt, net.config.loss)
        terms.total.backward()
        opt.step()
        history.append([float(terms.completion.detach()), float(terms.reg_coarse.detach()),
                        float(terms.correspondence.detach())])
    first, last = np.mean(history[:3], axis=0), np.mean(history[-3:], axis=0)
    print("completion, coarse pose, correspondence losses:", first, "->", last)
    assert last[0] < first[0]
    assert last[1] < 0.7 * first[1]
    assert last[2] < 0.7 * first[2]


def test_rotated_correspondences_apply_the_global_pose_to_each_token():
    """With the per-token offsets at 0 every predicted CT point
    is one rigid pose applied to the token's position, so the Procrustes fit returns that pose
    exactly (whatever the weights); the global rotation leaves the identity it starts from."""
    torch.manual_seed(1)
    head = CorrespondencePoseHead(32, model_preset("cpu").pose)
    with torch.no_grad():
        head.out.weight[:3].zero_()
        head.out.bias[:3].zero_()
        head.global_out.weight.normal_(std=0.5)
    tokens, pos = torch.randn(2, 20, 32), torch.randn(2, 20, 3)
    out = head(tokens, pos, torch.randn(1, 15, 32), torch.randn(1, 15, 3))
    R, t = out.transform[:, :3, :3].detach(), out.transform[:, :3, 3].detach()
    assert_close(torch.linalg.det(R).numpy(), np.ones(2), atol=1e-5)
    assert float((R - torch.eye(3)).abs().max()) > 0.1
    expected = pos @ R.transpose(1, 2) + t[:, None]
    assert_close(out.correspondences.predicted.detach().numpy(), expected.numpy(), atol=1e-4)
    assert_close(out.correspondences.global_transform.detach().numpy(),
                 out.transform.detach().numpy(), atol=1e-4)  # no offsets: the global pose
    out.transform.sum().backward()  # the pose trains the global head
    assert float(head.global_out.weight.grad.abs().sum()) > 0


def test_global_pose_term_adds_the_global_poses_error_to_the_registration_loss():
    """The correspondence head's global pose, 30 deg and 0.05 units off the truth, adds
    ``lambda_correspondence * (0.05 + pi / 6)`` to ``L_registration``; at the truth, or with
    weight 0, it adds nothing."""
    from comreg_core.model.config import LossConfig
    from comreg_core.model.losses import comreg_loss

    gt = make_transform(torch.tensor(Rotation.random(2, random_state=4).as_matrix(),
                                     dtype=torch.float32), torch.tensor([[0.1, 0, 0], [0, 0.2, 0]]))
    turn = torch.tensor(Rotation.from_rotvec([0, 0, np.pi / 6]).as_matrix(), dtype=torch.float32)
    off = gt.clone()
    off[:, :3, :3] = gt[:, :3, :3] @ turn
    off[:, :3, 3] += torch.tensor([0.03, 0.0, 0.04])
    pos = torch.randn(2, 30, 3)
    pts, w = torch.randn(2, 64, 3), torch.full((2, 30), 1 / 30)

    def registration(global_transform, weight):
        corr = Correspondences(pos, transform_points(gt, pos), w, global_transform=global_transform)
        return float(comreg_loss(pts[:, :16], pts, pts, gt, gt, gt,
                                 LossConfig(lambda_correspondence=weight), corr).registration)

    assert registration(off, 0.0) < 1e-5
    assert registration(gt, 2.0) < 1e-5
    assert registration(off, 2.0) == pytest.approx(2.0 * (0.05 + np.pi / 6), rel=1e-4)


def test_position_moments_match_numpy_and_ignore_sign_and_scale():
    from comreg_core.model.pose_head import position_moments

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(2, 50, 3)) * [3.0, 1.0, 0.5] + [0.2, -0.1, 0.4]
    m = position_moments(torch.tensor(pts)).numpy()
    for b in range(2):
        cov = np.cov(pts[b].T, bias=True)
        cov /= np.trace(cov)
        assert_close(m[b, :3], pts[b].mean(0), atol=1e-12)
        assert_close(m[b, 3:], cov[np.triu_indices(3)], atol=1e-12)
    mirrored = position_moments(torch.tensor(-2.0 * (pts - pts.mean(1, keepdims=True)))).numpy()
    assert_close(mirrored[:, 3:], m[:, 3:], atol=1e-12)  # sign and size do not change them
    cfg = model_preset("cpu", {"pose": {"token_dim": 32}}).pose
    head = CorrespondencePoseHead(16, cfg)
    out = head(torch.randn(2, 20, 16), torch.randn(2, 20, 3), torch.randn(1, 15, 16),
               torch.randn(1, 15, 3))
    assert out.transform.shape == (2, 4, 4)


