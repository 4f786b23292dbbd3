"""Benchmark: the pose search on its own (issue 8): success, flips, ambiguity
flags and latency, against plain ICP from the same coarse starts.

``.venv/bin/python -m tests.benchmarks search`` (defaults) or
``.venv/bin/python -m tests.benchmarks.bench_search [--trials 50] [--seed 0]
[--completion none|ideal]``

Needs no trained network: fresh simulated sweeps of the real fibula
(:func:`~comreg_core.evaluation.simulated_us_clouds`, 20,000 points each) are put into a random
"US" frame (known ``T_ct_us``), and coarse poses are made from the ground truth:

- ``near``: the truth turned by 15 deg about a random axis through the sweep's centroid and
  shifted by 10 mm in a random direction (a coarse pose at the edge of ICP's basin);
- ``flip``: that, flipped end to end (180 deg about a random short axis of the bone through its
  centre): the paper's flipped results;
- ``spin``: that, turned about the bone's long axis by U(45, 315) deg.

From each start: ``plain-icp`` = the network's own ICP (point-to-point soft ICP, 25
iterations, sigma 5e-3, 16 neighbours, 2048 US points against the 2048-point FPS subset of a
4096-point CT cloud, as the ``cpu`` preset) and the pose search (default settings, N_c
= 2048 and 4096 US points; its point-to-point ICP modes were dropped in issue 17: they crawled
along the shaft where point-to-plane converges). Printed per
start kind: success (RTE < 2 mm and RRE < 2 deg), flips (RRE > 90 deg), share flagged
ambiguous, silent failures (failed and not flagged), and the search's latency (median, 90th
percentile) on this machine's CPU. ``--completion ideal`` also hands the search a perfect
completion (the CT in the US frame), which adds the principal-axes solve.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

KINDS = ("near", "flip", "spin")


def _errors(T, truth, points):
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm

    return translation_error_mm(T, truth, points.mean(axis=0)), rotation_error_deg(T, truth)


def _cases(clouds, bone_centre, bone_axes, seed):
    """(kind, us points, truth T_ct_us, start T_ct_us) per cloud and kind."""
    from scipy.spatial.transform import Rotation

    from comreg_core.registration.search.search import rotation_about
    from comreg_core.transforms import apply_transform, invert_rigid

    rng = np.random.default_rng(seed)
    cases = []
    for cloud in clouds:
        T_us_ct = np.eye(4)
        T_us_ct[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T_us_ct[:3, 3] = rng.uniform(-100.0, 100.0, 3)
        us, truth = apply_transform(T_us_ct, cloud), invert_rigid(T_us_ct)
        for kind in KINDS:
            axis, direction = rng.normal(size=3), rng.normal(size=3)
            shift = np.eye(4)
            shift[:3, 3] = 10.0 * direction / np.linalg.norm(direction)
            P = shift @ rotation_about(cloud.mean(axis=0), axis, math.radians(15.0))
            if kind == "flip":
                a = rng.uniform(0.0, 2.0 * math.pi)
                short = math.cos(a) * bone_axes[:, 1] + math.sin(a) * bone_axes[:, 2]
                P = rotation_about(bone_centre, short, math.pi) @ P
            elif kind == "spin":
                P = rotation_about(bone_centre, bone_axes[:, 0],
                                   math.radians(rng.uniform(45.0, 315.0))) @ P
            cases.append((kind, us, truth, P @ truth))
    return cases


def _plain_icp(us, start, ct_subset, norm):
    """The network's ICP (cpu preset settings) from ``start``."""
    import torch

    from comreg_core.model.diff_icp import differentiable_icp
    from comreg_core.model.ops import subsample
    from comreg_core.transforms import orthonormalize

    src = subsample(torch.from_numpy(norm.points_to_model(us)).float()[None], 2048, 0)
    init = torch.from_numpy(norm.transform_to_model(start)).float()[None]
    with torch.no_grad():
        icp = differentiable_icp(src, ct_subset, init, iterations=25, sigma=5e-3, neighbors=16)
    return norm.transform_to_mm(orthonormalize(icp.transform[0].double().numpy()))


