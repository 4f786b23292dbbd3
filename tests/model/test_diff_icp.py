"""Differentiable ICP and weighted Procrustes against independent references.

References: scipy's ``Rotation.align_vectors``; a dense-softmax ICP written here in numpy; finite
differences (``torch.autograd.gradcheck``); the real fibula surface for convergence.
"""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from comreg_core.io.meshes import read_mesh
from comreg_core.model.diff_icp import (
    differentiable_icp,
    procrustes_rotation,
    weighted_procrustes,
)
from comreg_core.normalization import Normalization
from tests.helpers import FIBULA_STL, assert_close, random_rigid


def test_procrustes_recovers_random_rigid_transforms_exactly():
    rng = np.random.default_rng(0)
    B = 8
    Ts = np.stack([random_rigid(rng, 2.0) for _ in range(B)])
    src = rng.normal(size=(B, 200, 3))
    dst = np.einsum("bij,bnj->bni", Ts[:, :3, :3], src) + Ts[:, None, :3, 3]
    R, t = weighted_procrustes(torch.tensor(src), torch.tensor(dst))
    assert_close(R, Ts[:, :3, :3], atol=1e-9, what="rotation (float64)")
    assert_close(t, Ts[:, :3, 3], atol=1e-9, what="translation (float64)")
    R32, t32 = weighted_procrustes(torch.tensor(src, dtype=torch.float32),
                                   torch.tensor(dst, dtype=torch.float32))
    assert_close(R32, Ts[:, :3, :3], atol=1e-6, what="rotation (float32)")
    assert_close(t32, Ts[:, :3, 3], atol=1e-5, what="translation (float32)")
    assert_close(torch.linalg.det(R), np.ones(B), atol=1e-12)


def test_weighted_procrustes_agrees_with_scipy_align_vectors_on_noisy_data():
    rng = np.random.default_rng(1)
    for _ in range(5):
        T = random_rigid(rng, 1.0)
        src = rng.normal(size=(150, 3))
        dst = src @ T[:3, :3].T + T[:3, 3] + rng.normal(scale=0.2, size=(150, 3))
        w = rng.uniform(0.1, 2.0, 150)
        R, t = weighted_procrustes(torch.tensor(src)[None], torch.tensor(dst)[None],
                                   torch.tensor(w)[None])
        mu_s, mu_d = (w[:, None] * src).sum(0) / w.sum(), (w[:, None] * dst).sum(0) / w.sum()
        ref, _ = Rotation.align_vectors(dst - mu_d, src - mu_s, weights=w)
        assert_close(R[0], ref.as_matrix(), atol=1e-9, what="R vs align_vectors")
        assert_close(t[0], mu_d - ref.as_matrix() @ mu_s, atol=1e-9, what="t")


def test_procrustes_reflection_fix_returns_a_proper_rotation():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(100, 3)) * [3.0, 2.0, 0.5]
    mirror = np.diag([1.0, 1.0, -1.0])
    dst = src @ (Rotation.random(random_state=rng).as_matrix() @ mirror).T
    R, _ = weighted_procrustes(torch.tensor(src)[None], torch.tensor(dst)[None])
    ref, _ = Rotation.align_vectors(dst - dst.mean(0), src - src.mean(0))
    assert abs(float(torch.linalg.det(R[0])) - 1.0) < 1e-12
    assert_close(R[0], ref.as_matrix(), atol=1e-9, what="best proper rotation")


def svd_rotation_reference(M):
    """R = V D U^T straight from torch.linalg.svd (autograd's SVD backward)."""
    U, _, Vh = torch.linalg.svd(M)
    V = Vh.transpose(1, 2)
    d = torch.sign(torch.linalg.det(V @ U.transpose(1, 2))).detach()
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return V @ D @ U.transpose(1, 2)


def test_procrustes_rotation_backward_matches_svd_autograd_and_finite_differences():
    g = torch.Generator().manual_seed(8)
    M = torch.randn(6, 3, 3, generator=g, dtype=torch.float64)
    M[3] = -M[3]
    G = torch.randn(6, 3, 3, generator=g, dtype=torch.float64)
    a, b = M.clone().requires_grad_(True), M.clone().requires_grad_(True)
    (procrustes_rotation(a) * G).sum().backward()
    (svd_rotation_reference(b) * G).sum().backward()
    assert_close(procrustes_rotation(M), svd_rotation_reference(M), atol=1e-14)
    assert_close(a.grad, b.grad, atol=1e-12, what="stable backward vs SVD autograd")
    assert torch.autograd.gradcheck(procrustes_rotation, (M.clone().requires_grad_(True),))


