"""Point ops against naive references: FPS, kNN, gather, KD-tree Chamfer vs brute-force cdist."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from comreg_core.model.ops import (
    KNNIndex,
    chamfer_l1,
    furthest_point_sample,
    gather_points,
    knn,
    make_transform,
    nearest_distances,
    quaternion_to_matrix,
    safe_norm,
    subsample,
    transform_points,
)
from tests.helpers import assert_close


def naive_fps(points: np.ndarray, n: int, start: int) -> np.ndarray:
    """Textbook farthest point sampling in float64."""
    chosen = [start]
    nearest = np.linalg.norm(points - points[start], axis=1)
    for _ in range(n - 1):
        nxt = int(np.argmax(nearest))
        chosen.append(nxt)
        nearest = np.minimum(nearest, np.linalg.norm(points - points[nxt], axis=1))
    return np.array(chosen)


@pytest.mark.parametrize("n_points,n", [(3000, 200), (257, 64)])
def test_fps_fpsample_is_exact_fps_from_its_first_sample(n_points, n):
    rng = np.random.default_rng(0)
    pts = torch.tensor(rng.random((2, n_points, 3)), dtype=torch.float32)
    idx = furthest_point_sample(pts, n, start_index=0, backend="fpsample")
    assert idx.shape == (2, n) and idx.dtype == torch.int64
    for b in range(2):
        ref = naive_fps(pts[b].double().numpy(), n, int(idx[b, 0]))
        np.testing.assert_array_equal(idx[b].numpy(), ref)
        assert len(set(idx[b].tolist())) == n


def test_fps_torch_backend_starts_at_start_index_and_matches_reference():
    rng = np.random.default_rng(1)
    pts = torch.tensor(rng.random((2, 500, 3)))
    idx = furthest_point_sample(pts, 50, start_index=7, backend="torch")
    for b in range(2):
        np.testing.assert_array_equal(idx[b].numpy(), naive_fps(pts[b].numpy(), 50, 7))


def test_fps_deterministic_with_fixed_start_and_reproducible_random_start():
    pts = torch.rand(3, 1000, 3, generator=torch.Generator().manual_seed(0))
    a = furthest_point_sample(pts, 100, 0)
    assert torch.equal(a, furthest_point_sample(pts, 100, 0))
    torch.manual_seed(5)
    r1 = furthest_point_sample(pts, 100, None)
    torch.manual_seed(5)
    r2 = furthest_point_sample(pts, 100, None)
    assert torch.equal(r1, r2)
    assert furthest_point_sample(pts, 1000, 0).shape == (3, 1000)
    assert subsample(pts, 2000) is pts and subsample(pts, 10).shape == (3, 10, 3)


def test_fps_rejects_bad_input():
    with pytest.raises(ValueError):
        furthest_point_sample(torch.rand(10, 3), 4)
    with pytest.raises(ValueError):
        furthest_point_sample(torch.rand(1, 10, 3), 11)
    with pytest.raises(ValueError):
        furthest_point_sample(torch.rand(1, 10, 3), 4, start_index=10)


@pytest.mark.parametrize("n,m,k", [(3000, 2500, 8), (60, 80, 5)])  # KD-tree path, dense path
def test_knn_matches_brute_force(n, m, k):
    g = torch.Generator().manual_seed(2)
    q, r = torch.rand(2, n, 3, generator=g), torch.rand(2, m, 3, generator=g)
    idx = knn(q, r, k)
    ref = torch.cdist(q.double(), r.double()).argsort(-1)[..., :k]
    assert idx.shape == (2, n, k)
    assert torch.equal(idx, ref)
    shared = KNNIndex(r[:1]).query(q, k)  # one reference cloud for both query clouds
    assert torch.equal(shared[0], ref[0])
    assert torch.equal(shared[1], torch.cdist(q[1:].double(), r[:1].double()).argsort(-1)[0, :, :k])
    with pytest.raises(ValueError):
        knn(q, r, m + 1)
    with pytest.raises(ValueError):
        knn(q, torch.rand(3, m, 3), 1)


def test_gather_points():
    pts = torch.arange(2 * 5 * 2, dtype=torch.float32).reshape(2, 5, 2)
    idx = torch.tensor([[[0, 4]], [[3, 3]]])
    out = gather_points(pts, idx)
    assert out.shape == (2, 1, 2, 2)
    assert torch.equal(out[0, 0], pts[0, [0, 4]]) and torch.equal(out[1, 0], pts[1, [3, 3]])
    assert torch.equal(gather_points(pts[:1], idx)[1, 0], pts[0, [3, 3]])


def brute_force_chamfer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    d = torch.cdist(a, b)  # B N M, float64
    return d.min(2).values.mean(1) + d.min(1).values.mean(1)


def test_kdtree_chamfer_equals_brute_force_values_and_gradients_float64():
    g = torch.Generator().manual_seed(3)
    a = torch.rand(2, 3000, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(2, 2200, 3, generator=g, dtype=torch.float64, requires_grad=True)
    value = chamfer_l1(a, b)
    ga, gb = torch.autograd.grad(value.sum(), (a, b))
    a2, b2 = a.detach().clone().requires_grad_(True), b.detach().clone().requires_grad_(True)
    ref = brute_force_chamfer(a2, b2)
    ra, rb = torch.autograd.grad(ref.sum(), (a2, b2))
    assert_close(value.detach(), ref.detach(), atol=1e-12, what="Chamfer value")
    assert_close(ga, ra, atol=1e-12, what="Chamfer gradient wrt a")
    assert_close(gb, rb, atol=1e-12, what="Chamfer gradient wrt b")


def test_chamfer_of_identical_clouds_is_zero_with_finite_gradient():
    a = torch.rand(1, 100, 3, requires_grad=True)
    value = chamfer_l1(a, a.detach().clone())
    value.sum().backward()
    assert float(value.detach()) == 0.0 and torch.isfinite(a.grad).all()
    assert nearest_distances(a, a).shape == (1, 100)


def test_safe_norm():
    x = torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]], requires_grad=True)
    n = safe_norm(x)
    n.sum().backward()
    assert n.tolist() == [5.0, 0.0]
    assert_close(x.grad, [[0.6, 0.8, 0.0], [0.0, 0.0, 0.0]], atol=1e-7)


def test_quaternion_and_transform_helpers_match_scipy():
    rng = np.random.default_rng(4)
    rot = Rotation.random(5, random_state=rng)
    xyzw = rot.as_quat()
    wxyz = torch.tensor(np.concatenate([xyzw[:, 3:], xyzw[:, :3]], 1) * 3.0)  # not unit
    assert_close(quaternion_to_matrix(wxyz), rot.as_matrix(), atol=1e-12)
    t = torch.tensor(rng.normal(size=(5, 3)))
    T = make_transform(torch.tensor(rot.as_matrix()), t)
    pts = torch.tensor(rng.normal(size=(5, 7, 3)))
    expected = np.einsum("bij,bnj->bni", rot.as_matrix(), pts.numpy()) + t.numpy()[:, None]
    assert_close(transform_points(T, pts), expected, atol=1e-12)
    assert_close(T[:, 3], np.tile([0, 0, 0, 1.0], (5, 1)), atol=0)
