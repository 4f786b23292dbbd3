"""Benchmark of the ComReg network on this machine's CPU.

Run: ``.venv/bin/python -m tests.benchmarks.bench_model [--presets cpu paper] [--repeats 3]``

For each preset: parameter count; forward time at batch 4 (eval, no grad); forward + backward time
at batch 4 (train mode, full ComReg loss); inference time at batch 1 with the CT half cached;
peak memory of each measurement (a fresh process each, so peaks do not mix). Then the
differentiable ICP alone: K = 25 iterations, N_c = 4096 points per cloud, batch 1 and 4, forward
and forward + backward. Inputs are samples of the real fibula mesh (a partial "US-like" half for
the source) in normalised coordinates. Times are the *minimum* of ``--repeats`` runs after a
warm-up (the least disturbed run: on a shared machine the median mostly measures the neighbours).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import sys
import time


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _clouds(n_source: int, n_target: int, batch: int, seed: int = 0):
    """Fibula samples in normalised coordinates: partial sources (rotated, shifted), full target."""
    import numpy as np
    import torch
    from scipy.spatial.transform import Rotation

    from comreg_core.io.meshes import read_mesh
    from comreg_core.normalization import Normalization
    from tests.helpers import FIBULA_STL

    mesh = read_mesh(FIBULA_STL).to_trimesh()
    target = np.asarray(mesh.sample(n_target, seed=seed))
    norm = Normalization.from_ct(target)
    rng = np.random.default_rng(seed)
    sources, gts = [], []
    for b in range(batch):
        dense = np.asarray(mesh.sample(3 * n_source, seed=seed + 1 + b))
        normal = rng.normal(size=3)
        side = (dense - dense.mean(0)) @ normal
        partial = dense[side > np.quantile(side, 0.5)][:n_source]  # one side: shadowed half gone
        partial = partial[rng.choice(len(partial), n_source, replace=len(partial) < n_source)]
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.uniform(-0.5, 0.5, 3)).as_matrix()
        T[:3, 3] = rng.uniform(-20, 20, 3)
        sources.append(norm.points_to_model(partial @ T[:3, :3].T + T[:3, 3]))
        gts.append(np.linalg.inv(norm.transform_to_model(T)))
    f = torch.float32
    return (torch.tensor(np.stack(sources), dtype=f), torch.tensor(norm.points_to_model(target),
            dtype=f)[None], torch.tensor(np.stack(gts), dtype=f))


def _timed(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def _measure_model(preset: str, what: str, repeats: int, threads: int, queue) -> None:
    import torch

    if threads:
        torch.set_num_threads(threads)

    from comreg_core.model import ComRegNet, comreg_loss
    from comreg_core.training.config import model_preset

    torch.manual_seed(0)
    cfg = model_preset(preset, {"icp": {"num_points": 4096}} if what == "infer1@4096" else None)
    net = ComRegNet(cfg)
    n_cloud = max(cfg.completion.input_points, cfg.icp.num_points)
    batch = 1 if what.startswith("infer1") else 4
    source, target, gt = _clouds(n_cloud, n_cloud, batch)
    base = _rss_mb()
    if what == "fwd":
        net.eval()

        def run():
            with torch.no_grad():
                net(source, target)
    elif what.startswith("infer1"):
        net.eval()
        with torch.no_grad():
            enc = net.encode_target(target)

        def run():
            with torch.no_grad():
                net(source, enc)
    else:
        net.train()
        # Per-sample ground truth: the complete CT cloud moved into each source frame.
        gt_points = (target - gt[:, :3, 3].unsqueeze(1)) @ gt[:, :3, :3]

        def run():
            net.zero_grad(set_to_none=True)
            out = net(source, target)
            loss = comreg_loss(out.completion.centres, out.completion.dense, gt_points,
                               out.coarse_transform, out.fine_transform, gt, cfg.loss)
            loss.total.backward()
    seconds = _timed(run, repeats)
    queue.put({"seconds": seconds, "peak_mb": _rss_mb(), "base_mb": base,
               "params": sum(p.numel() for p in net.parameters())})


def _measure_icp(batch: int, backward: bool, neighbors: int, repeats: int, threads: int,
                 queue) -> None:
    import torch

    if threads:
        torch.set_num_threads(threads)

    from comreg_core.model import differentiable_icp
    from comreg_core.model.ops import make_transform, quaternion_to_matrix

    source, target, gt = _clouds(4096, 4096, batch)
    base = _rss_mb()
    q = torch.tensor([[1.0, 0.05, -0.03, 0.02]]).repeat(batch, 1).requires_grad_(backward)

    def run():
        init = make_transform(quaternion_to_matrix(q), torch.zeros(batch, 3)) @ gt
        res = differentiable_icp(source, target, init, iterations=25, sigma=5e-3,
                                 neighbors=neighbors)
        if backward:
            res.transform.sum().backward()
    queue.put({"seconds": _timed(run, repeats), "peak_mb": _rss_mb(), "base_mb": base})


def _in_child(target, *args):
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=target, args=(*args, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["cpu", "paper"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    parser.add_argument("--skip-icp", action="store_true")
    args = parser.parse_args(argv)
    import os

    import torch

    from comreg_core.training.config import model_preset

    load = os.getloadavg()[0]
    threads = args.threads or torch.get_num_threads()
    print(f"torch {torch.__version__}, {threads} threads, "
          f"{os.cpu_count()} CPUs, load average {load:.1f} (shared machine: times are "
          f"pessimistic)")
    for preset in args.presets:
        repeats = args.repeats if preset == "cpu" else 1
        rows = {}
        whats = ["fwd", "fwd+bwd", "infer1"]
        if model_preset(preset).icp.num_points != 4096:
            whats.append("infer1@4096")
        for what in whats:
            rows[what] = _in_child(_measure_model, preset, what, repeats, args.threads)
        params = rows["fwd"]["params"]
        print(f"\npreset {preset}: {params / 1e6:.2f} M parameters")
        labels = {"fwd": "forward, batch 4 (eval, no grad)",
                  "fwd+bwd": "forward + backward, batch 4 (train, full loss)",
                  "infer1": "inference, batch 1 (CT half cached)",
                  "infer1@4096": "inference, batch 1, ICP on N_c = 4096"}
        for what, r in rows.items():
            print(f"  {labels[what]:<48} {r['seconds']:8.3f} s   peak RSS {r['peak_mb']:7.0f} MB "
                  f"(+{r['peak_mb'] - r['base_mb']:.0f} MB over the loaded model and inputs)")
    if args.skip_icp:
        return 0
    print("\ndifferentiable ICP, K = 25, N_c = 4096 per cloud, soft:")
    for neighbors in (16, 32):
        for batch in (1, 4):
            for backward in (False, True):
                r = _in_child(_measure_icp, batch, backward, neighbors, args.repeats, args.threads)
                label = (f"k = {neighbors}, batch {batch}, "
                         f"{'forward + backward' if backward else 'forward'}")
                print(f"  {label:<48} {r['seconds']:8.3f} s   peak RSS {r['peak_mb']:7.0f} MB "
                      f"(+{r['peak_mb'] - r['base_mb']:.0f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