def test_procrustes_gradient_is_finite_for_repeated_singular_values():
    """A cross-covariance with two equal singular values (a round cross-section): autograd's SVD
    backward gives NaN, the Procrustes rotation is still smooth and its gradient finite."""
    M = torch.diag(torch.tensor([3.0, 1.0, 1.0], dtype=torch.float64))[None]
    G = torch.arange(9, dtype=torch.float64).reshape(1, 3, 3)
    ref = M.clone().requires_grad_(True)
    (svd_rotation_reference(ref) * G).sum().backward()
    assert not torch.isfinite(ref.grad).all()
    ours = M.clone().requires_grad_(True)
    (procrustes_rotation(ours) * G).sum().backward()
    assert torch.isfinite(ours.grad).all()
    Q = torch.tensor(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix())[None]
    for m in (M, Q @ M):
        assert torch.autograd.gradcheck(procrustes_rotation, (m.clone().requires_grad_(True),))


def test_procrustes_rejects_bad_shapes():
    with pytest.raises(ValueError):
        weighted_procrustes(torch.rand(1, 5, 3), torch.rand(1, 6, 3))
    with pytest.raises(ValueError):
        weighted_procrustes(torch.rand(1, 5, 3), torch.rand(1, 5, 3), torch.rand(1, 4))


def dense_soft_icp_reference(source, target, init, iterations, sigma):
    """Soft ICP with a dense softmax over all targets, numpy float64 (independent reference)."""
    coarse = source @ init[:3, :3].T + init[:3, 3]
    R, t = np.eye(3), np.zeros(3)
    history = []
    for _ in range(iterations):
        x = coarse @ R.T + t
        d2 = ((x[:, None, :] - target[None, :, :]) ** 2).sum(-1)
        logits = -d2 / (2 * sigma**2)
        w = np.exp(logits - logits.max(1, keepdims=True))
        w /= w.sum(1, keepdims=True)
        y = w @ target
        mu_s, mu_y = coarse.mean(0), y.mean(0)
        H = (coarse - mu_s).T @ (y - mu_y)
        U, _, Vt = np.linalg.svd(H)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        R = Vt.T @ D @ U.T
        t = mu_y - R @ mu_s
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = R, t
        history.append(step @ init)
    return np.stack(history)


def test_knn_restricted_soft_icp_matches_dense_softmax_reference():
    rng = np.random.default_rng(3)
    target = rng.uniform(-0.5, 0.5, size=(400, 3))
    sigma, k = 0.04, 16
    B = 2
    sources, inits, refs = [], [], []
    for _ in range(B):
        src = target[rng.choice(400, 300, replace=False)] + rng.normal(scale=0.01, size=(300, 3))
        init = np.eye(4)
        init[:3, :3] = Rotation.from_rotvec(rng.normal(scale=0.03, size=3)).as_matrix()
        init[:3, 3] = rng.normal(scale=0.02, size=3)
        sources.append(src)
        inits.append(init)
        refs.append(dense_soft_icp_reference(src, target, init, 10, sigma))
    res = differentiable_icp(torch.tensor(np.stack(sources)), torch.tensor(target)[None],
                             torch.tensor(np.stack(inits)), iterations=10, sigma=sigma,
                             neighbors=k)
    assert res.transform_history.shape == (B, 10, 4, 4)
    assert_close(res.transform_history, np.stack(refs), atol=1e-5, what="kNN vs dense ICP")
    # The truncation is real (weight beyond the 16 nearest is not exactly 0) but tiny.
    x = torch.tensor(sources[0] @ inits[0][:3, :3].T + inits[0][:3, 3])
    d2 = torch.cdist(x, torch.tensor(target)).square()
    w = torch.softmax(-d2 / (2 * sigma**2), -1).sort(-1, descending=True).values
    beyond = 1 - w[:, :k].sum(-1)
    assert 1e-12 < beyond.mean().item() < 1e-5 and beyond.max().item() < 1e-3
    dense = differentiable_icp(torch.tensor(np.stack(sources)), torch.tensor(target)[None],
                               torch.tensor(np.stack(inits)), iterations=10, sigma=sigma,
                               neighbors=None)
    assert_close(dense.transform_history, np.stack(refs), atol=1e-10, what="dense mode")


