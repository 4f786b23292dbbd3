"""Point-cloud operations in pure PyTorch (plus KD-trees on the CPU): sampling, neighbours, Chamfer.

Nothing here needs a compiled extension. Index-finding steps (farthest point sampling, k nearest
neighbours) carry no gradient; they run on the CPU with ``fpsample`` / ``pykdtree`` and on a GPU
with plain torch. Every *value* that needs a gradient (distances, gathered points) is recomputed in
torch from the indices, so it is exact and differentiable, and memory stays O(N k) instead of the
O(N M) of a dense distance matrix.

All functions take batched tensors ``(B, N, 3)`` and work on the device of their inputs.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from comreg_core.pointsets import farthest_point_indices

#: Above this many query x reference pairs a CPU neighbour search uses a KD-tree instead of cdist.
_DENSE_PAIRS_CPU = 1 << 18
#: Pairs per chunk of a GPU (or dense) neighbour search: bounds the temporary distance matrix.
_CHUNK_PAIRS = 1 << 26
#: Use the GPU code paths (torch FPS loop, chunked cdist kNN) on the CPU as well; tests set it to
#: exercise those paths on machines without a GPU.
FORCE_TORCH_BACKENDS = False


def check_points(points: Tensor, name: str = "points", dims: int = 3) -> Tensor:
    """Raise ``ValueError`` unless ``points`` is a floating ``(B, N, dims)`` tensor with N >= 1."""
    if not isinstance(points, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(points).__name__}")
    if points.ndim != 3 or points.shape[-1] != dims or points.shape[1] < 1:
        raise ValueError(f"{name} must have shape (B, N, {dims}) with N >= 1, got "
                         f"{tuple(points.shape)}")
    if not points.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got {points.dtype}")
    return points


def _check_batches(query: Tensor, ref: Tensor) -> None:
    if ref.shape[0] not in (1, query.shape[0]):
        raise ValueError(f"batch sizes do not match: {query.shape[0]} query clouds and "
                         f"{ref.shape[0]} reference clouds (use 1 reference cloud or one each)")


# ----------------------------------------------------------------------------------------------
# Gather
# ----------------------------------------------------------------------------------------------

def gather_points(points: Tensor, idx: Tensor) -> Tensor:
    """Pick rows of each cloud by index (differentiable in ``points``).

    Args:
        points: ``(B, M, C)`` values per point (a reference batch of 1 is shared by all of idx).
        idx: ``(B, ...)`` int64 indices into dimension 1 of ``points``.

    Returns:
        ``(B, ..., C)``: ``out[b, ...] = points[b, idx[b, ...]]``.
    """
    if points.ndim != 3:
        raise ValueError(f"points must have shape (B, M, C), got {tuple(points.shape)}")
    if idx.ndim < 1 or idx.shape[0] < 1:
        raise ValueError(f"idx must have shape (B, ...), got {tuple(idx.shape)}")
    Bp, M, C = points.shape
    B = idx.shape[0]
    if Bp not in (1, B):
        raise ValueError(f"points has batch {Bp} but idx has batch {B}")
    flat = idx.reshape(B, -1).long()
    if Bp == 1:
        out = points[0].index_select(0, flat.reshape(-1))  # B*K C
    else:
        base = torch.arange(B, device=idx.device).unsqueeze(1) * M  # B 1
        out = points.reshape(B * M, C).index_select(0, (flat + base).reshape(-1))  # B*K C
    return out.reshape(*idx.shape, C)


# ----------------------------------------------------------------------------------------------
# Farthest point sampling
# ----------------------------------------------------------------------------------------------

def furthest_point_sample(points: Tensor, n: int, start_index: int | None = 0,
                          backend: str = "auto") -> Tensor:
    """Farthest point sampling: indices of ``n`` well-spread points of each cloud (no gradient).

    Args:
        points: ``(B, N, 3)``.
        n: number of samples, ``1 <= n <= N``.
        start_index: fixes the start of every cloud's sampling, so the result is deterministic;
            ``None`` draws one start per cloud from torch's global generator (reproducible under
            ``torch.manual_seed``). Models pass 0 in eval mode and None in training. The torch
            backend starts exactly at this index; fpsample 1.0's bucket FPS applies it after its
            internal KD reordering, so its first sample is another (but fixed) point: the result
            is still exact FPS from its first sample.
        backend: ``"fpsample"`` (CPU, bucket-based exact FPS), ``"torch"`` (a loop of n steps,
            any device) or ``"auto"`` (fpsample on the CPU, torch elsewhere).

    Returns:
        ``(B, n)`` int64 indices on the device of ``points``.
    """
    check_points(points)
    B, N, _ = points.shape
    if not 1 <= n <= N:
        raise ValueError(f"cannot sample {n} points from clouds of {N}")
    if start_index is None:
        starts = torch.randint(0, N, (B,)).tolist()
    else:
        if not 0 <= start_index < N:
            raise ValueError(f"start_index {start_index} is outside 0..{N - 1}")
        starts = [int(start_index)] * B
    if backend == "auto":
        use_fpsample = points.device.type == "cpu" and N >= 2 and not FORCE_TORCH_BACKENDS
        backend = "fpsample" if use_fpsample else "torch"
    if n == N:
        return torch.arange(N, device=points.device).expand(B, N).clone()
    if backend == "torch":
        return _fps_torch(points.detach(), n, torch.tensor(starts, device=points.device))
    if backend != "fpsample":
        raise ValueError(f"unknown FPS backend {backend!r}")
    pts = points.detach().to("cpu", torch.float32).numpy()
    out = np.empty((B, n), dtype=np.int64)
    for b in range(B):
        out[b] = farthest_point_indices(pts[b], n, start=starts[b])
    return torch.from_numpy(out).to(points.device)


def _fps_torch(points: Tensor, n: int, starts: Tensor) -> Tensor:
    B, N, _ = points.shape
    batch = torch.arange(B, device=points.device)
    idx = torch.empty(B, n, dtype=torch.long, device=points.device)
    nearest = torch.full((B, N), float("inf"), dtype=points.dtype, device=points.device)  # B N
    current = starts.long()
    for i in range(n):
        idx[:, i] = current
        d = (points - points[batch, current].unsqueeze(1)).square().sum(-1)  # B N
        nearest = torch.minimum(nearest, d)
        current = nearest.argmax(-1)
    return idx


def subsample(points: Tensor, n: int, start_index: int | None = 0) -> Tensor:
    """The FPS subset of ``n`` points of each cloud (all points when ``N <= n``); ``(B, n', 3)``."""
    check_points(points)
    if points.shape[1] <= n:
        return points
    return gather_points(points, furthest_point_sample(points, n, start_index))


# ----------------------------------------------------------------------------------------------
# k nearest neighbours
# ----------------------------------------------------------------------------------------------

class KNNIndex:
    """Nearest-neighbour search structure over reference clouds, built once, queried many times.

    On the CPU each reference cloud gets a ``pykdtree`` KD-tree (small problems use a dense
    ``cdist``); on other devices the search is a chunked ``cdist`` + ``topk``. Indices only: no
    gradient. Args: ``ref`` ``(Br, M, 3)``; a single reference cloud serves every query cloud.
    """

    def __init__(self, ref: Tensor):
        check_points(ref, "ref")
        self.ref = ref.detach()
        self._trees: list | None = None

    def _kdtrees(self):
        if self._trees is None:
            from pykdtree.kdtree import KDTree

            ref = self.ref.to("cpu", torch.float32).numpy()
            self._trees = [KDTree(np.ascontiguousarray(r)) for r in ref]
        return self._trees

    def query(self, query: Tensor, k: int) -> Tensor:
        """Indices of the ``k`` nearest reference points of every query point, nearest first.

        Args:
            query: ``(B, N, 3)``; B must equal the reference batch or the reference batch be 1.
            k: neighbours per point, ``1 <= k <= M``.

        Returns:
            ``(B, N, k)`` int64 indices into the reference cloud, on the device of ``query``.
        """
        check_points(query, "query")
        _check_batches(query, self.ref)
        B, N, _ = query.shape
        M = self.ref.shape[1]
        if not 1 <= k <= M:
            raise ValueError(f"k = {k} neighbours requested from reference clouds of {M} points")
        query = query.detach()
        if query.device.type == "cpu" and N * M > _DENSE_PAIRS_CPU and not FORCE_TORCH_BACKENDS:
            trees = self._kdtrees()
            q = query.to(torch.float32).numpy()
            out = np.empty((B, N, k), dtype=np.int64)
            for b in range(B):
                tree = trees[b if len(trees) > 1 else 0]
                _, idx = tree.query(np.ascontiguousarray(q[b]), k=k)
                out[b] = idx.reshape(N, k)
            return torch.from_numpy(out)
        return _knn_dense(query, self.ref.to(query.dtype), k)


def _knn_dense(query: Tensor, ref: Tensor, k: int) -> Tensor:
    B, N, _ = query.shape
    M = ref.shape[1]
    ref = ref.expand(B, -1, -1)
    chunk = max(1, _CHUNK_PAIRS // max(M, 1))
    parts = []
    for s in range(0, N, chunk):
        d = torch.cdist(query[:, s:s + chunk], ref)  # B n M
        parts.append(d.topk(k, dim=-1, largest=False, sorted=True).indices)
    return torch.cat(parts, dim=1)


def knn(query: Tensor, ref: Tensor, k: int) -> Tensor:
    """Indices ``(B, N, k)`` of the k nearest points of ``ref`` ``(B|1, M, 3)`` for each point of
    ``query`` ``(B, N, 3)``, nearest first (no gradient); see :class:`KNNIndex`."""
    return KNNIndex(ref).query(query, k)


# ----------------------------------------------------------------------------------------------
# Distances and Chamfer
# ----------------------------------------------------------------------------------------------

def safe_norm(x: Tensor, dim: int = -1) -> Tensor:
    """Euclidean norm along ``dim`` whose gradient is 0 (not NaN) where the vector is exactly 0.

    Values are exact everywhere; gradients are exact wherever the norm is differentiable.
    """
    sq = x.square().sum(dim)
    positive = sq > 0
    safe_sq = torch.where(positive, sq, torch.ones_like(sq))
    return torch.where(positive, safe_sq.sqrt(), torch.zeros_like(sq))


def nearest_distances(a: Tensor, b: Tensor) -> Tensor:
    """Distance from every point of ``a`` to its nearest point of ``b`` (exact, differentiable).

    Args:
        a: ``(B, N, 3)``.
        b: ``(B, M, 3)`` (or ``(1, M, 3)``, shared).

    Returns:
        ``(B, N)`` unsquared distances; the nearest index comes from :func:`knn` (no gradient), the
        distance is recomputed from the gathered point, so gradients reach ``a`` and ``b``.
    """
    check_points(a, "a")
    check_points(b, "b")
    _check_batches(a, b)
    idx = knn(a, b, 1)[..., 0]  # B N
    nearest = gather_points(b, idx)  # B N 3
    return safe_norm(a - nearest, dim=-1)


def chamfer_l1(a: Tensor, b: Tensor) -> Tensor:
    """Symmetric L1 Chamfer distance of the ComReg paper, per cloud.

    ``CD(a, b) = mean_i min_j ||a_i - b_j|| + mean_j min_i ||b_j - a_i||`` (unsquared distances,
    the two directions summed, not averaged).

    Args:
        a: ``(B, N, 3)``.
        b: ``(B, M, 3)``.

    Returns:
        ``(B,)`` Chamfer distances, differentiable in ``a`` and ``b``.
    """
    check_points(a, "a")
    check_points(b, "b")
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"batch sizes differ: {a.shape[0]} vs {b.shape[0]}")
    return nearest_distances(a, b).mean(1) + nearest_distances(b, a).mean(1)


# ----------------------------------------------------------------------------------------------
# Rigid transforms as tensors
# ----------------------------------------------------------------------------------------------

def quaternion_to_matrix(quaternion: Tensor) -> Tensor:
    """Rotation matrices of unit quaternions ``(..., 4)`` in (w, x, y, z) order; ``(..., 3, 3)``.

    The quaternion is normalised here (its norm floored at 1e-12, so the output stays finite).
    """
    if quaternion.shape[-1] != 4:
        raise ValueError(f"quaternions must have shape (..., 4), got {tuple(quaternion.shape)}")
    q = quaternion / quaternion.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def make_transform(rotation: Tensor, translation: Tensor) -> Tensor:
    """Homogeneous ``(..., 4, 4)`` matrices from rotations ``(..., 3, 3)`` and translations
    ``(..., 3)`` (differentiable)."""
    if rotation.shape[-2:] != (3, 3) or translation.shape[-1] != 3:
        raise ValueError(f"need rotations (..., 3, 3) and translations (..., 3), got "
                         f"{tuple(rotation.shape)} and {tuple(translation.shape)}")
    top = torch.cat([rotation, translation.unsqueeze(-1)], dim=-1)  # ... 3 4
    bottom = torch.zeros_like(top[..., :1, :])  # ... 1 4
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)


