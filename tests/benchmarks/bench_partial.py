"""Benchmark: short sweeps over one face of the bone (issue 21), registered by the pose search
alone and, given pretrained runs, by ComReg and its plain pipeline.

``.venv/bin/python -m tests.benchmarks.bench_partial [--trials 100] [--seed 0]
[--set simulated-fibula,simulated-tibia,real-fibula] [--perturbation paper,full]
[--model fibula=RUN --untrained fibula=RUN0 --model tibia=RUN ...]``; with ``--trust`` the
rows of issue 33 instead (priors, unions of real runs, the verdict with ``p_correct``: see
:mod:`tests.benchmarks.partial_trust`).

Sets:

- ``simulated-fibula`` / ``simulated-tibia``: fresh simulated sweeps (the project's simulator,
  seeds disjoint from training) of the shared fibula CT and of the tibia-like bone of
  ``tests.helpers.tibia_like_mesh``, transverse only, 40-50 mm long (``trajectory.length_mm``),
  over one face (the probe's side drifts by at most 20 deg), never past the bone's ends. The
  tibia-like shaft is an extrusion from 30 to 80 % of its length, so a patch of it fits as well
  anywhere along ~150 mm (no score can choose there: they must be flagged);
  ``simulated-tibia-anatomical`` sweeps its anatomical variant (tapered, rounder distally,
  twisted 30 deg), a shaft that changes along its length as a real tibia's does;
- ``real-fibula``: the shared real fibula sweep (111 B-mode frames) cut into runs of
  consecutive frames whose probe path covers 30-60 mm (non-overlapping), bone points from the
  project's detector, truth = the recorded tracking (itself ~3 mm off: the data's floor).

Every trial moves a sweep by a random rigid pose (``paper``: one axis, +-90 deg, +-100 mm;
``full``: any rotation, up to 500 mm). Success: RTE < 4 mm and RRE < 5 deg (the issue's
criterion for partial sweeps); flips: RRE > 90 deg; unflagged flips: flips not flagged
ambiguous. Latency: median and 90th percentile of the method's own time (machine load stated
by the caller). ``worse``: trials in which the method's chosen score is worse than the search
alone's on the same moved sweep (paired; the network must never make it worse: 0). ``--model BONE=RUN`` adds ``comreg`` / ``comreg-plain`` for that bone's sets (a run
trained on that CT: the shared fibula, or ``tibia_like_mesh()``, e.g. from ``bench_learning
--bone tibia-like``), ``--untrained BONE=RUN0`` the same network at 0 epochs (the control).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

SETS = ("simulated-fibula", "simulated-tibia", "simulated-tibia-anatomical", "real-fibula")
#: The short one-face sweeps of the simulated sets.
PARTIAL_SWEEPS = {"trajectory": {"length_mm": [40.0, 50.0], "side_drift_deg": 20.0,
                                 "longitudinal_probability": 0.0, "end_margin_mm": 0.0,
                                 "n_slices": [100, 250]}}


def real_runs(shared_data, lengths=(30.0, 60.0)) -> list[tuple[np.ndarray, np.ndarray]]:
    """The real fibula sweep's bone points cut into runs of consecutive frames whose probe path
    (image-centre positions) covers ``lengths[0]``-``lengths[1]`` mm; non-overlapping. Each run:
    ``(points (n, 3), beam origins (n, 3))`` in the tracking's (= CT) frame."""
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import extract_us_surface
    from comreg_core.surfaces.us_points import beam_origins

    sweep = read_tracked_sweep(shared_data / "ultrabones100k-fibula")
    points = extract_us_surface(sweep).points
    origins = beam_origins(points.points, sweep.T_ref_image[points.frame_index])
    h, w = sweep.image_shape
    centre = np.array([w * sweep.spacing[0] / 2, h * sweep.spacing[1] / 2, 0.0, 1.0])
    valid = np.flatnonzero(sweep.valid)
    path = (sweep.T_ref_image[valid] @ centre)[:, :3]
    travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    runs, start = [], 0
    target = float(np.mean(lengths))
    while start < len(valid):
        end = int(np.searchsorted(travel, travel[start] + target))
        if end >= len(valid):
            break
        if lengths[0] <= travel[end] - travel[start] <= lengths[1]:
            keep = np.isin(points.frame_index, valid[start:end + 1])
            if keep.sum() >= 200:
                runs.append((points.points[keep], origins[keep]))
        start = end + 1
    return runs


