"""Benchmark: live registration while scanning (issue 34), the real fibula sweep replayed over
OpenIGTLink on 127.0.0.1 into ``comreg live``, real server and client in their own processes.

``.venv/bin/python -m tests.benchmarks.bench_live [--rate 4 | --fps 40] [--starts 0,15,30,45,60,75]
[--model RUN_DIR] [--untrained RUN0] [--verdict-calibration FILE] [--prior none,landmark]
[--search background,inline] [--stress [--timings x4,x20,40fps]] [--out DIR]``

Each replay serves the shared sweep (111 B-mode frames, every 10th of the recording) from one
start frame to its end (``comreg replay --first-frame K --rate R``); ``comreg live --until-end
--out`` registers it as it comes. Per replay it prints:

- ``ok@mm``: the bone covered (mm along the CT's long axis, updates.csv's ``covered_mm``) at the
  first update whose verdict is OK, and whether that pose is correct: RTE < 4 mm and
  RRE < 5 deg at the points' centroid, against the pseudo ground truth (ICP of the whole
  sweep's points from the recorded pose: :func:`comreg_core.demo.pseudo_ground_truth`),
  starred (stress set) when it came after the stream's last frame; ``ok@img``: the images
  received by then;
- ``ok&wrong``: updates whose verdict was OK and whose pose was not correct (target: none);
- ``final``: the verdict and correctness of the registration written on stop;
- latency of the updates (median, 95th percentile; target median <= 0.2 s) and how many
  updates ran the full search;
- frames: served by the replay, received and registered by live, and lost without a report
  (sent but not received, or received but neither registered nor reported; target 0).

Priors (``--prior``, each a row per method and start): ``none``; ``landmark``: what an operating
room gives by touching the ankle with a tracked pointer, one landmark pair (``comreg live
--landmarks``) at the CT's inferior end along its long axis (the lateral malleolus), the US
point the pseudo ground truth's image of it moved 10 mm in a direction drawn per start (seeded),
tolerance 15 mm.

Full searches (``--search``, each a row per method and start): ``background`` (``comreg
live``'s default: in a second process while warm updates go on) or ``inline`` (``comreg live
--inline-search``: in the update).

The stress set (``--stress``, issue 49): every start and method at x4, x20 (about 37 frames/s)
and a fixed 40 frames/s (``comreg replay --fps 40``), no prior, background search; per replay
and per timing and method it adds the frames' age when an update took them (``frames.csv``),
frames skipped (no new bone) and dropped for lag, and the final registration against ``comreg
register`` on every frame served from that start (the differences in RTE and RRE against the
pseudo ground truth; the target: within 0.1 mm and 0.1 deg).

Controls: with ``--model RUN_DIR`` every replay runs twice, by the search alone and with the
network (``--model``); ``--untrained RUN0`` adds a third, the same network untrained.
Targets: never OK-and-wrong; OK within 150 mm; median update <= 0.2 s; no frame lost
unreported. Timings depend on the machine's load: state it with the figures.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
SHARED = REPO.parent / "shared" / "data" / "ultrabones100k-fibula"


def pseudo_truth(ct_path: Path) -> np.ndarray:
    """``T_ct_us`` of the whole sweep: ICP from the recorded pose (tracking = CT frame)."""
    from comreg_core.demo import pseudo_ground_truth
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.registration.geometry.surface import CTSurface
    from comreg_core.surfaces.us import extract_us_surface

    points = extract_us_surface(read_tracked_sweep(SHARED)).points.points
    return pseudo_ground_truth(points, CTSurface(ct_path))


def serving_port(replay: subprocess.Popen) -> int:
    """The port ``comreg replay --port 0`` printed it serves on (its stderr)."""
    seen = []
    for _ in range(50):
        line = replay.stderr.readline()
        found = re.search(r"on [^ ]+:(\d+); waiting", line)
        if found:
            return int(found.group(1))
        seen.append(line)
        if not line and replay.poll() is not None:
            break
    raise RuntimeError(f"comreg replay did not start: {''.join(seen)[-2000:]}")


def landmark_files(start: int, T_truth: np.ndarray, ct: Path, folder: Path) -> list[Path]:
    """The ``landmark`` prior of replay ``start`` (module docstring): ``[ct.mrk.json,
    us.mrk.json]`` written into ``folder`` (LPS)."""
    from comreg_core.io import read_mesh
    from comreg_core.transforms import apply_transform, invert_rigid

    points = read_mesh(ct).in_space("LPS").vertices
    centred = points - points.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    axis = axis if axis[2] < 0 else -axis  # towards inferior (LPS: -z)
    ct_point = points[np.argmax(centred @ axis)]
    direction = np.random.default_rng(1000 + start).normal(size=3)
    us_point = apply_transform(invert_rigid(T_truth), ct_point[None])[0] \
        + 10.0 * direction / np.linalg.norm(direction)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, point in (("ct", ct_point), ("us", us_point)):
        markups = {"markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "controlPoints": [
            {"label": "malleolus", "position": [float(v) for v in point],
             "description": "tol=15"}]}]}
        paths.append(folder / f"{name}.mrk.json")
        paths[-1].write_text(json.dumps(markups))
    return paths


def one_replay(start: int, rate: float, out: Path, ct: Path, model: Path | None,
               verdict_calibration: Path | None, landmarks: list[Path] | None = None,
               search: str = "background", timeout_s: float = 900.0,
               fps: float | None = None) -> dict:
    """Serve the sweep from frame ``start`` into ``comreg live`` (at ``rate`` times the
    recorded timing, or at ``fps`` frames a second); the figures of the run."""
    cli = [sys.executable, "-m", "comreg_core.cli"]
    timing = ["--rate", str(rate)] if fps is None else ["--fps", str(fps)]
    replay = subprocess.Popen(cli + ["replay", str(SHARED), "--port", "0", *timing,
                                     "--first-frame", str(start), "--wait", "300"], cwd=REPO,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = serving_port(replay)
        args = cli + ["live", "--igtl", f"127.0.0.1:{port}", "--ct", str(ct), "--out", str(out),
                      "--until-end", "--no-report", f"--{search}-search"]
        if model is not None:
            args += ["--model", str(model)]
        if verdict_calibration is not None:
            args += ["--verdict-calibration", str(verdict_calibration)]
        if landmarks:
            args += ["--landmarks", *map(str, landmarks)]
        began = time.monotonic()
        live = subprocess.run(args, cwd=REPO, capture_output=True, text=True,
                              timeout=timeout_s)
        out.mkdir(parents=True, exist_ok=True)
        (out / "live_stdout.txt").write_text(live.stdout)
        (out / "live_stderr.txt").write_text(live.stderr)
        if live.returncode != 0:  # the replay still waits for a client: say why, not a timeout
            raise RuntimeError(f"live failed ({live.returncode}): {live.stderr[-2000:]}")
        try:
            replay_out, _ = replay.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"the replay from frame {start} did not end within 60 s of live "
                               f"(live's last lines: {live.stdout[-1000:]})") from None
    finally:
        replay.kill()
    served = re.search(r"served (\d+) frames .*?: (\d+) sent", replay_out)
    used = re.search(r"(\d+) of (\d+) frames registered(?:, (\d+) waiting)?", live.stdout)
    reported = re.search(r"(\d+) not used", live.stdout)
    skipped = re.search(r"(\d+) skipped \(no new bone\)", live.stdout)
    late = re.search(r"on time within (\d+) ms", replay_out)
    modes = re.findall(r"\| (warm\+full|full|warm) \d", live.stdout)
    return {"wall_s": time.monotonic() - began, "served": int(served.group(1)),
            "full_searches": sum(m != "warm" for m in modes),
            "sent": int(served.group(2)), "used": int(used.group(1)),
            "received": int(used.group(2)),
            "reported": (int(reported.group(1)) if reported else 0)
            + (int(skipped.group(1)) if skipped else 0),
            "replay_late_ms": int(late.group(1)) if late else None}


def frame_figures(out: Path) -> dict:
    """Per frame (``frames.csv``): how old the frames were when an update took them (median,
    95th percentile, largest; s), how many were skipped (no new bone) or dropped (lag), and
    when the last one arrived (s since live was ready: the stream's end)."""
    with open(out / "frames.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    ages = np.array([float(r["age_s"]) for r in rows if r["age_s"]])
    return {"age_median_s": float(np.median(ages)) if len(ages) else None,
            "age_p95_s": float(np.percentile(ages, 95)) if len(ages) else None,
            "age_max_s": float(ages.max()) if len(ages) else None,
            "skipped": sum(r["fate"] == "skipped" for r in rows),
            "dropped_lag": sum(r["fate"] == "lag" for r in rows),
            "stream_end_s": max((float(r["received_s"]) for r in rows), default=None)}


def figures(out: Path, T_truth: np.ndarray, run: dict) -> dict:
    """The figures of one replay from its folder (updates.csv, result.json)."""
    from comreg_core.io import read_points
    from comreg_core.live.updates import read_updates, row_transform
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm

    rows = read_updates(out / "updates.csv")
    correct = []
    for row in rows:
        T = row_transform(row)
        centroid = np.array([row["centroid_x"], row["centroid_y"], row["centroid_z"]])
        correct.append(translation_error_mm(T, T_truth, centroid) < 4.0
                       and rotation_error_deg(T, T_truth) < 5.0)
    ok = [row["verdict"] == "ok" for row in rows]
    first = next((k for k, flag in enumerate(ok) if flag), None)
    latency = np.array([row["latency_s"] for row in rows])
    result = json.loads((out / "result.json").read_text())
    points = read_points(out / "us_points.ply").points
    T_final = np.array(result["T_ct_us"])
    final_correct = (translation_error_mm(T_final, T_truth, points.mean(axis=0)) < 4.0
                     and rotation_error_deg(T_final, T_truth) < 5.0)
    unreported = (run["sent"] - run["received"]) + \
        (run["received"] - run["used"] - run["reported"])
    centroid = points.mean(axis=0)
    frames = frame_figures(out)
    return {"updates": len(rows), **frames,
            "ok_after_end": None if first is None or frames["stream_end_s"] is None
            else rows[first]["time_s"] > frames["stream_end_s"],
            "final_rte_mm": translation_error_mm(T_final, T_truth, centroid),
            "final_rre_deg": rotation_error_deg(T_final, T_truth),
            "ok_at_mm": None if first is None else rows[first]["covered_mm"],
            "ok_at_images": None if first is None else int(rows[first]["frames_received"]),
            "ok_correct": None if first is None else correct[first],
            "ok_and_wrong": int(sum(o and not c for o, c in zip(ok, correct))),
            "final": f"{result['verdict']}/{'right' if final_correct else 'WRONG'}",
            "latency_median_s": float(np.median(latency)) if len(latency) else None,
            "latency_p95_s": float(np.percentile(latency, 95)) if len(latency) else None,
            "unreported": unreported, **run}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=4.0)
    parser.add_argument("--fps", type=float, default=None, help="replay at this fixed frame "
                        "rate instead of --rate")
    parser.add_argument("--stress", action="store_true", help="the stress set (module "
                        "docstring): x4, x20 and 40 frames/s, no prior, background search")
    parser.add_argument("--timings", default=",".join(label for label, _, _ in STRESS),
                        help="the stress set's timings to run (of x4,x20,40fps)")
    parser.add_argument("--starts", default="0,15,30,45,60,75")
    parser.add_argument("--model", type=Path, default=None)
    parser.add_argument("--untrained", type=Path, default=None, help="the same network before "
                        "its first step (the control), e.g. from bench_learning")
    parser.add_argument("--verdict-calibration", type=Path, default=None)
    parser.add_argument("--prior", default="none", help="none,landmark (module docstring)")
    parser.add_argument("--search", default="background", help="background,inline (module "
                        "docstring)")
    parser.add_argument("--out", type=Path, default=REPO / "out" / "bench_live")
    args = parser.parse_args(argv)
    timings = [t for t in STRESS if t[0] in args.timings.split(",")]
    if not timings:
        parser.error(f"--timings {args.timings}: of {', '.join(t[0] for t in STRESS)}")
    ct = SHARED / "fibula.stl"
    starts = [int(s) for s in args.starts.split(",")]
    methods = [("search", None)] + ([("comreg", args.model)] if args.model else []) \
        + ([("untrained", args.untrained)] if args.untrained else [])
    T_truth = pseudo_truth(ct)
    if args.stress:
        return stress(args, starts, methods, ct, T_truth, timings)
    print(f"replays of {SHARED.name} at "
          + (f"x{args.rate:g}" if args.fps is None else f"{args.fps:g} frames/s")
          + f" from frames {starts}; verdict: "
          + (f"p_correct ({args.verdict_calibration})" if args.verdict_calibration
             else "the search's confidence (no --verdict-calibration)"), flush=True)
    priors = args.prior.split(",")
    if not set(priors) <= {"none", "landmark"}:
        parser.error(f"--prior {args.prior}: none and/or landmark")
    searches = args.search.split(",")
    if not set(searches) <= {"background", "inline"}:
        parser.error(f"--search {args.search}: background and/or inline")
    header = (f"{'method':9} {'prior':8} {'search':10} {'start':>5} {'upd':>4} {'ok@mm':>6} "
              f"{'ok@img':>6} {'ok?':>5} "
              f"{'ok&wrong':>8} {'final':>11} {'lat_med':>7} {'lat_p95':>7} {'full':>4} "
              f"{'served':>6} {'recv':>5} {'used':>5} {'unrep':>5} {'wall_s':>6}")
    print(header, flush=True)
    summary = []
    for prior, search, (name, model), start in itertools.product(priors, searches, methods,
                                                                 starts):
        out = args.out / f"{name}_{prior}_{search}_from{start:03d}"
        if out.exists():
            import shutil

            shutil.rmtree(out)
        landmarks = None if prior == "none" else landmark_files(
            start, T_truth, ct, args.out / f"landmarks_from{start:03d}")
        run = one_replay(start, args.rate, out, ct, model, args.verdict_calibration,
                         landmarks, search, fps=args.fps)
        f = figures(out, T_truth, run)
        summary.append({"method": name, "prior": prior, "search": search, "start": start, **f})

        right = None if f["ok_correct"] is None else ("yes" if f["ok_correct"] else "NO")
        print(f"{name:9} {prior:8} {search:10} {start:>5} {f['updates']:>4} "
              f"{_fmt(f['ok_at_mm'], '6.0f')} {_fmt(f['ok_at_images'], '6d')} {_fmt(right, '>5')} "
              f"{f['ok_and_wrong']:>8} {f['final']:>11} "
              f"{_fmt(f['latency_median_s'], '7.2f')} {_fmt(f['latency_p95_s'], '7.2f')} "
              f"{f['full_searches']:>4} {f['served']:>6} {f['received']:>5} "
              f"{f['used']:>5} {f['unreported']:>5} {f['wall_s']:>6.0f}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_live.json").write_text(json.dumps(summary, indent=2) + "\n")
    for prior, search in itertools.product(priors, searches):
        rows = [row for row in summary if row["prior"] == prior and row["search"] == search]
        wrong = sum(row["ok_and_wrong"] for row in rows)
        late = [row["ok_at_mm"] for row in rows if row["ok_at_mm"] is not None]
        medians = [row["latency_median_s"] for row in rows
                   if row["latency_median_s"] is not None]
        print(f"targets, prior {prior}, {search} search: OK-and-wrong updates {wrong} (0); OK "
              f"reached in {len(late)}/{len(rows)} replays, within 150 mm in "
              f"{sum(v <= 150 for v in late)}; median update latency "
              f"{np.median(medians) if medians else float('nan'):.2f} s (<= 0.2); frames lost "
              f"unreported {sum(row['unreported'] for row in rows)} (0)")
    print(f"figures in {args.out / 'bench_live.json'}")


#: The stress set's timings: (label, --rate, --fps).
STRESS = (("x4", 4.0, None), ("x20", 20.0, None), ("40fps", 1.0, 40.0))


def reference(start: int, model: Path | None, ct: Path, T_truth: np.ndarray,
              folder: Path) -> tuple[float, float]:
    """``comreg register`` (the same method) on every frame served from ``start`` (extract-us
    of them, with their beam origins): its RTE (mm, at the points' centroid) and RRE (deg)
    against ``T_truth``."""
    from dataclasses import replace

    from comreg_core.io import PointCloud, write_points
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.register import register_to_directory
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
    from comreg_core.surfaces.us import extract_us_surface
    from comreg_core.surfaces.us_points import beam_origins

    sweep = read_tracked_sweep(SHARED)
    keep = np.arange(start, sweep.n_frames)
    sweep = replace(sweep, frames=sweep.frames[keep], T_ref_image=sweep.T_ref_image[keep],
                    timestamps=sweep.timestamps[keep], valid=sweep.valid[keep],
                    frame_names=[sweep.frame_names[i] for i in keep])
    points = extract_us_surface(sweep).points
    origins = beam_origins(points.points, sweep.T_ref_image[points.frame_index])
    folder.mkdir(parents=True, exist_ok=True)
    ply = write_points(PointCloud(points.points, "LPS", beam_origins=origins),
                       folder / "us_points.ply")
    result = register_to_directory(model, ply, folder / "register", ct_mesh=ct)
    centroid = points.points.mean(axis=0)
    return (translation_error_mm(result.T_ct_us, T_truth, centroid),
            rotation_error_deg(result.T_ct_us, T_truth))


def stress(args, starts: list[int], methods: list, ct: Path, T_truth: np.ndarray,
           timings=STRESS) -> None:
    """The stress set: the shared sweep at ``timings`` (:data:`STRESS`: x4, x20, about 37
    frames/s, and 40 frames/s) from each start, by each method (no prior, background
    search): per replay and per timing and method, the update latency, the frames' age when
    used, skipped and dropped frames, OK and wrong, the first OK in mm of bone, and the
    final registration against ``comreg register`` on every frame served (RTE / RRE against
    the pseudo ground truth)."""
    import os
    import shutil

    print(f"stress set: {SHARED.name} at " + ", ".join(label for label, _, _ in timings)
          + f" from frames {starts}; load average at the start "
          f"{', '.join(f'{v:.1f}' for v in os.getloadavg())}", flush=True)
    refs = {(name, start): reference(start, model, ct, T_truth,
                                     args.out / "reference" / f"{name}_from{start:03d}")
            for name, model in methods for start in starts}
    print(f"{'timing':6} {'method':9} {'start':>5} {'upd':>4} {'ok@mm':>6} {'ok?':>4} "
          f"{'ok&wr':>5} {'final':>11} {'lat_med':>7} {'lat_p95':>7} {'age_p95':>7} "
          f"{'age_max':>7} {'skip':>4} {'drop':>4} {'recv':>4} {'used':>4} {'dRTE':>6} "
          f"{'dRRE':>6} {'late_ms':>7}", flush=True)
    rows = []
    for (label, rate, fps), (name, model), start in itertools.product(timings, methods, starts):
        out = args.out / f"stress_{label}_{name}_from{start:03d}"
        shutil.rmtree(out, ignore_errors=True)
        run = one_replay(start, rate, out, ct, model, args.verdict_calibration, fps=fps)
        f = figures(out, T_truth, run)
        rte, rre = refs[(name, start)]
        f.update(timing=label, method=name, start=start, d_rte_mm=f["final_rte_mm"] - rte,
                 d_rre_deg=f["final_rre_deg"] - rre, register_rte_mm=rte, register_rre_deg=rre)
        rows.append(f)
        print(f"{label:6} {name:9} {start:>5} {f['updates']:>4} {_ok_mm(f):>6} "
              f"{_fmt(None if f['ok_correct'] is None else 'yes' if f['ok_correct'] else 'NO', '>4')} "
              f"{f['ok_and_wrong']:>5} {f['final']:>11} "
              f"{_fmt(f['latency_median_s'], '7.2f')} {_fmt(f['latency_p95_s'], '7.2f')} "
              f"{_fmt(f['age_p95_s'], '7.2f')} {_fmt(f['age_max_s'], '7.2f')} "
              f"{f['skipped']:>4} {f['dropped_lag']:>4} {f['received']:>4} {f['used']:>4} "
              f"{f['d_rte_mm']:>6.2f} {f['d_rre_deg']:>6.2f} "
              f"{_fmt(f['replay_late_ms'], '>7')}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_live_stress.json").write_text(json.dumps(rows, indent=2) + "\n")
    for (label, _, _), (name, _) in itertools.product(timings, methods):
        sel = [r for r in rows if r["timing"] == label and r["method"] == name]
        meds = [r["latency_median_s"] for r in sel if r["latency_median_s"] is not None]
        p95s = [r["latency_p95_s"] for r in sel if r["latency_p95_s"] is not None]
        ages = [r["age_max_s"] for r in sel if r["age_max_s"] is not None]
        print(f"{label}, {name}: median update {_range(meds)} s, 95th percentile "
              f"{_range(p95s)} s; oldest frame used {_range(ages)} s; dropped for lag "
              f"{sum(r['dropped_lag'] for r in sel)}, skipped {sum(r['skipped'] for r in sel)} "
              f"of {sum(r['received'] for r in sel)}; OK-and-wrong "
              f"{sum(r['ok_and_wrong'] for r in sel)}; first OK (mm) "
              f"{', '.join(_ok_mm(r) for r in sel)}; final - register: "
              f"RTE {_range([r['d_rte_mm'] for r in sel], '+.2f')} mm, RRE "
              f"{_range([r['d_rre_deg'] for r in sel], '+.2f')} deg", flush=True)
    print("* the first OK came after the stream's last frame (with a full search's answer)")
    print(f"load average at the end {', '.join(f'{v:.1f}' for v in os.getloadavg())}; "
          f"figures in {args.out / 'bench_live_stress.json'}")


def _ok_mm(row: dict) -> str:
    """The first OK's bone (mm), starred when it came after the stream's last frame."""
    return _fmt(row["ok_at_mm"], ".0f") + ("*" if row.get("ok_after_end") else "")


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _range(values: list, spec: str = ".2f") -> str:
    return "-" if not values else f"{format(min(values), spec)} to {format(max(values), spec)}"


if __name__ == "__main__":
    main()
