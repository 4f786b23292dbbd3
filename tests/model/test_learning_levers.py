"""The levers that make the ``cpu`` preset learn: rotation representations, the correspondence
pose head, the source-centroid input frame, ICP only inside the fine-loss gate, and a few
training steps lowering the losses on a tiny bone."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from comreg_core.model import ComRegNet, output_loss
from comreg_core.config import ConfigError
from comreg_core.model.comreg import principal_axes
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
    six = PoseHead(32, model_preset("paper", {"pose": {"rotation": "6d"}}).pose)
    tokens, pos = torch.randn(2, 10, 32), torch.randn(2, 10, 3)
    out = six(tokens, pos, tokens[:1], pos[:1])
    assert six.out.out_features == 9 and out.correspondences is None
    R = out.transform[:, :3, :3].detach()
    assert_close((R @ R.transpose(1, 2)).numpy(), np.tile(np.eye(3), (2, 1, 1)), atol=1e-5)
    assert_close(out.quaternion.norm(dim=-1).numpy(), np.ones(2), atol=1e-6)


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
    assert float(correspondence_loss(Correspondences(pos, truth, w), gt)) < 1e-6
    off = Correspondences(pos, truth + torch.tensor([0.03, 0.0, 0.04]), w)
    assert float(correspondence_loss(off, gt)) == pytest.approx(0.05, rel=1e-5)
    assert float(correspondence_loss(None, gt)) == 0.0


def test_centroid_frame_makes_the_network_translation_equivariant(tiny_batch):
    torch.manual_seed(0)
    source, target, _, _ = tiny_batch
    d = torch.tensor([0.2, -0.1, 0.15])
    for frame, equivariant in (("centroid", True), ("ct", False)):
        net = tiny_model(input_frame=frame).eval()
        with torch.no_grad():
            a = net(source, target)
            b = net(source + d, target)
        shift = make_transform(torch.eye(3).expand(4, 3, 3), (-d).expand(4, 3))  # x -> x - d
        expected = a.coarse_transform @ shift  # what the coarse pose of the moved cloud must be
        error = float((b.coarse_transform - expected).abs().max())
        if equivariant:
            assert error < 1e-4, error
            assert_close(b.completion.dense.numpy(), (a.completion.dense + d).numpy(),
                         atol=1e-4)
        else:
            assert error > 1e-3, error


def test_principal_frame_makes_the_network_rigid_motion_equivariant(tiny_batch):
    torch.manual_seed(0)
    source, target, _, _ = tiny_batch
    M = make_transform(torch.tensor(Rotation.from_rotvec([0.3, -1.2, 0.8]).as_matrix(),
                                    dtype=torch.float32), torch.tensor([0.2, -0.1, 0.15]))
    moved = transform_points(M.expand(4, 4, 4), source)
    net = tiny_model(input_frame="principal").eval()
    with torch.no_grad():
        a = net(source, target)
        b = net(moved, target)
    expected = a.coarse_transform @ torch.linalg.inv(M)  # the moved cloud's pose
    assert float((b.coarse_transform - expected).abs().max()) < 1e-3
    assert_close(b.completion.dense.numpy(),
                 transform_points(M.expand(4, 4, 4), a.completion.dense).numpy(), atol=1e-3)


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
    pose and correspondence losses all fall clearly (this is the training maths working, not
    a learning-speed figure, which is the benchmark's). In the preset's CT frame the moved
    sources lie up to 1.5 units off the CT's centre, so the completion has to learn where as
    well as what: it falls by ~15 % in these steps (0.84x measured), the pose terms by ~60 %."""
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
    assert last[0] < 0.9 * first[0]
    assert last[1] < 0.8 * first[1]
    assert last[2] < 0.8 * first[2]


