"""Benchmark: what the live session's frame rules cost (issue 49), offline on the shared fibula
sweep (111 frames, every 10th of the recording).

``.venv/bin/python -m tests.benchmarks.bench_live_frames [--spacings 0,0.5,1,2,4,8]``

1. **Frame spacing.** The frames ``comreg live --frame-spacing MM,DEG`` keeps (the gate of
   :class:`~comreg_core.live.intake.FrameGate` in stream order; DEG = MM, 0: every frame), and
   the registration of their points (``comreg register``'s pose search, the points of
   ``extract-us``) against the pseudo ground truth (ICP of the whole sweep from its recorded
   pose): RTE (mm, at the points' centroid) and RRE (deg), beside every frame's.
2. **Clean-up per update.** The time to clean up all points so far after one more frame, as
   ``extract-us`` does (all points again) and kept up to date
   (:class:`~comreg_core.surfaces.us_denoise_incremental.IncrementalDenoise`), at 20, 60 and
   100 frames with bone (median of 5 repeats; the same points kept, checked).

Timings depend on the machine's load: state it with the figures.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import numpy as np

from tests.benchmarks.bench_live import SHARED, pseudo_truth


def _subset(sweep, keep):
    return replace(sweep, frames=sweep.frames[keep], T_ref_image=sweep.T_ref_image[keep],
                   timestamps=sweep.timestamps[keep], valid=sweep.valid[keep],
                   frame_names=[sweep.frame_names[i] for i in keep])


def kept_frames(sweep, mm: float) -> np.ndarray:
    """Indices of the frames the gate keeps at a spacing of ``mm`` mm and ``mm`` deg."""
    from comreg_core.live.intake import FrameGate, FrameSpacing
    from comreg_core.live.stream import Frame

    gate = FrameGate(FrameSpacing(mm, mm) if mm > 0 else None)
    return np.array([i for i in range(sweep.n_frames) if gate.admit(Frame(
        i, sweep.frames[i], sweep.spacing, sweep.T_ref_image[i], 0.0, 0.0), 0.0)])


def spacing_costs(spacings: list[float]) -> None:
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.register import Registrar
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
    from comreg_core.surfaces.us import extract_us_surface
    from comreg_core.surfaces.us_points import beam_origins

    sweep = read_tracked_sweep(SHARED)
    T_truth = pseudo_truth(SHARED / "fibula.stl")
    registrar = Registrar.from_ct(SHARED / "fibula.stl")
    print(f"{'spacing':>8} {'frames':>6} {'points':>6} {'RTE_mm':>7} {'RRE_deg':>7}", flush=True)
    for mm in spacings:
        keep = kept_frames(sweep, mm)
        part = _subset(sweep, keep)
        points = extract_us_surface(part).points
        origins = beam_origins(points.points, part.T_ref_image[points.frame_index])
        result = registrar.register(points.points, seed=0, beam_origins=origins)
        centroid = points.points.mean(axis=0)
        print(f"{mm:>8g} {len(keep):>6} {len(points.points):>6} "
              f"{translation_error_mm(result.T_ct_us, T_truth, centroid):>7.2f} "
              f"{rotation_error_deg(result.T_ct_us, T_truth):>7.2f}", flush=True)


def cleanup_costs(at=(20, 60, 100), repeats: int = 5) -> None:
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.live.points import detect_frame
    from comreg_core.live.stream import Frame
    from comreg_core.surfaces.us_config import DenoiseConfig
    from comreg_core.surfaces.us_denoise import denoise_points
    from comreg_core.surfaces.us_denoise_incremental import IncrementalDenoise
    from comreg_core.surfaces.us_points import USSurfacePoints

    sweep = read_tracked_sweep(SHARED)
    found = [detect_frame(Frame(i, sweep.frames[i], sweep.spacing, sweep.T_ref_image[i],
                                0.0, 0.0)) for i in range(sweep.n_frames)]
    found = [d for d in found if len(d.points)]
    print(f"{'frames':>6} {'points':>6} {'all_ms':>7} {'incremental_ms':>14}", flush=True)
    for n in at:
        full_s, inc_s = [], []
        for _ in range(repeats):
            cleanup = IncrementalDenoise(DenoiseConfig())
            for d in found[:n - 1]:
                cleanup.add(d.points, np.full(len(d.points), d.index), d.scores)
            cleanup.cloud(n - 1, n - 1)
            last = found[n - 1]
            t = time.perf_counter()
            cleanup.add(last.points, np.full(len(last.points), last.index), last.scores)
            kept = cleanup.cloud(n, n)
            inc_s.append(time.perf_counter() - t)
            t = time.perf_counter()
            raw = USSurfacePoints(np.concatenate([d.points for d in found[:n]]),
                                  np.concatenate([np.full(len(d.points), d.index)
                                                  for d in found[:n]]),
                                  np.concatenate([d.scores for d in found[:n]]), n, n)
            whole = denoise_points(raw, DenoiseConfig())
            full_s.append(time.perf_counter() - t)
            assert np.array_equal(kept.points, whole.points)
        print(f"{n:>6} {len(raw.points):>6} {1000 * np.median(full_s):>7.1f} "
              f"{1000 * np.median(inc_s):>14.1f}", flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spacings", default="0,0.5,1,2,4,8")
    args = parser.parse_args(argv)
    print(f"load average {', '.join(f'{v:.1f}' for v in os.getloadavg())}", flush=True)
    spacing_costs([float(v) for v in args.spacings.split(",")])
    cleanup_costs()
    print(f"load average {', '.join(f'{v:.1f}' for v in os.getloadavg())}", flush=True)


if __name__ == "__main__":
    main()
