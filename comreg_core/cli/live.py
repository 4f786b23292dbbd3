"""``comreg live`` and ``comreg replay``: registration while scanning, from an OpenIGTLink
stream, and a recorded sweep served as one. The work is in :mod:`comreg_core.live`."""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path
from typing import Optional

import typer

from comreg_core.cli.comreg import app
from comreg_core.cli.options import (DEVICE_OPTION, INIT_OPTION, INIT_TOLERANCE_OPTION, INPUTS,
                                     LANDMARK_TOLERANCE_OPTION, LANDMARKS_OPTION, NETWORK, OUTPUT,
                                     SEARCH, STREAM, VERDICT, Device)

#: The panel of these commands in 'comreg --help'.
PANEL = "Live"

# --- comreg live ---------------------------------------------------------------------------------
LIVE_IGTL = typer.Option(..., "--igtl", metavar="HOST:PORT", rich_help_panel=STREAM,
                         help="The OpenIGTLink server sending the tracked B-mode frames (PLUS "
                         "Server, 'comreg replay', 3D Slicer), e.g. 127.0.0.1:18944.")
LIVE_IMAGE_DEVICE = typer.Option("Image", "--image-device", rich_help_panel=STREAM,
                                 help="The IMAGE device of the B-mode frames.")
LIVE_TRANSFORM_DEVICE = typer.Option(
    None, "--transform-device", rich_help_panel=STREAM, help="The TRANSFORM device of their "
    "poses (default ImageToReference; ProbeToReference with --probe-calibration).")
LIVE_SEND_DEVICE = typer.Option("ReferenceToCT", "--send-device", rich_help_panel=STREAM,
                                help="The TRANSFORM device the registration is sent back as.")
LIVE_UNTIL_END = typer.Option(False, "--until-end", rich_help_panel=STREAM, help="Stop when the "
                              "server closes the stream (default: reconnect and go on until "
                              "Ctrl-C).")
LIVE_CONNECT_TIMEOUT = typer.Option(
    30.0, "--connect-timeout", metavar="SECONDS", rich_help_panel=STREAM, help="Give up (exit "
    "2, nothing written) when no server answered within this many seconds of starting to "
    "connect. The first connection only: a lost one is retried for as long as live runs (with "
    "--until-end, a closed stream ends it).")
LIVE_SPACING = typer.Option(
    "0.5,0.5", "--frame-spacing", metavar="MM,DEG", rich_help_panel=STREAM, help="Skip, before "
    "detection, a frame whose image moved less than MM (at every corner) and turned less than "
    "DEG from the last frame used: it shows no new bone (counted as skipped, not lost). 0,0: "
    "use every frame.")
LIVE_MAX_AGE = typer.Option(
    0.5, "--max-frame-age", metavar="SECONDS", rich_help_panel=STREAM, help="No frame is older "
    "than this when an update registers it: frames the registration cannot keep up with are "
    "dropped (counted, 'dropped (lag)'). inf: frames wait, none is dropped.")
LIVE_UPDATE_EVERY = typer.Option(
    0.2, "--update-every", metavar="SECONDS", min=0.0, rich_help_panel=STREAM, help="While "
    "frames wait for bone detection, start an update at most this often (the frames detected "
    "meanwhile wait for it), leaving the processor to detection. 0: as often as frames come.")
LIVE_DETECT_WORKERS = typer.Option(
    None, "--detect-workers", min=0, rich_help_panel=STREAM, help="Processes that find the bone "
    "in the frames beside the update loop (default: one per core less one, two on 2 cores, 1 to "
    "4; 0: in the live process).")
LIVE_CT = typer.Option(..., "--ct", rich_help_panel=INPUTS, help="The CT bone mesh (mm).")
LIVE_CALIBRATION = typer.Option(
    None, "--probe-calibration", "--calibration", rich_help_panel=INPUTS,
    help="The probe calibration (as 'comreg extract-us' takes it: a PLUS device-set XML with "
    "ImageToProbe, or calibration.json) when the poses streamed are the probe's (default device "
    "then ProbeToReference). --calibration: its former name.")
LIVE_MODEL = typer.Option(None, "--model", rich_help_panel=NETWORK, help="Run folder written by "
                          "'comreg pretrain': the network's pose first, then the search around "
                          "it (default: the search alone).")
