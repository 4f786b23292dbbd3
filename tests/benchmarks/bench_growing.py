"""Benchmark: ``comreg register``'s verdict on the real fibula sweep as it grows, the offline
twin of ``bench_live`` (no stream, no settling gate, no halves check: the verdict a user gets
from ``register`` on a partial recording).

``.venv/bin/python -m tests.benchmarks.bench_growing [--starts 0,15,30,45,60,75] [--step 3]
[--model RUN_DIR] [--untrained RUN0] [--verdict-calibration FILE]``

For each start frame, the bone points of frames ``start..end`` (the live session's detector and
clean-up, :class:`~comreg_core.live.points.SweepPoints`) are registered for every ``step``-th
``end`` to the sweep's last frame, in the tracker's frame (the CT's: the registration does not
start from it), with their beam origins, by the search alone (``Registrar.from_ct``) and, with
``--model`` / ``--untrained``, by the network then the search (``Registrar.from_run``: the
trained run and its untrained control). Each registration is judged as ``register`` judges it
(:func:`comreg_core.register.folder.registration_verdict`; by ``p_correct`` with
``--verdict-calibration``) and is right when RTE < 4 mm and RRE < 5 deg at the points' centroid
against the pseudo ground truth (ICP of the whole sweep from its recorded pose, as
``bench_live``). Per start and method it prints the bone covered at the first OK (mm along the
CT's long axis, as ``comreg live``'s ``covered_mm``, the points placed by the pseudo ground
truth), whether it was right, how many
registrations were OK and wrong (target: none), how many were wrong with ``p_correct`` >= 0.95
whatever the verdict (``wr>=.95``; target: none; each listed at the end with its errors), how
many were right but CHECK, and how many ``register`` refused (the network needs 256 points; the
first frames of a start give fewer).
The *settle point* is the bone covered from which on every longer prefix's pose is right (the
data settle the pose there); ``lag`` is the bone between it and the first OK (target: <= 30 mm),
``early`` the OKs before it (target: none).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from tests.benchmarks.bench_live import SHARED, pseudo_truth


def prefixes(start: int, step: int):
    """``(end frame, points (N, 3), beam origins (N, 3))`` of the sweep's frames
    ``start..end`` for every ``step``-th end with at least 3 frames with bone."""
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.live.points import SweepPoints
    from comreg_core.live.stream import Frame

    sweep = read_tracked_sweep(SHARED)
    points = SweepPoints()
    for k in range(start, sweep.n_frames):
        points.add(Frame(k, sweep.frames[k], sweep.spacing, sweep.T_ref_image[k],
                         float(sweep.timestamps[k]), 0.0))
        if (k - start) % step != step - 1 and k != sweep.n_frames - 1:
            continue
        cloud = points.cloud() if points.frames_with_bone >= 3 else None
        if cloud is not None:
            yield k, cloud.points, points.beam_origins(cloud)


def covered_mm(points: np.ndarray, T_ct_us: np.ndarray, target) -> float:
    """Bone covered by ``points`` placed by ``T_ct_us``, along the CT's long axis (mm)."""
    from comreg_core.live.points import covered_length_mm
    from comreg_core.transforms import apply_transform

    moved = apply_transform(T_ct_us, points)
    return covered_length_mm((moved - target.centre) @ target.axes[:, 0])


def settle_columns(trail: list[tuple[float, bool, bool]]) -> str:
    """``settle@mm lag early`` of one start's ``(covered mm, right, ok)`` prefixes (module
    docstring): ``-`` where the data never settle the pose or no OK follows."""
    settle = next((i for i in range(len(trail)) if all(r for _, r, _ in trail[i:])), None)
    if settle is None:
        return f"{'-':>9} {'-':>6} {sum(ok for _, _, ok in trail):>5}"
    early = sum(ok for _, _, ok in trail[:settle])
    after = next((mm for mm, _, ok in trail[settle:] if ok), None)
    lag = "-" if after is None else f"{after - trail[settle][0]:.0f}"
    return f"{trail[settle][0]:9.0f} {lag:>6} {early:>5}"


