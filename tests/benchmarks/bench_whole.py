"""Benchmark: the verdict on whole clouds (issue 48: "OK and right from every start").

``.venv/bin/python -m tests.benchmarks.bench_whole [--starts 8] [--noise 0.43] [--model
fibula=RUN --untrained fibula=RUN0] [--bundled-untrained RUN0]``

Sets, each moved by ``--starts`` ``paper`` poses (one axis, +-90 deg, +-100 mm; the poses of
``evaluation_rng(0, STREAM_POSES, k)``) and registered and judged as ``comreg register`` does
(:func:`~comreg_core.register.folder.registration_verdict`, uncalibrated):

- ``bundled``: the bundled sample's 3,166 real points (truth: the demo's pseudo ground truth);
  ``comreg`` is the bundled model, ``untrained`` ``--bundled-untrained`` (the same network
  before its first step, e.g. ``out/sample_untrained``).
- ``whole-real-fibula``: the shared real sweep's 9.5k bone points (truth: its pseudo ground
  truth, ``partial_trust.whole_sweep_truth``); ``--model`` / ``--untrained``.
- ``simulated-whole``: 8 simulated sweeps of the whole fibula
  (:func:`~comreg_core.evaluation.evaluate.simulated_us_clouds`) with ``--noise`` mm of Gaussian
  noise per point (numpy seed 5); truth: the simulator's. ``--model`` / ``--untrained``.

Per set and method: right (within 4 mm and 5 deg), right and OK, wrong and OK (target: every
result right and OK), and the reasons of every result that is not right and OK.
"""

from __future__ import annotations

import argparse
import numpy as np

from tests.benchmarks.bench_latency import bundled_case, registrars
from tests.helpers import SHARED_DATA

SIMULATED_CLOUDS = 8


def cases(noise_mm: float) -> dict:
    """``{set: (CT mesh, [US points (n, 3) in the CT frame], its own model or None)}`` (the
    bundled sample's model; the fibula's come from the command line)."""
    from comreg_core.evaluation.evaluate import simulated_us_clouds
    from comreg_core.io import read_mesh
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import extract_us_surface
    from comreg_core.transforms import apply_transform
    from tests.benchmarks.partial_trust import whole_sweep_truth

    ct_b, points_b, truth_b, model_b = bundled_case()
    ct_f = read_mesh(SHARED_DATA / "ultrabones100k-fibula" / "fibula.stl")
    sweep = extract_us_surface(read_tracked_sweep(SHARED_DATA / "ultrabones100k-fibula"))
    truth_f = whole_sweep_truth(SHARED_DATA, ct_f)
    rng = np.random.default_rng(5)
    clouds = [c + rng.normal(0.0, noise_mm, c.shape)
              for c in simulated_us_clouds(ct_f, SIMULATED_CLOUDS)]
    return {"bundled": (ct_b, [apply_transform(truth_b, points_b)], model_b),
            "whole-real-fibula": (ct_f, [apply_transform(truth_f, sweep.points.points)], None),
            "simulated-whole": (ct_f, clouds, None)}


def judge_set(registrar, clouds: list, starts: int) -> tuple[list[int], list[str]]:
    """``([right, right and OK, wrong and OK], notes)`` of every cloud (CT frame) moved by each
    of ``starts`` paper poses."""
    from comreg_core.evaluation.evaluate import STREAM_POSES, evaluation_rng
    from comreg_core.register.folder import registration_verdict
    from comreg_core.registration.geometry.metrics import (rotation_error_deg,
                                                           translation_error_mm)
    from comreg_core.simulation import sample_initial_pose
    from comreg_core.transforms import apply_transform, invert_rigid

    tally, notes = [0, 0, 0], []
    for c, cloud in enumerate(clouds):
        for k in range(starts):
            T_move = sample_initial_pose(evaluation_rng(0, STREAM_POSES, k), "paper",
                                         registrar.surface.bbox_centre)
            moved = apply_transform(T_move, cloud)
            result = registrar.register(moved)
            verdict, _ = registration_verdict(result, registrar)
            truth = invert_rigid(T_move)
            rte = translation_error_mm(result.T_ct_us, truth, moved.mean(axis=0))
            rre = rotation_error_deg(result.T_ct_us, truth)
            right = rte < 4.0 and rre < 5.0
            tally[0] += right
            tally[1] += right and verdict.ok
            tally[2] += verdict.ok and not right
            if not (right and verdict.ok):
                notes.append(f"cloud {c} start {k}: {rte:.1f} mm / {rre:.1f} deg, "
                             f"{verdict.verdict}: {' '.join(r[:90] for r in verdict.reasons)}")
    return tally, notes


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--starts", type=int, default=8)
    parser.add_argument("--noise", type=float, default=0.43, help="mm per point, simulated")
    parser.add_argument("--model", default=None, help="fibula=RUN")
    parser.add_argument("--untrained", default=None, help="fibula=RUN0")
    parser.add_argument("--bundled-untrained", default=None, help="RUN0 of the bundled model")
    args = parser.parse_args(argv)
    fibula = {"model": None if args.model is None else args.model.partition("=")[2],
              "untrained": None if args.untrained is None else args.untrained.partition("=")[2]}
    print(f"whole clouds, {args.starts} paper starts each; simulated noise {args.noise} mm; "
          "verdict uncalibrated; right: within 4 mm and 5 deg", flush=True)
    for name, (ct, clouds, own_model) in cases(args.noise).items():
        model, untrained = ((own_model, args.bundled_untrained) if name == "bundled"
                            else (fibula["model"], fibula["untrained"]))
        for method, registrar in registrars(ct, model, untrained).items():
            (right, right_ok, wrong_ok), notes = judge_set(registrar, clouds, args.starts)
            total = len(clouds) * args.starts
            print(f"{name:>18} {method:>9}: right {right} / right and OK {right_ok} / wrong and "
                  f"OK {wrong_ok} of {total}", flush=True)
            for note in notes:
                print(f"{'':>30}{note}", flush=True)


if __name__ == "__main__":
    main()