def main(argv: list[str] | None = None) -> None:
    import torch

    from comreg_core.evaluation.evaluate import simulated_us_clouds
    from comreg_core.registration import (CTSurface, SearchConfig, is_flip, is_success,
                                          search_poses)
    from comreg_core.normalization import Normalization
    from comreg_core.model.ops import subsample
    from comreg_core.transforms import apply_transform, invert_rigid
    from tests.helpers import FIBULA_STL

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=50, help="simulated sweeps (x 3 start kinds)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--completion", choices=("none", "ideal"), default="none")
    p.add_argument("--shaft-rotations", type=int, default=SearchConfig.shaft_rotations)
    p.add_argument("--no-4096", action="store_true", help="skip the N_c = 4096 run")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)

    surface = CTSurface(FIBULA_STL)
    norm = Normalization.from_ct(surface.vertices)
    target = surface.cloud(SearchConfig.target_points)
    ct_cloud, _ = CTSurface(FIBULA_STL, sample_seed=1).samples(4096)
    ct_subset = subsample(torch.from_numpy(norm.points_to_model(ct_cloud)).float()[None], 2048, 0)
    whole, _ = CTSurface(FIBULA_STL, sample_seed=2).samples(8192)
    start = time.perf_counter()
    clouds = simulated_us_clouds(surface, args.trials, seed=args.seed)
    print(f"{args.trials} simulated sweeps of the fibula in {time.perf_counter() - start:.0f} s "
          f"(median {int(np.median([len(c) for c in clouds]))} points); torch threads "
          f"{torch.get_num_threads()}")
    cases = _cases(clouds, target.centre, target.axes, args.seed)

    variants = {"plain-icp": None}
    rotations = args.shaft_rotations
    variants["search-2048"] = SearchConfig(icp_points=2048, shaft_rotations=rotations)
    if not args.no_4096:
        variants["search-4096"] = SearchConfig(icp_points=4096,
                                                  shaft_rotations=rotations)
    rows = {name: {kind: [] for kind in KINDS} for name in variants}
    for name, config in variants.items():
        for kind, us, truth, T0 in cases:
            completion = None
            if args.completion == "ideal":
                completion = apply_transform(invert_rigid(truth), whole)
            t0 = time.perf_counter()
            if config is None:
                T, flagged, refined = _plain_icp(us, T0, ct_subset, norm), None, 1
            else:
                res = search_poses(us, T0, target, completion, config)
                T, flagged, refined = res.T_ct_us, res.ambiguous, len(res.candidates)
            seconds = time.perf_counter() - t0
            rte, rre = _errors(T, truth, us)
            rows[name][kind].append((is_success(rte, rre), is_flip(rre), flagged, seconds,
                                     refined))

    print(f"\nstarts: truth + 15 deg / 10 mm ('near'), flipped end to end ('flip'), turned "
          f"45-315 deg about the shaft ('spin'); completion: {args.completion}; "
          f"{rotations} shaft rotations")
    print(f"{'method':>16} {'start':>5} {'success':>8} {'flips':>6} {'ambig.':>7} "
          f"{'silent fail':>11} {'B':>3} {'median s':>9} {'p90 s':>6}")
    for name in variants:
        for kind in KINDS:
            r = rows[name][kind]
            ok = np.array([x[0] for x in r])
            flip = np.array([x[1] for x in r])
            flags = [x[2] for x in r]
            secs = np.array([x[3] for x in r])
            amb = "-" if flags[0] is None else f"{np.mean(flags):.1%}"
            silent = "-" if flags[0] is None else \
                f"{np.mean([not o and not f for o, f in zip(ok, flags)]):.1%}"
            print(f"{name:>16} {kind:>5} {ok.mean():8.1%} {flip.mean():6.1%} {amb:>7} "
                  f"{silent:>11} {r[0][4]:3d} {np.median(secs):9.3f} "
                  f"{np.percentile(secs, 90):6.3f}")


if __name__ == "__main__":
    main()
