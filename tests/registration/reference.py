"""Numpy references of the compiled kernels (``comreg_core/registration/geometry/kernels.py``): the
code they replaced, kept here to test them against."""

from __future__ import annotations

import numpy as np

from comreg_core.registration.geometry.icp import MIN_PAIRS


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
                                ) -> np.ndarray:
    """Exact closest point of each point ``p[i]`` on triangle ``(a[i], b[i], c[i])`` (all
    ``(..., 3)``), by the Voronoi-region tests of Ericson, *Real-Time Collision Detection*, 5.1.5,
    vectorised (the code ``mesh_kernels.closest_on_candidates`` replaced): its reference."""
    dot = lambda u, v: np.einsum("...j,...j->...", u, v)  # noqa: E731
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        out = a + ab * v[..., None] + ac * w[..., None]  # interior (face region)
        # edge regions (each overrides the face region where it applies)
        t_bc = np.clip((d4 - d3) / ((d4 - d3) + (d5 - d6)), 0, 1)
        on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        out = np.where(on_bc[..., None], b + (c - b) * t_bc[..., None], out)
        t_ac = np.clip(d2 / (d2 - d6), 0, 1)
        on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out = np.where(on_ac[..., None], a + ac * t_ac[..., None], out)
        t_ab = np.clip(d1 / (d1 - d3), 0, 1)
        on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out = np.where(on_ab[..., None], a + ab * t_ab[..., None], out)
    # vertex regions
    out = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, out)
    return out


def numpy_pose_steps(moved, q, nrm, d, trim_fraction, T):
    """:func:`~comreg_core.registration.geometry.kernels.pose_steps` in numpy (the code the kernel
    replaced): the reference it is tested against."""
    from scipy.spatial.transform import Rotation

    m = len(moved)
    matched = np.isfinite(d)
    out = np.zeros((m, 4))
    out[:, 0], out[:, 3] = np.nan, matched.mean(axis=1)
    if trim_fraction > 0:  # of the matched pairs, the farthest trim_fraction left out
        count = matched.sum(axis=1)
        keep = np.minimum(count, np.maximum(MIN_PAIRS, count - (trim_fraction * count
                                                                ).astype(np.int64)))
        limit = np.sort(np.where(matched, d, np.inf), axis=1)[
            np.arange(m), np.maximum(keep - 1, 0)][:, None]  # m 1
        w = (matched & (d <= limit)).astype(np.float64)  # m n
    else:
        w = matched.astype(np.float64)
    ok = np.flatnonzero(w.sum(1) >= MIN_PAIRS)
    moved, q, nrm, w, Ta = moved[ok], q[ok], nrm[ok], w[ok], T[ok]
    q, nrm = np.where(w[..., None] > 0, q, 0.0), np.where(w[..., None] > 0, nrm, 0.0)
    r = np.einsum("bni,bni->bn", moved - q, nrm)  # signed distance to the plane
    out[ok, 0] = np.sqrt((w * r * r).sum(1) / w.sum(1))
    c = (w[..., None] * moved).sum(1) / w.sum(1)[:, None]
    A = np.concatenate([np.cross(moved - c[:, None], nrm), nrm], axis=2)
    Aw = A * w[..., None]
    H = Aw.transpose(0, 2, 1) @ A
    g = (Aw.transpose(0, 2, 1) @ r[..., None])[..., 0]
    damp = (1e-6 * np.trace(H, axis1=1, axis2=2)[:, None, None] + 1e-12) * np.eye(6)
    x = np.linalg.solve(H + damp, -g[..., None])[..., 0]
    step = np.tile(np.eye(4), (len(ok), 1, 1))
    step[:, :3, :3] = Rotation.from_rotvec(x[:, :3]).as_matrix()
    step[:, :3, 3] = c - np.einsum("bij,bj->bi", step[:, :3, :3], c) + x[:, 3:]
    T[ok] = step @ Ta
    out[ok, 1], out[ok, 2] = np.linalg.norm(x[:, :3], axis=1), np.linalg.norm(x[:, 3:], axis=1)
    return out
