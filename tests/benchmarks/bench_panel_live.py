"""Benchmark: the 3D Slicer panel's live mode, the GUI thread's work per update (issue 50).

``.venv/bin/python -m tests.benchmarks.bench_panel_live [--rate 10] [--step 1]
[--search background,inline]``

Headless on slicer-core's MRML: the shared fibula sweep (111 frames; every ``--step``-th of
them) arrives in an image node and a pose node at ``--rate`` frames a second, as 3D
Slicer's OpenIGTLink connector updates them; the module's timer ticks every
:data:`comreg_plugin.live.TICK_MS` ms. The session registers in its second process
(:mod:`comreg_plugin.live_process`; ``--search background``: its full searches in a third, as
``comreg live``; ``inline``: in the session's process). On the main thread (the GUI thread in
3D Slicer) it measures:

- ``capture``: the module's handler of a new image (pixels and pose copied into a frame), per
  frame;
- ``tick``: each timer tick (frames handed to the process, its answers taken), and ``apply``:
  the ticks that wrote an update into the scene (transform, figures, status line);
- ``per update``: all main-thread time of the module (captures and ticks) over the updates
  applied; target: median apply <= 20 ms and per-update share <= 20 ms at 10 frames/s.

Also: updates applied, frames registered, the last verdict, and the wall time from the first
frame to the last update. Timings depend on the machine's load: state it with the figures.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path


def run(rate: float, step: int, background: bool) -> dict:
    """Stream the sweep into the nodes at ``rate`` frames/s and tick the live mode; the
    main-thread timings (s)."""
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_plugin.live import TICK_MS, LiveRegistration
    from comreg_plugin.logic import ComRegLogic
    from comreg_plugin.panel_testing import streamFrame
    from comreg_plugin.scene_io import vtkMatrixFromArray
    from tests.helpers import FIBULA_STL, cut_sweep

    folder = Path(tempfile.mkdtemp(prefix="bench-panel-live-"))
    sweep = read_tracked_sweep(cut_sweep(folder / "sweep", 0, 10**6, step=step))
    logic = ComRegLogic()
    logic.getParameterNode().resultDirectory = str(folder / "registrations")
    ct = logic.loadBoneMesh(FIBULA_STL)
    image = logic.scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Image")
    pose = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ImageToReference")
    live = LiveRegistration(logic, image, pose, ctModelNode=ct, background=background)
    while live.processId is None:  # the CT side prepared in the process (not timed)
        live.tick()
        time.sleep(0.05)
    captures, ticks, applies = [], [], []
    capture = live.captureFrame

    def timed_capture():
        start = time.perf_counter()
        frame = capture()
        captures.append(time.perf_counter() - start)
        return frame

    live.captureFrame = timed_capture
    start = next_frame = next_tick = time.perf_counter()
    i = 0
    while i < sweep.n_frames or live.busy:
        now = time.perf_counter()
        if i < sweep.n_frames and now >= next_frame:
            streamFrame(image, pose, sweep, i, vtkMatrixFromArray)
            i, next_frame = i + 1, next_frame + 1.0 / rate
        if now >= next_tick:
            t0 = time.perf_counter()
            applied = live.tick()
            (applies if applied is not None else ticks).append(time.perf_counter() - t0)
            next_tick += TICK_MS / 1000.0
        time.sleep(max(0.0, min(next_frame, next_tick) - time.perf_counter()))
    wall = time.perf_counter() - start
    last = live.updates[-1]
    live.stop()
    main = sum(captures) + sum(ticks) + sum(applies)
    return {"frames": sweep.n_frames, "updates": len(applies), "captures": captures,
            "ticks": ticks + applies, "applies": applies, "per_update": main / len(applies),
            "wall": wall, "verdict": last.verdict, "used": last.frames_used}


def _ms(values) -> str:
    return (f"median {1000 * statistics.median(values):.2f} ms, max "
            f"{1000 * max(values):.2f} ms") if values else "none"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=10.0, help="frames a second")
    parser.add_argument("--step", type=int, default=1, help="every n-th frame of the sweep")
    parser.add_argument("--search", default="background",
                        help="background, inline or both (comma-separated)")
    args = parser.parse_args(argv)
    for search in args.search.split(","):
        r = run(args.rate, args.step, search == "background")
        print(f"search {search}: {r['frames']} frames at {args.rate:g}/s, {r['updates']} "
              f"updates applied ({r['used']} frames registered, last {r['verdict'].upper()}) "
              f"in {r['wall']:.1f} s", flush=True)
        print(f"  main thread: capture {_ms(r['captures'])}; tick {_ms(r['ticks'])}; apply "
              f"{_ms(r['applies'])}; all of it per update {1000 * r['per_update']:.2f} ms",
              flush=True)


if __name__ == "__main__":
    main()
