"""Benchmark: registration latency (issue 35), with the accuracy beside it. (The numpy path
the compiled kernels replaced was measured against them in the same run before it was removed:
docs/performance.md has the ratios.)

``.venv/bin/python -m tests.benchmarks.bench_latency [--trials 10] [--seed 0]
[--set bundled,simulated-fibula,real-fibula,grown] [--model fibula=RUN --untrained
fibula=RUN0]``

Sets (every trial moves the points by a random ``paper`` pose: one axis, +-90 deg, +-100 mm):

- ``bundled``: the bundled sample's whole cloud (``resources/sample``: the real fibula sweep's
  bone points, the CT surface extracted from its segmentation); truth: ICP of the cloud from
  the recorded tracking (the demo's pseudo ground truth). Methods: ``search``, ``comreg``
  (the bundled model) and ``untrained`` (the same network before its first step).
- ``simulated-fibula``: simulated 40-50 mm one-face sweeps of the shared fibula CT
  (``bench_partial``'s); truth: the simulator's. ``comreg``/``untrained`` with ``--model
  fibula=RUN``/``--untrained fibula=RUN0``.
- ``real-fibula``: the real sweep cut into 30-60 mm runs (``bench_partial``'s, with beam
  origins); truth: ICP of the whole sweep from its recorded pose (``partial_trust``).
- ``grown``: the real sweep growing by 10 frames at a time from 30 frames (live scanning):
  a full search at 30 frames, then a warm re-registration (``Registrar.register(warm_start=
  ...)``) per step; latency of the warm updates; truth as ``real-fibula``.

Columns: success (RTE < 4 mm and RRE < 5 deg), flagged (share of results the search calls
ambiguous), RTE/RRE medians, latency median and 90th percentile (s, the registration call
with the CT's structures built beforehand, as a ``Registrar`` reused across calls has them),
worse (trials whose chosen score is worse than the search alone's on the same case: 0 expected),
judge s (median seconds of the one judge after the registration: the verdict, the pose's
uncertainty, its profiles and where to scan next).
The load average is printed: measure on an idle machine.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

SETS = ("bundled", "simulated-fibula", "real-fibula", "grown")
SUCCESS_MM, SUCCESS_DEG = 4.0, 5.0


def bundled_case():
    """``(CT mesh, US points (n, 3), truth T_ct_us (4, 4), sample model path)`` of the bundled
    sample (tracking and CT in one frame)."""
    from comreg_core.demo import (SAMPLE_MODEL, SAMPLE_SWEEP, pseudo_ground_truth,
                                  write_sample_ct_surface)
    from comreg_core.io import read_mesh
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import extract_us_surface

    folder = "out/bench_latency"
    os.makedirs(folder, exist_ok=True)
    ct = read_mesh(write_sample_ct_surface(f"{folder}/ct_bone.stl"))
    points = extract_us_surface(read_tracked_sweep(SAMPLE_SWEEP)).points.points
    return ct, points, pseudo_ground_truth(points, ct), SAMPLE_MODEL


def real_sweep(shared_data):
    """The shared real sweep's ``(points (n, 3), beam origins (n, 3), frame index (n,))``."""
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import extract_us_surface
    from comreg_core.surfaces.us_points import beam_origins

    sweep = read_tracked_sweep(shared_data / "ultrabones100k-fibula")
    us = extract_us_surface(sweep).points
    return us.points, beam_origins(us.points, sweep.T_ref_image[us.frame_index]), us.frame_index


def registrars(ct, model, untrained) -> dict:
    """``{method: Registrar}``: the search alone, and the models given (paths or None)."""
    from comreg_core.register import Registrar

    methods = {"search": Registrar.from_ct(ct)}
    for label, path in (("comreg", model), ("untrained", untrained)):
        if path is not None:
            methods[label] = Registrar.from_run(path, "cpu", ct_mesh=ct)
    return methods


def errors(T, T_truth, points) -> tuple[float, float]:
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm

    return (translation_error_mm(T, T_truth, points.mean(axis=0)),
            rotation_error_deg(T, T_truth))


def time_trials(registrar, cases) -> list:
    """Every case ``(points, beam origins or None, truth)``: rows ``(seconds, RTE mm, RRE deg,
    flagged, chosen score mm, judge seconds)``."""
    from comreg_core.register.folder import registration_verdict

    rows = []
    first = registrar.register(cases[0][0], beam_origins=cases[0][1])  # CT structures, kernels
    registration_verdict(first, registrar)
    for points, origins, T_truth in cases:
        start = time.perf_counter()
        result = registrar.register(points, beam_origins=origins)
        seconds = time.perf_counter() - start
        start = time.perf_counter()
        registration_verdict(result, registrar)
        judged = time.perf_counter() - start
        rows.append((seconds, *errors(result.T_ct_us, T_truth, points),
                     bool(result.info.get("ambiguous")), result.search.best.score_mm,
                     judged))
    return rows


