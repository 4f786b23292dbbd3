"""Pose loss (finite at 0 and 180 degrees), Chamfer-based completion terms, adaptive lambda_reg."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from comreg_core.config import ConfigError
from comreg_core.model.config import LossConfig
from comreg_core.model.losses import comreg_loss, pose_loss, rotation_angle
from comreg_core.model.ops import chamfer_l1, make_transform, quaternion_to_matrix
from tests.helpers import assert_close


def test_rotation_angle_matches_scipy_over_the_whole_range():
    rng = np.random.default_rng(0)
    R1 = Rotation.random(200, random_state=rng)
    angles = np.concatenate([rng.uniform(0, np.pi, 194), [0.0, 1e-7, 1e-4, np.pi - 1e-4,
                                                           np.pi - 1e-7, np.pi]])
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    R2 = R1 * Rotation.from_rotvec(axes * angles[:, None])
    for dtype, atol in ((torch.float64, 1e-7), (torch.float32, 2e-3)):
        got = rotation_angle(torch.tensor(R1.as_matrix(), dtype=dtype),
                             torch.tensor(R2.as_matrix(), dtype=dtype))
        assert_close(got, angles, atol=atol, what=f"angle {dtype}")
    # arccos form of the paper, away from the ends
    M = np.einsum("bji,bjk->bik", R1.as_matrix(), R2.as_matrix())
    paper = np.arccos(np.clip((np.trace(M, axis1=1, axis2=2) - 1) / 2, -1, 1))
    mid = (angles > 0.1) & (angles < np.pi - 0.1)
    assert_close(rotation_angle(torch.tensor(R1.as_matrix()), torch.tensor(R2.as_matrix()))[mid],
                 paper[mid], atol=1e-12)


@pytest.mark.parametrize("angle_deg", [0.0, 180.0])
def test_pose_loss_is_finite_with_finite_gradients_at_0_and_180_degrees(angle_deg):
    rng = np.random.default_rng(1)
    R = torch.tensor(Rotation.random(random_state=rng).as_matrix(), dtype=torch.float32)
    t = torch.tensor([1.0, 2.0, 3.0])
    T = make_transform(R, t)[None]
    # Estimated pose parametrised like the pose head: quaternion + translation.
    rel = Rotation.from_rotvec(np.deg2rad(angle_deg) * np.array([0.0, 0.6, 0.8]))
    xyzw = (Rotation.from_matrix(R.double().numpy()) * rel).as_quat()
    q = torch.tensor([[xyzw[3], *xyzw[:3]]], dtype=torch.float32, requires_grad=True)
    t_hat = t.clone()[None].requires_grad_(True)
    T_hat = make_transform(quaternion_to_matrix(q), t_hat)
    loss = pose_loss(T_hat, T)
    loss.sum().backward()
    assert torch.isfinite(loss).all() and torch.isfinite(q.grad).all()
    assert torch.isfinite(t_hat.grad).all()
    assert abs(float(loss.detach()) - math.radians(angle_deg)) < 1e-3
    # float64 and gradients with respect to both arguments too
    A = torch.tensor(Rotation.random(random_state=rng).as_matrix(), requires_grad=True)
    B = (A.detach() @ torch.tensor(rel.as_matrix())).requires_grad_(True)
    ang = rotation_angle(A, B)
    ang.backward()
    assert torch.isfinite(A.grad).all() and torch.isfinite(B.grad).all()
    assert abs(float(ang.detach()) - math.radians(angle_deg)) < 1e-7


def test_pose_loss_values():
    R = Rotation.from_rotvec([0.0, 0.0, 0.3]).as_matrix()
    T_hat = make_transform(torch.tensor(R), torch.tensor([3.0, 4.0, 0.0]))[None]
    T = torch.eye(4, dtype=torch.float64)[None]
    assert_close(pose_loss(T_hat, T), [5.0 + 0.3], atol=1e-12)
    with pytest.raises(ValueError):
        pose_loss(T_hat, torch.eye(4)[None, :3])


def test_comreg_loss_terms_and_adaptive_weight():
    g = torch.Generator().manual_seed(2)
    centres = torch.rand(2, 20, 3, generator=g, requires_grad=True)
    dense = torch.rand(2, 80, 3, generator=g, requires_grad=True)
    gt_points = torch.rand(2, 100, 3, generator=g)
    q = torch.randn(2, 4, generator=g, requires_grad=True)
    t = torch.randn(2, 3, generator=g, requires_grad=True)
    coarse = make_transform(quaternion_to_matrix(q), t)
    fine = make_transform(quaternion_to_matrix(q.detach() + 0.1), t.detach() * 0.5)
    fine.requires_grad_(True)
    gt = make_transform(quaternion_to_matrix(torch.randn(2, 4, generator=g)),
                        torch.randn(2, 3, generator=g))
    cfg = LossConfig(fine_gate_deg=180.0, fine_gate_translation=math.inf)  # the paper's
    terms = comreg_loss(centres, dense, gt_points, coarse, fine, gt, cfg)
    sparse = chamfer_l1(centres, gt_points).mean()
    dense_cd = chamfer_l1(dense, gt_points).mean()
    reg = 1.0 * pose_loss(coarse, gt).mean() + 0.5 * pose_loss(fine, gt).mean()
    assert_close(terms.sparse.detach(), sparse.detach(), atol=1e-7)
    assert_close(terms.dense.detach(), dense_cd.detach(), atol=1e-7)
    assert_close(terms.completion.detach(), (sparse + dense_cd).detach(), atol=1e-7)
    assert_close(terms.registration.detach(), reg.detach(), atol=1e-6)
    lam = 0.1 * (sparse + dense_cd) / reg
    assert_close(terms.lambda_reg, lam.detach(), rtol=1e-6)
    assert not terms.lambda_reg.requires_grad
    # The registration term is rho times the completion term, in value.
    assert_close(terms.total.detach(), 1.1 * terms.completion.detach(), rtol=1e-6)
    # Gradient of the registration inputs = lambda_reg x d(L_registration), the weight detached.
    expected = torch.autograd.grad(float(lam.detach()) * reg, t, retain_graph=True)[0]
    terms.total.backward(retain_graph=True)
    assert_close(t.grad, expected, rtol=1e-5, atol=1e-7)
    # lambda_fine = 0 removes the fine term's gradient (the paper's ablation)
    fine.grad = None
    comreg_loss(centres, dense, gt_points, coarse, fine, gt,
                LossConfig(lambda_fine=0.0)).total.backward()
    assert float(fine.grad.abs().max()) == 0.0


def test_fine_gate_keeps_only_samples_whose_coarse_pose_is_near():
    gt = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    coarse = gt.clone()
    # coarse errors: 5 deg, 9 deg, 11 deg about z; 5 deg and 0.03 translation
    for i, deg in enumerate((5.0, 9.0, 11.0, 5.0)):
        coarse[i, :3, :3] = torch.from_numpy(Rotation.from_euler("z", deg, degrees=True).as_matrix())
    coarse[3, 1, 3] = 0.03
    fine = gt.clone()
    fine[:, 0, 3] = 1.0
    fine.requires_grad_(True)
    points = torch.zeros(4, 4, 3, dtype=torch.float64)
    cfg = LossConfig(fine_gate_deg=10.0, fine_gate_translation=0.025)
    terms = comreg_loss(points, points, points, coarse, fine, gt, cfg)
    # two of four samples are near enough: their fine loss is 1 (translation), the others 0
    assert_close(terms.reg_fine.detach(), torch.tensor(0.5, dtype=torch.float64))
    terms.reg_fine.backward()
    assert [float(g.abs().max()) > 0 for g in fine.grad] == [True, True, False, False]
    ungated = comreg_loss(points, points, points, coarse, fine, gt,
                          LossConfig(fine_gate_deg=180.0, fine_gate_translation=math.inf))
    assert_close(ungated.reg_fine.detach(), torch.tensor(1.0, dtype=torch.float64))
    with pytest.raises(ConfigError, match="fine_gate_deg"):
        LossConfig(fine_gate_deg=0.0)
    with pytest.raises(ConfigError, match="fine_gate_translation"):
        LossConfig(fine_gate_translation=-1.0)