def main(argv=None) -> None:
    from comreg_core.errors import ComRegError
    from comreg_core.register import Registrar
    from comreg_core.register.folder import registration_verdict
    from comreg_core.registration.judgement.calibration import Calibration
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--starts", default="0,15,30,45,60,75")
    parser.add_argument("--step", type=int, default=3, help="frames between registrations")
    parser.add_argument("--model", type=Path, default=None)
    parser.add_argument("--untrained", type=Path, default=None)
    parser.add_argument("--verdict-calibration", type=Path, default=None)
    args = parser.parse_args(argv)
    ct = SHARED / "fibula.stl"
    T_truth = pseudo_truth(ct)
    calibration = (Calibration.load(args.verdict_calibration) if args.verdict_calibration
                   else None)
    registrars = {"search": Registrar.from_ct(ct)}
    for name, run in (("comreg", args.model), ("untrained", args.untrained)):
        if run is not None:
            registrars[name] = Registrar.from_run(run, device="cpu", ct_mesh=ct)
    target = registrars["search"].search_target(
        registrars["search"].search_config.target_points)
    starts = [int(s) for s in args.starts.split(",")]
    print(f"register on growing prefixes of {SHARED.name} from frames {starts}, every "
          f"{args.step} frames; verdict: " + (f"p_correct ({args.verdict_calibration})"
                                              if calibration else "uncalibrated"), flush=True)
    print(f"{'method':9} {'start':>5} {'regs':>4} {'ok@mm':>6} {'ok?':>4} {'ok&wrong':>8} "
          f"{'wr>=.95':>7} {'right&check':>11} {'refused':>7} {'settle@mm':>9} {'lag mm':>6} "
          f"{'early':>5}",
          flush=True)
    # per method: registrations, OK and wrong, wrong at p_correct >= 0.95, right but CHECK,
    # refused; and the wrong ones at p_correct >= 0.95
    totals = {name: [0, 0, 0, 0, 0] for name in registrars}
    confident_wrong = []
    for start in starts:
        grown = list(prefixes(start, args.step))
        for name, registrar in registrars.items():
            first, first_right = None, None
            wrong = sure = checked = count = refused = 0
            trail = []  # (covered mm, right, ok) per registered prefix
            for _, points, origins in grown:
                try:
                    result = registrar.register(points, seed=0, beam_origins=origins)
                except ComRegError:  # too few points for the network: register refuses
                    refused += 1
                    continue
                verdict, _ = registration_verdict(result, registrar, calibration)
                centroid = points.mean(axis=0)
                rte = translation_error_mm(result.T_ct_us, T_truth, centroid)
                rre = rotation_error_deg(result.T_ct_us, T_truth)
                right = rte < 4.0 and rre < 5.0
                p_correct = verdict.figures.get("p_correct")
                covered = covered_mm(points, T_truth, target)
                count += 1
                wrong += verdict.ok and not right
                if not right and p_correct is not None and p_correct >= 0.95:
                    sure += 1
                    confident_wrong.append(
                        f"{name} from {start}, {len(points)} points, "
                        f"{covered:.0f} mm of bone: {rte:.1f} mm / "
                        f"{rre:.1f} deg off, p_correct {p_correct:.2f}, {verdict.verdict.upper()}")
                checked += right and not verdict.ok
                trail.append((covered, right, verdict.ok))
                if verdict.ok and first is None:
                    first, first_right = trail[-1][0], right
            totals[name] = [a + b for a, b in zip(totals[name],
                                                  (count, wrong, sure, checked, refused))]
            print(f"{name:9} {start:>5} {count:>4} "
                  + ("     -" if first is None else f"{first:6.0f}")
                  + f" {'-' if first_right is None else ('yes' if first_right else 'NO'):>4} "
                  f"{wrong:>8} {sure:>7} {checked:>11} {refused:>7} {settle_columns(trail)}",
                  flush=True)
    for name, (count, wrong, sure, checked, refused) in totals.items():
        print(f"{name}: {count} registrations, OK and wrong {wrong} (target 0), wrong at "
              f"p_correct >= 0.95 {sure} (target 0), right but CHECK {checked}, refused "
              f"{refused}")
    for line in confident_wrong:
        print(f"wrong at p_correct >= 0.95: {line}")


if __name__ == "__main__":
    main()