def test_matched_correspondences_are_mixtures_of_ct_tokens_and_learn(tiny_batch):
    """``correspondence: match``: every predicted CT point is a convex combination of the CT
    tokens' positions, and a few steps raise the share of tokens whose best match is the CT
    token nearest their true place (in the centroid frame trial M was measured in)."""
    source, target, gt, gt_points = tiny_batch
    torch.manual_seed(0)
    net = tiny_model(input_frame="centroid",
                     pose={**TINY["model"]["pose"], "head": "correspondence",
                           "correspondence": "match"}).train()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    hits = []
    for step in range(25):
        opt.zero_grad()
        out = net(source, target)
        c = out.correspondences
        if step == 0:
            lo = c.anchors.amin(dim=1, keepdim=True) - 1e-6
            hi = c.anchors.amax(dim=1, keepdim=True) + 1e-6
            assert bool(((c.predicted >= lo) & (c.predicted <= hi)).all())
        truth = transform_points(gt, c.positions)
        nearest = torch.cdist(truth, c.anchors.expand(4, -1, -1)).argmin(-1)
        hits.append(float((c.logits.argmax(-1) == nearest).float().mean()))
        terms = output_loss(out, gt_points, gt, net.config.loss)
        terms.total.backward()
        opt.step()
    print("share of tokens matched to the right CT token:", hits[0], "->", hits[-1])
    assert np.mean(hits[-3:]) > np.mean(hits[:3]) + 0.05


def test_rotated_correspondences_apply_the_global_pose_to_each_token():
    """``correspondence: rotated``: with the per-token offsets at 0 every predicted CT point
    is one rigid pose applied to the token's position, so the Procrustes fit returns that pose
    exactly (whatever the weights); the global rotation leaves the identity it starts from."""
    torch.manual_seed(1)
    cfg = model_preset("cpu", {"pose": {"correspondence": "rotated"}}).pose
    head = CorrespondencePoseHead(32, cfg)
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
    """``loss.lambda_global``: the rotated head's global pose, 30 deg and 0.05 units off the
    truth, adds ``lambda_global * (0.05 + pi / 6)`` to ``L_registration``; at the truth it adds
    nothing; other heads' correspondences carry no global pose."""
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
        return float(comreg_loss(pts[:, :16], pts, pts, gt, gt, gt, LossConfig(lambda_global=weight),
                                 corr).registration)

    assert registration(off, 0.0) < 1e-5
    assert registration(gt, 2.0) < 1e-5
    assert registration(off, 2.0) == pytest.approx(2.0 * (0.05 + np.pi / 6), rel=1e-4)
    assert registration(None, 2.0) < 1e-5


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
    cfg = model_preset("cpu", {"pose": {"token_dim": 32, "moments": True}}).pose
    head = CorrespondencePoseHead(16, cfg)
    out = head(torch.randn(2, 20, 16), torch.randn(2, 20, 3), torch.randn(1, 15, 16),
               torch.randn(1, 15, 3))
    assert out.transform.shape == (2, 4, 4)


def test_azimuth_frame_turns_the_completion_with_a_turn_about_the_ct_long_axis(tiny_batch):
    torch.manual_seed(0)
    source, target, _, _ = tiny_batch
    axes = principal_axes(target[0])
    x = (target[0] - target[0].mean(0)).double().numpy()
    long_axis = np.linalg.eigh(x.T @ x)[1][:, -1]  # numpy's largest principal axis
    assert abs(float(axes[0].numpy() @ long_axis)) > 1 - 1e-6
    assert_close(principal_axes(target[0, ::3]).numpy(), axes.numpy(), atol=0.05)  # same signs
    turn = make_transform(torch.tensor(Rotation.from_rotvec(1.1 * axes[0].numpy()).as_matrix(),
                                       dtype=torch.float32), torch.zeros(3))
    moved = transform_points(turn.expand(4, 4, 4), source)
    net = tiny_model(input_frame="azimuth").eval()
    with torch.no_grad():
        a = net(source, target)
        b = net(moved, target)
    # f sees the same input, so its completion turns with the cloud; the pose head also gets
    # the azimuth, so the coarse pose is free to differ from a's turned one.
    assert_close(b.completion.dense.numpy(),
                 transform_points(turn.expand(4, 4, 4), a.completion.dense).numpy(), atol=1e-3)
    assert b.coarse_transform.shape == (4, 4, 4)
    with pytest.raises(ConfigError, match="azimuth"):
        tiny_model(input_frame="azimuth", pose={"correspondence": "regress"})