LIVE_BACKGROUND = typer.Option(True, "--background-search/--inline-search",
                               rich_help_panel=SEARCH, help="Run the full searches in a second "
                               "process while warm updates go on (default), or in the update "
                               "loop.")
LIVE_SEED = typer.Option(0, "--seed", min=0, rich_help_panel=SEARCH,
                          help="Random seed of the registrations.")
LIVE_VERDICT_CALIBRATION = typer.Option(
    None, "--verdict-calibration", rich_help_panel=VERDICT, help="calibration.json from 'comreg "
    "calibrate' (default: the run folder's own): the verdict is then OK only when p_correct >= "
    "0.95.")
LIVE_OUT = typer.Option(None, "--out", "-o", rich_help_panel=OUTPUT, help="Output folder: "
                        "updates.csv as it goes; on stop what 'comreg register' and 'comreg "
                        "report' write for the points.")
LIVE_REPORT = typer.Option(True, "--report/--no-report", rich_help_panel=OUTPUT, help="With "
                           "--out, also write report.html on stop (screenshots: some seconds).")


@app.command("live", rich_help_panel=PANEL)
def live(
    igtl: str = LIVE_IGTL,
    image_device: str = LIVE_IMAGE_DEVICE,
    transform_device: Optional[str] = LIVE_TRANSFORM_DEVICE,
    send_device: str = LIVE_SEND_DEVICE,
    until_end: bool = LIVE_UNTIL_END,
    connect_timeout: float = LIVE_CONNECT_TIMEOUT,
    frame_spacing: str = LIVE_SPACING,
    max_frame_age: float = LIVE_MAX_AGE,
    detect_workers: Optional[int] = LIVE_DETECT_WORKERS,
    update_every: float = LIVE_UPDATE_EVERY,
    ct_mesh: Path = LIVE_CT,
    calibration: Optional[Path] = LIVE_CALIBRATION,
    model: Optional[Path] = LIVE_MODEL,
    device: Device = DEVICE_OPTION,
    background: bool = LIVE_BACKGROUND,
    seed: int = LIVE_SEED,
    init: Optional[Path] = INIT_OPTION,
    init_tolerance: Optional[str] = INIT_TOLERANCE_OPTION,
    landmarks: Optional[tuple[Path, Path]] = LANDMARKS_OPTION,
    landmark_tolerance: Optional[float] = LANDMARK_TOLERANCE_OPTION,
    verdict_calibration: Optional[Path] = LIVE_VERDICT_CALIBRATION,
    out: Optional[Path] = LIVE_OUT,
    report: bool = LIVE_REPORT,
) -> None:
    """Register while scanning: connect to an OpenIGTLink server, take its B-mode frames (IMAGE)
    and their poses (TRANSFORM, PLUS names such as ImageToReference), find the bone in each
    frame as 'comreg extract-us' does, and register the growing sweep to the CT: warm from the
    last pose each update, the full search when the evidence changes.

    Each update sends back a TRANSFORM (ReferenceToCT: the stream's reference frame to the CT,
    as 3D Slicer applies it) and a STRING ComRegStatus (JSON: verdict, p_correct, the bone
    covered in mm, advice: 'enough' or which end to scan towards), and prints one status line.
    A lost connection is reconnected and nothing registered is lost. A prior from the operating
    room (--init, --landmarks; as 'comreg register' takes them, in the stream's reference
    frame) bounds every update and the final registration. Stop with Ctrl-C (or
    --until-end, or SIGTERM); --out then gets the files of 'comreg register' and its
    report. When no server answers within --connect-timeout (30 s), live gives up with exit
    status 2 and writes nothing.
    """
    from comreg_core.live.igtl import IMAGE_POSE_DEVICE, PROBE_POSE_DEVICE
    from comreg_core.live.stream import probe_calibration
    from comreg_core.register.inputs import load_prior

    host, port = _host_port(igtl)
    _check_connect_timeout(connect_timeout)
    _check_inputs(out, ct_mesh, model, calibration, verdict_calibration, init, landmarks)
    prior = load_prior(init, init_tolerance, landmarks, landmark_tolerance)
    T_probe_pixel = None if calibration is None else probe_calibration(calibration)
    pose_device = transform_device or (IMAGE_POSE_DEVICE if calibration is None
                                       else PROBE_POSE_DEVICE)
    _check_device_names(image_device, pose_device, send_device)
    frames, update_every_s = _frame_rules(frame_spacing, max_frame_age, update_every)
    session, recipe = _session(ct_mesh, model, device, verdict_calibration, prior, seed, frames)
    summary = _listen(session, recipe, (background, detect_workers, update_every_s),
                      (host, port), image_device, pose_device, send_device, T_probe_pixel,
                      until_end, connect_timeout, out)
    typer.echo(summary.line())
    if out is not None:
        _finish(session, out, model, ct_mesh, device, verdict_calibration, prior, report)