@pytest.mark.parametrize("neighbors", [None, 6, 1])
def test_icp_gradcheck_tiny_case(neighbors):
    g = torch.Generator().manual_seed(4)
    source = torch.rand(1, 12, 3, generator=g, dtype=torch.float64)
    target = (source[:, :10] + 0.05 * torch.randn(1, 10, 3, generator=g, dtype=torch.float64))
    target = target.clone().requires_grad_(True)
    init = torch.eye(4, dtype=torch.float64)[None].clone()
    init[0, :3, 3] = torch.tensor([0.03, -0.02, 0.01], dtype=torch.float64)
    init[0, :3, :3] = torch.tensor(Rotation.from_rotvec([0.05, -0.03, 0.04]).as_matrix())
    init.requires_grad_(True)
    source.requires_grad_(True)

    def f(src, tgt, T0):
        res = differentiable_icp(src, tgt, T0, iterations=3, sigma=0.3, neighbors=neighbors)
        return res.transform, res.rmse

    assert torch.autograd.gradcheck(f, (source, target, init), eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.fixture(scope="module")
def fibula_sample(shared_data):
    mesh = read_mesh(FIBULA_STL).to_trimesh()
    points = np.asarray(mesh.sample(4096, seed=0))
    other = np.asarray(mesh.sample(4096, seed=1))
    norm = Normalization.from_ct(points)
    return norm, norm.points_to_model(points), norm.points_to_model(other)


def _start_poses(scale, count=4, seed=5):
    """Perturbations of 10-20 degrees about random axes and 10 mm, in model units."""
    rng = np.random.default_rng(seed)
    poses, angles = [], []
    for _ in range(count):
        angle = rng.uniform(10.0, 20.0)
        axis = rng.normal(size=3)
        direction = rng.normal(size=3)
        P = np.eye(4)
        rotvec = np.deg2rad(angle) * axis / np.linalg.norm(axis)
        P[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
        P[:3, 3] = 10.0 * direction / np.linalg.norm(direction) / scale
        poses.append(P)
        angles.append(angle)
    return np.stack(poses), angles


def _errors(T, scale):
    """Rotation error (deg) and translation error at the bone centre (mm) w.r.t. the identity."""
    rot = np.rad2deg(Rotation.from_matrix(T[:, :3, :3]).magnitude())
    return rot, np.linalg.norm(T[:, :3, 3], axis=1) * scale


def test_soft_icp_converges_on_the_real_fibula(fibula_sample):
    """The fibula sample (4096 points, sigma = 5e-3 normalised = 2 mm) moved 10-20 deg / 10 mm
    back onto itself. Point-to-point ICP converges linearly on a long bone: K = 25 brings 10-20
    deg to within about 0.3 deg, K = 50 to the soft fixed point (0.03 deg, 0.01 mm here)."""
    norm, points, _ = fibula_sample
    P, angles = _start_poses(norm.scale)
    B = len(P)
    src = torch.tensor(points)[None].expand(B, -1, -1)
    res = differentiable_icp(src, torch.tensor(points)[None], torch.tensor(P), iterations=50,
                             sigma=5e-3, neighbors=16)
    rot, trans = _errors(res.transform.numpy(), norm.scale)
    assert (rot < 0.1).all(), f"rotation errors {rot} deg from starts {angles}"
    assert (trans < 0.1).all(), f"translation errors {trans} mm"
    start_rot, _ = _errors(P, norm.scale)
    hist_rot = np.rad2deg(Rotation.from_matrix(
        res.transform_history[:, 24, :3, :3].numpy()).magnitude())
    assert (hist_rot < start_rot / 5).all()  # after the paper's K = 25 already > 5x better
    assert res.rmse_history.shape == (B, 50) and (res.rmse.numpy() * norm.scale < 1.0).all()


def test_icp_with_an_independent_sample_of_the_real_fibula(fibula_sample):
    """With an independent sample of the surface soft ICP stops at the sampling-noise floor
    (measured 0.13-0.27 deg, 0.1-0.3 mm)."""
    norm, points, other = fibula_sample
    P, _ = _start_poses(norm.scale, count=2, seed=6)
    target = torch.tensor(points)[None]
    soft = differentiable_icp(torch.tensor(other)[None].expand(2, -1, -1), target,
                              torch.tensor(P), iterations=60, sigma=5e-3, neighbors=16)
    rot, trans = _errors(soft.transform.numpy(), norm.scale)
    assert (rot < 0.5).all() and (trans < 0.5).all(), (rot, trans)


def test_icp_options_and_errors():
    src = torch.rand(2, 50, 3, dtype=torch.float64)
    tgt = torch.rand(2, 60, 3, dtype=torch.float64)
    res = differentiable_icp(src, tgt, iterations=0)
    assert torch.equal(res.transform, torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
    assert res.transform_history.shape == (2, 0, 4, 4)
    early = differentiable_icp(src, tgt, iterations=200, sigma=0.05, rel_tol=1e-6)
    assert early.transform_history.shape[1] < 200 and bool(early.converged.all())
    weighted = differentiable_icp(src, tgt, iterations=2, sigma=0.05,
                                  source_weights=torch.ones(2, 50, dtype=torch.float64))
    plain = differentiable_icp(src, tgt, iterations=2, sigma=0.05)
    assert_close(weighted.transform, plain.transform, atol=1e-12)
    for kwargs in ({"sigma": 0.0},
                   {"init_transform": torch.eye(4)}, {"source_weights": torch.ones(2, 49)}):
        with pytest.raises(ValueError):
            differentiable_icp(src, tgt, **kwargs)
    with pytest.raises(ValueError):
        differentiable_icp(src, torch.rand(3, 60, 3, dtype=torch.float64))