def transform_points(transform: Tensor, points: Tensor) -> Tensor:
    """Apply ``(B, 4, 4)`` transforms to ``(B, N, 3)`` points: ``p' = R p + t``; ``(B, N, 3)``."""
    check_points(points)
    if transform.ndim != 3 or transform.shape[-2:] != (4, 4):
        raise ValueError(f"transform must have shape (B, 4, 4), got {tuple(transform.shape)}")
    R = transform[:, :3, :3]  # B 3 3
    t = transform[:, :3, 3]  # B 3
    return points @ R.transpose(1, 2) + t.unsqueeze(1)


def rotation_6d_to_matrix(x: Tensor) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` of the continuous 6-D representation ``(..., 6)`` (Zhou
    et al., CVPR 2019): the two 3-vectors are orthonormalised by Gram-Schmidt and become the
    first two *columns*; the third is their cross product."""
    if x.shape[-1] != 6:
        raise ValueError(f"6-D rotations must have shape (..., 6), got {tuple(x.shape)}")
    a, b = x[..., :3], x[..., 3:]
    e1 = a / a.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b = b - (e1 * b).sum(-1, keepdim=True) * e1
    e2 = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    e3 = torch.cross(e1, e2, dim=-1)
    return torch.stack([e1, e2, e3], dim=-1)


def matrix_to_quaternion(rotation: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` (w, x, y, z; w >= 0) of rotation matrices ``(..., 3, 3)``
    (Shepperd's method: the largest of the four squared components is taken first)."""
    if rotation.shape[-2:] != (3, 3):
        raise ValueError(f"rotations must have shape (..., 3, 3), got {tuple(rotation.shape)}")
    m = rotation
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    squares = torch.stack([1 + tr, 1 + 2 * m[..., 0, 0] - tr, 1 + 2 * m[..., 1, 1] - tr,
                           1 + 2 * m[..., 2, 2] - tr], dim=-1)  # ... 4, = 4 q_k^2
    k = squares.argmax(dim=-1, keepdim=True)  # ... 1
    off = torch.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                       m[..., 1, 0] - m[..., 0, 1], m[..., 0, 1] + m[..., 1, 0],
                       m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]], dim=-1)
    # 4 q_k q_j for each choice of k (rows: k = w, x, y, z; columns: j = w, x, y, z)
    products = torch.stack([
        torch.stack([squares[..., 0], off[..., 0], off[..., 1], off[..., 2]], -1),
        torch.stack([off[..., 0], squares[..., 1], off[..., 3], off[..., 4]], -1),
        torch.stack([off[..., 1], off[..., 3], squares[..., 2], off[..., 5]], -1),
        torch.stack([off[..., 2], off[..., 4], off[..., 5], squares[..., 3]], -1),
    ], dim=-2)  # ... 4 4
    q = products.gather(-2, k.unsqueeze(-1).expand(*k.shape[:-1], 1, 4)).squeeze(-2)  # ... 4
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(q[..., :1] < 0, -q, q)