def _frame_rules(spacing: str, max_age: float, update_every: float) -> tuple[dict, float]:
    """``--frame-spacing MM,DEG`` and ``--max-frame-age`` as the session's ``spacing`` (a
    :class:`~comreg_core.live.intake.FrameSpacing`, None for 0,0: every frame) and
    ``max_frame_age_s`` (None for inf), and ``--update-every`` (s); a :class:`ComRegError`
    when they are not numbers of that kind."""
    import math

    from comreg_core.errors import ComRegError
    from comreg_core.live.intake import FrameGate, FrameSpacing

    try:
        mm, deg = (float(v) for v in spacing.split(","))
    except ValueError:
        raise ComRegError(f"--frame-spacing '{spacing}' is not MM,DEG.",
                          "Give e.g. --frame-spacing 0.5,0.5 (0,0 uses every frame).") from None
    rules = {"spacing": None if FrameSpacing(mm, deg) == FrameSpacing(0.0, 0.0)
             else FrameSpacing(mm, deg),
             "max_frame_age_s": None if max_age == float("inf") else max_age}
    FrameGate(rules["spacing"], rules["max_frame_age_s"])  # refuses a bad age limit
    if not math.isfinite(update_every):
        raise ComRegError(f"--update-every {update_every:g} is not a finite number of seconds.",
                          "Give e.g. --update-every 0.2 (0: as often as frames come).")
    return rules, update_every


def _check_connect_timeout(seconds: float) -> float:
    """``seconds`` when it is a positive, finite number; a :class:`ComRegError` otherwise."""
    import math

    from comreg_core.errors import ComRegError

    if not (math.isfinite(seconds) and seconds > 0):
        raise ComRegError(f"--connect-timeout {seconds:g} is not a positive, finite number of "
                          "seconds.", "Give e.g. --connect-timeout 30 (the default).")
    return seconds


def _host_port(text: str) -> tuple[str, int]:
    """``HOST:PORT`` -> ``(host, port)``; a :class:`ComRegError` when it is not one."""
    from comreg_core.errors import ComRegError

    host, _, port = text.rpartition(":")
    try:
        number = int(port)
        if not host or not 0 < number < 65536:
            raise ValueError
    except ValueError:
        raise ComRegError(f"--igtl '{text}' is not HOST:PORT.",
                          "Give the OpenIGTLink server as e.g. --igtl 127.0.0.1:18944 (PLUS "
                          "Server's default port).") from None
    return host.strip("[]"), number


def _check_inputs(out, ct_mesh, model, calibration, verdict_calibration, init, landmarks) -> None:
    """Before connecting: --out can be written and the CT mesh exists."""
    from comreg_core.io._files import check_output_folder, require_input_file

    inputs = [ct_mesh, model, calibration, verdict_calibration, init, *(landmarks or ())]
    if out is not None:
        check_output_folder(out, inputs=inputs)
    require_input_file(ct_mesh, "CT bone mesh")


def _check_device_names(image_device: str, pose_device: str, send_device: str) -> None:
    from comreg_core.errors import ComRegError

    if not image_device.strip() or not pose_device.strip() or not send_device.strip():
        raise ComRegError("A device name is empty.", "Give --image-device, --transform-device "
                          "and --send-device names, e.g. Image and ImageToReference.")