def grown_trials(registrar, points, origins, frames, T_truth) -> list:
    """The sweep growing 10 frames at a time from 30: a full search, then warm updates."""
    rows = []
    first = frames < 30
    last = registrar.register(points[first], beam_origins=origins[first])
    for upto in range(40, int(frames.max()) + 2, 10):
        used = frames < upto
        start = time.perf_counter()
        last = registrar.register(points[used], beam_origins=origins[used], warm_start=last)
        seconds = time.perf_counter() - start
        rows.append((seconds, *errors(last.T_ct_us, T_truth, points[used]),
                     bool(last.info.get("ambiguous")), last.search.best.score_mm, np.nan))
    return rows


def print_rows(name: str, method: str, rows: list, search: list | None = None) -> None:
    """One line of figures; ``worse``: trials whose chosen score is worse than the search
    alone's on the same case (``search``'s rows; paired)."""
    a = np.array(rows, dtype=np.float64)
    seconds, rte, rre, flagged = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    worse = "-" if search is None or search is rows else str(
        int(np.sum(a[:, 4] > np.array(search, dtype=np.float64)[:, 4])))
    success = np.mean((rte < SUCCESS_MM) & (rre < SUCCESS_DEG))
    print(f"{name:>17} {method:>9} {len(a):>6} {success:>7.0%} {flagged.mean():>7.0%} "
          f"{np.median(rte):>7.2f} {np.median(rre):>7.2f} {np.median(seconds):>7.3f} "
          f"{np.percentile(seconds, 90):>6.3f} {worse:>6} {np.median(a[:, 5]):>7.3f}",
          flush=True)


def main(argv: list[str] | None = None) -> None:
    from comreg_core.config import from_dict
    from comreg_core.io import read_mesh
    from comreg_core.simulation import sample_initial_pose
    from comreg_core.simulation.config import SimulationConfig
    from comreg_core.transforms import apply_transform, invert_rigid
    from tests.benchmarks.bench_partial import PARTIAL_SWEEPS, real_runs, simulated_runs
    from tests.benchmarks.bench_learning import write_untrained_control
    from tests.benchmarks.partial_trust import whole_sweep_truth
    from tests.helpers import FIBULA_STL, SHARED_DATA

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", default=",".join(SETS))
    p.add_argument("--model", action="append", default=[], help="fibula=RUN")
    p.add_argument("--untrained", action="append", default=[], help="fibula=RUN0")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    models = dict(a.split("=", 1) for a in args.model)
    untrained = dict(a.split("=", 1) for a in args.untrained)
    import numba
    import torch

    print(f"load average {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} cores; torch "
          f"{torch.get_num_threads()} threads, numba {numba.get_num_threads()}; "
          f"success: RTE < {SUCCESS_MM:g} mm and RRE < {SUCCESS_DEG:g} deg")
    print(f"{'set':>17} {'method':>9} {'trials':>6} {'success':>7} {'flagged':>7} "
          f"{'RTE med':>7} {'RRE med':>7} {'median s':>7} {'p90 s':>6} {'worse':>6} "
          f"{'judge s':>7}")
    rng_pose = np.random.default_rng(args.seed)
    fibula = read_mesh(FIBULA_STL)
    for name in args.set.split(","):
        if name == "bundled":
            ct, points, T_truth, model = bundled_case()
            control = write_untrained_control(model, __import__("pathlib").Path(
                "out/bench_latency/sample_untrained"))
            methods = registrars(ct, model, control)
            runs = [(points, None, T_truth)]
        elif name == "simulated-fibula":
            config = from_dict(SimulationConfig, PARTIAL_SWEEPS, "simulation")
            runs = [(pts, origins, np.eye(4))
                    for pts, origins in simulated_runs(fibula, args.trials, args.seed, config)]
            methods = registrars(fibula, models.get("fibula"), untrained.get("fibula"))
        elif name == "real-fibula":
            T_truth = whole_sweep_truth(SHARED_DATA, fibula)
            runs = [(pts, origins, T_truth) for pts, origins in real_runs(SHARED_DATA)]
            methods = registrars(fibula, models.get("fibula"), untrained.get("fibula"))
        elif name == "grown":
            T_truth = whole_sweep_truth(SHARED_DATA, fibula)
            points, origins, frames = real_sweep(SHARED_DATA)
            methods = registrars(fibula, None, None)
            print_rows(name, "search", grown_trials(methods["search"], points, origins, frames,
                                                    T_truth))
            continue
        else:
            raise SystemExit(f"unknown set {name!r}; choose from {', '.join(SETS)}")
        cases = []
        for k in range(args.trials):
            points, origins, T_truth = runs[k % len(runs)]
            T_move = sample_initial_pose(rng_pose, "paper", center=points.mean(axis=0))
            cases.append((apply_transform(T_move, points),
                          None if origins is None else apply_transform(T_move, origins),
                          T_truth @ invert_rigid(T_move)))
        rows = {method: time_trials(registrar, cases) for method, registrar in methods.items()}
        for method, method_rows in rows.items():
            print_rows(name, method, method_rows, rows["search"])


if __name__ == "__main__":
    main()