def simulated_runs(ct, count: int, seed: int, config) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` fresh simulated short sweeps of ``ct`` (evaluation seeds, disjoint from
    training): ``(points, beam origins)`` each, CT frame."""
    from comreg_core.evaluation.evaluate import STREAM_CLOUDS, evaluation_rng
    from comreg_core.simulation import BoneModel, simulate_sweep
    from comreg_core.surfaces.us_points import beam_origins

    bone = BoneModel(ct)
    runs = []
    for i in range(count):
        sweep = simulate_sweep(bone, config, evaluation_rng(seed, STREAM_CLOUDS, i))
        poses = sweep.trajectory.T_ct_image[sweep.slice_index]
        runs.append((sweep.points, beam_origins(sweep.points, poses)))
    return runs


def _methods(bone: str, ct, args) -> dict:
    from comreg_core.register import Registrar

    methods = {"search": Registrar.from_ct(ct)}
    runs = {"comreg": dict(a.split("=", 1) for a in args.model),
            "untrained": dict(a.split("=", 1) for a in args.untrained)}
    for label, by_bone in runs.items():
        if bone in by_bone:
            registrar = Registrar.from_run(by_bone[bone], "cpu")
            methods[label] = registrar
            methods[f"{label}-plain"] = (
                lambda points, r=registrar: r.register(points, search=False))
    return methods


def worse_than_search(rows: list[dict], search: list[dict] | None) -> str:
    """How many trials the method's chosen score is worse than the search alone's on the same
    trial (paired; ``-`` for a method without a score or the search itself)."""
    if search is None or rows is search or any(r.get("score_mm") is None for r in rows):
        return "-"
    return str(sum(r["score_mm"] > s["score_mm"] for r, s in zip(rows, search)))


def _row(name: str, rows: list[dict], search: list[dict] | None = None) -> str:
    rte = np.array([r["RTE_mm"] for r in rows])
    rre = np.array([r["RRE_deg"] for r in rows])
    ok = (rte < 4.0) & (rre < 5.0)
    flips = rre > 90.0
    amb = np.array([bool(r.get("ambiguous")) for r in rows])
    secs = np.array([r["runtime_s"] for r in rows])
    has_flag = any(r.get("ambiguous") is not None for r in rows)
    return (f"{name:>16} {ok.mean():8.0%} {flips.mean():6.0%} "
            f"{(f'{amb.mean():.0%}' if has_flag else '-'):>7} "
            f"{(f'{(flips & ~amb).mean():.0%}' if has_flag else '-'):>9} "
            f"{np.median(rte):8.2f} {np.median(rre):8.2f} {np.median(secs):7.2f} "
            f"{np.percentile(secs, 90):6.2f} {worse_than_search(rows, search):>6}")


def main(argv: list[str] | None = None) -> None:
    from comreg_core.config import from_dict
    from comreg_core.evaluation.calibrate import CALIBRATION_SWEEPS
    from comreg_core.simulation.config import SimulationConfig
    from tests.helpers import FIBULA_STL, SHARED_DATA, tibia_like_mesh

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", default=",".join(SETS))
    p.add_argument("--perturbation", default="paper,full")
    p.add_argument("--model", action="append", default=[], help="BONE=RUN trained on that CT")
    p.add_argument("--untrained", action="append", default=[],
                   help="BONE=RUN of the same network at 0 epochs")
    p.add_argument("--trust", action="store_true", help="the trust rows instead (priors, "
                   "unions, verdict with p_correct: tests/benchmarks/partial_trust.py)")
    p.add_argument("--prior", default="none,init,landmark", help="with --trust")
    p.add_argument("--calibration-sweeps", type=int, default=CALIBRATION_SWEEPS,
                   help="with --trust (default: comreg calibrate's)")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if args.trust:
        from tests.benchmarks.partial_trust import run_trust

        default = "real-fibula,real-fibula-union,simulated-fibula,simulated-tibia-anatomical"
        run_trust(args, (default if args.set == ",".join(SETS) else args.set).split(","))
        return

    config = from_dict(SimulationConfig, PARTIAL_SWEEPS, "simulation")
    print(f"success: RTE < 4 mm and RRE < 5 deg; {args.trials} trials per set and perturbation; "
          f"seed {args.seed}; '+beams': the same method given each point's beam origin")
    print(f"{'method':>16} {'success':>8} {'flips':>6} {'ambig.':>7} {'unflagged':>9} "
          f"{'RTE med':>8} {'RRE med':>8} {'median s':>7} {'p90 s':>6} {'worse':>6}")
    for name in args.set.split(","):
        bone = name.split("-", 1)[1]
        ct = (FIBULA_STL if bone == "fibula"
              else tibia_like_mesh(anatomical=bone == "tibia-anatomical"))
        if name.startswith("simulated"):
            runs = simulated_runs(ct, args.trials, args.seed, config)
        else:
            runs = real_runs(SHARED_DATA)
        extents = [float(np.ptp(c, axis=0).max()) for c, _ in runs]
        print(f"{name}: {len(runs)} sweeps, {int(np.median([len(c) for c, _ in runs]))} points "
              f"(median), extent {min(extents):.0f}-{max(extents):.0f} mm")
        methods = _methods(bone, ct, args)
        for perturbation in args.perturbation.split(","):
            start = time.perf_counter()
            rows = _trials(methods, runs, ct, args.trials, args.seed, perturbation)
            print(f"-- {name}, {perturbation} poses ({time.perf_counter() - start:.0f} s)")
            for method, method_rows in rows.items():
                paired = None if method.startswith("search") else rows.get("search")
                print(_row(method, method_rows, paired), flush=True)


def _trials(methods: dict, runs: list, ct, trials: int, seed: int, perturbation: str) -> dict:
    """Every method (and ``search+beams``) on ``trials`` random poses of the runs (trial ``k``
    moves run ``k % len(runs)``, its points and beam origins alike)."""
    from comreg_core.evaluation.evaluate import STREAM_POSES, evaluation_rng
    from comreg_core.registration.geometry.metrics import registration_metrics
    from comreg_core.registration.geometry.surface import CTSurface
    from comreg_core.simulation import sample_initial_pose
    from comreg_core.transforms import apply_transform, invert_rigid

    surface = CTSurface(ct)
    names = list(methods) + ["search+beams"]
    rows: dict[str, list] = {name: [] for name in names}
    for k in range(trials):
        points, origins = runs[k % len(runs)]
        T_p = sample_initial_pose(evaluation_rng(seed, STREAM_POSES, k), perturbation,
                                  surface.bbox_centre)
        moved, moved_origins = apply_transform(T_p, points), apply_transform(T_p, origins)
        for name in names:
            start = time.perf_counter()
            if name == "search+beams":
                result = methods["search"].register(moved, beam_origins=moved_origins)
            else:
                result = methods[name](moved)
            seconds = time.perf_counter() - start
            errors = registration_metrics(result.T_ct_us, invert_rigid(T_p), moved, surface)
            search = getattr(result, "search", None)
            rows[name].append({**errors, "runtime_s": seconds,
                               "ambiguous": getattr(result, "ambiguous", None),
                               "score_mm": None if search is None
                               else search.best.score_mm})
    return rows


if __name__ == "__main__":
    main()