def _session(ct_mesh, model, device: Device, verdict_calibration, prior, seed: int,
             frames: dict):
    """``(the live session, the recipe of its registrar)``; a verdict calibration made for
    another CT, or for registrations that know more than ``prior``, is refused here, before
    any work. ``frames``: the session's ``spacing`` and ``max_frame_age_s``."""
    from comreg_core.live.background import RegistrarRecipe, build_registrar
    from comreg_core.live.session import LiveSession
    from comreg_core.register.inputs import calibration_path, find_calibration
    from comreg_core.registration.search.priors import prior_kind

    verdict = find_calibration(verdict_calibration, model)
    recipe = RegistrarRecipe(str(ct_mesh), None if model is None else str(model), device.value)
    registrar = build_registrar(recipe)
    if verdict is not None:
        note = verdict.check_fits(registrar.fingerprint, prior_kind(prior),
                                  calibration_path(verdict_calibration, model))
        if note:
            typer.echo(f"live: {note}", err=True)
    return LiveSession(registrar, calibration=verdict, prior=prior, seed=seed, **frames), recipe


def _listen(session, recipe, work: tuple, where: tuple[str, int],
            image_device: str, pose_device: str, send_device: str, T_probe_pixel,
            until_end: bool, connect_timeout: float, out):
    """Prepare the CT side (and the full-search and detection workers), then register the
    stream's frames until it stops; returns the run's summary. ``work``: ``(background
    search, detection workers or None, seconds between updates)``."""
    from comreg_core.live.background import (WORKER_START_S, FullSearchWorker,
                                             keep_freed_memory, one_thread)
    from comreg_core.live.detection import DetectionPool, default_workers
    from comreg_core.live.receiver import FrameReceiver
    from comreg_core.live.run import run_live, stop_on_signals

    host, port = where
    background, detect_workers, update_every_s = work
    with ExitStack() as stack:
        if background:
            session.worker = stack.enter_context(FullSearchWorker(recipe, session.prior))
            session.first_search_beside = True  # no update waits for a search
        workers = default_workers() if detect_workers is None else detect_workers
        pool = stack.enter_context(DetectionPool(workers, session.points.config))
        stack.enter_context(one_thread())
        keep_freed_memory()
        typer.echo("preparing the CT side ...", err=True)
        session.warm_up()
        if session.worker is not None and not session.worker.wait_ready(WORKER_START_S):
            typer.echo("live: the full-search worker is not ready; the update loop runs the "
                       "full searches until it is", err=True)
        if not pool.wait_ready(WORKER_START_S):
            pool.close()
            typer.echo("live: the detection workers are not ready; frames are detected in "
                       "the live process", err=True)
        receiver = FrameReceiver(host, port, image_device, pose_device, T_probe_pixel,
                                 reconnect=not until_end, connect_timeout_s=connect_timeout)
        typer.echo(f"listening to {host}:{port} for IMAGE '{image_device}' + TRANSFORM "
                   f"'{pose_device}'; sending '{send_device}' (Ctrl-C to stop)", err=True)
        with stop_on_signals() as stop:
            return run_live(session, receiver, out_dir=out, until_end=until_end, stop=stop,
                            send_device=send_device, on_status=typer.echo, pool=pool,
                            update_every_s=update_every_s,
                            on_note=lambda line: typer.echo(f"live: {line}", err=True))


def _finish(session, out: Path, model, ct_mesh, device: Device, verdict_calibration, prior,
            report: bool) -> None:
    """On stop, with --out: what 'comreg register' (and 'comreg report') write."""
    from comreg_core.live.run import finish_live
    from comreg_core.register.folder import summary_lines

    result, page = finish_live(session, out, run_dir=model, ct_mesh=ct_mesh, device=device.value,
                               calibration=verdict_calibration, prior=prior, report=report)
    for line in summary_lines(result, out, with_network=model is not None):
        typer.echo(line)
    if page is not None:
        typer.echo(f"wrote {page}")


# --- comreg replay -------------------------------------------------------------------------------
REPLAY_SWEEP = typer.Argument(..., help="A recorded tracked sweep: PLUS sequence (.igs.mha, "
                              ".seq.mha, .igs.nrrd, .seq.nrrd), a frame folder (frames + "
                              "tracking.csv + calibration.json) or a 3D Slicer volume sequence.")
REPLAY_CALIBRATION = typer.Option(None, "--probe-calibration", "--calibration",
                                  rich_help_panel=INPUTS, help="Its probe calibration (as "
                                  "'comreg extract-us' takes it; a frame folder's own by "
                                  "default): also gives the ProbeToReference poses. "
                                  "--calibration: its former name.")
REPLAY_FIRST_FRAME = typer.Option(0, "--first-frame", min=0, rich_help_panel=INPUTS,
                                  help="Begin at this frame (0 = the first).")
REPLAY_PORT = typer.Option(18944, "--port", min=0, max=65535, rich_help_panel=STREAM,
                           help="The port to serve on (0: a free one, printed).")
REPLAY_HOST = typer.Option("127.0.0.1", "--host", rich_help_panel=STREAM,
                           help="The address to serve on.")
REPLAY_RATE = typer.Option(1.0, "--rate", rich_help_panel=STREAM, help="Speed: 1 = as recorded, "
                           "4 = four times as fast.")
REPLAY_FPS = typer.Option(None, "--fps", rich_help_panel=STREAM, help="Send at this fixed "
                          "frame rate instead of the recorded timing (e.g. 40: a scanner's "
                          "rate).")
REPLAY_WAIT = typer.Option(None, "--wait", min=0.0, rich_help_panel=STREAM, help="Give up when "
                           "no client connects within this many seconds (default: wait).")


@app.command("replay", rich_help_panel=PANEL)
def replay(
    sweep: Path = REPLAY_SWEEP,
    calibration: Optional[Path] = REPLAY_CALIBRATION,
    first_frame: int = REPLAY_FIRST_FRAME,
    port: int = REPLAY_PORT,
    host: str = REPLAY_HOST,
    rate: float = REPLAY_RATE,
    fps: Optional[float] = REPLAY_FPS,
    wait: Optional[float] = REPLAY_WAIT,
) -> None:
    """Serve a recorded sweep over OpenIGTLink as PLUS Server would for a tracked probe: per
    frame an IMAGE 'Image', its TRANSFORM 'ImageToReference' and the probe's TRANSFORM
    'ProbeToReference' (where the recording gives it or its calibration derives it) with the
    same time stamp, at the recorded rate (or --rate times it), to the first client that
    connects (--fps: at a fixed frame rate instead); then close the connection, so that
    'comreg live --until-end' stops.
    """
    import math

    from comreg_core.errors import ComRegError
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.live.background import keep_freed_memory
    from comreg_core.live.replay import ReplayServer, replay_sweep
    from comreg_core.live.stream import recorded_probe_poses

    if not (math.isfinite(rate) and rate > 0):
        raise ComRegError(f"--rate {rate:g} is not a positive speed.", "Give e.g. --rate 1.")
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise ComRegError(f"--fps {fps:g} is not a positive frame rate.", "Give e.g. --fps 40.")
    tracked = read_tracked_sweep(sweep, calibration=calibration)
    if first_frame >= tracked.n_frames:
        raise ComRegError(f"--first-frame {first_frame} is outside the sweep's "
                          f"{tracked.n_frames} frames.",
                          f"Give a frame number from 0 to {tracked.n_frames - 1}.")
    probe_poses, source = recorded_probe_poses(tracked, calibration)
    keep_freed_memory()  # a frame's messages are built anew at every send
    server = ReplayServer(host, port)
    speed = f"x{rate:g}" if fps is None else f"{fps:g} frames/s"
    typer.echo(f"serving {sweep} ({tracked.n_frames - first_frame} frames from frame "
               f"{first_frame}, {speed}) on {host}:{server.port}; waiting for a client",
               err=True)
    if probe_poses is None:
        typer.echo(f"replay: sending ImageToReference only, no ProbeToReference: {source}",
                   err=True)
    try:
        stats = replay_sweep(tracked, server, rate=rate, first_frame=first_frame, wait_s=wait,
                             probe_poses=probe_poses, fps=fps)
    except KeyboardInterrupt:
        server.close()
        typer.echo("stopped (Ctrl-C)", err=True)
        return
    typer.echo(f"served {stats.frames} frames in {stats.duration_s:.1f} s: {stats.sent} sent"
               + (f", {stats.unsent} while no client was connected" if stats.unsent else "")
               + (f", {stats.without_pose} without a pose" if stats.without_pose else "")
               + (f", {stats.without_probe} without a probe pose"
                  if stats.without_probe and probe_poses is not None else "")
               + f"; on time within {1000 * stats.late_max_s:.0f} ms (median "
               f"{1000 * stats.late_median_s:.0f} ms)")
