"""The ``comreg`` command line. Thin: every command calls library functions and prints results.

Heavy imports (VTK, torch) happen inside commands so ``comreg --help`` stays fast. Every command
checks its output places before any work; errors a user can fix (:class:`comreg_core.errors.
ComRegError`, and what the operating system refuses) are printed as one line and exit with status
2, in one place for all commands (:mod:`comreg_core.cli_errors`).
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from comreg_core import choices, runs
from comreg_core import __version__
from comreg_core.cli_batch import batch as batch_command
from comreg_core.cli_calibrate import calibrate as calibrate_command
from comreg_core.cli_errors import CommandApp, set_verbose
from comreg_core.cli_evaluate import evaluate as evaluate_command
from comreg_core.cli_live import live as live_command
from comreg_core.cli_live import replay as replay_command
from comreg_core.cli_shared import (INIT_OPTION, INIT_TOLERANCE_OPTION, LANDMARK_TOLERANCE_OPTION,
                                     LANDMARKS_OPTION, Device)
from comreg_core.cli_shared import progress_bar as _progress_bar

app = CommandApp(
    name="comreg",
    help="ComReg: patient-specific CT-ultrasound bone surface registration.\n\n"
    "Extract the CT bone surface, pretrain on ultrasound sweeps simulated from it, then register "
    "a real tracked-ultrasound bone surface in one forward pass. Every command prints what it "
    "wrote; errors you can fix exit with status 2 and say what to do.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"comreg {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print the version and exit."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details."),
) -> None:
    set_verbose(verbose)


class SurfaceMethod(str, Enum):
    flying_edges = "flying_edges"
    surface_nets = "surface_nets"


@app.command("extract-ct")
def extract_ct(
    segmentation: Path = typer.Argument(
        ..., help="CT bone segmentation: label map (.nrrd, .nhdr, .mha, .mhd), 3D Slicer "
        ".seg.nrrd, or a bone mesh (.stl, .ply, .obj, .vtk, .vtp) to validate and pass through."),
    out: Path = typer.Option(..., "--out", "-o", help="Output mesh (.stl, .ply, .obj, .vtk, .vtp)."),
    label: Optional[int] = typer.Option(None, "--label", help="Label value of the bone."),
    segment: Optional[str] = typer.Option(None, "--segment", help="Segment name (or ID) of the bone."),
    method: Optional[SurfaceMethod] = typer.Option(
        None, help="Meshing algorithm (default flying_edges: discrete marching cubes)."),
    smoothing: Optional[float] = typer.Option(
        None, min=0.0, max=1.0, help="Smoothing strength 0..1 (default keeps the surface within "
        "0.2 mm of the unsmoothed one)."),
    decimation: Optional[float] = typer.Option(
        None, min=0.0, max=0.99, help="Fraction of triangles to remove (0 = none)."),
    largest_component: bool = typer.Option(
        False, "--largest-component/--all-components", help="Keep only the largest connected piece."),
) -> None:
    """Extract the closed CT bone surface mesh (patient mm) from a segmentation.

    Reads a label map or a 3D Slicer .seg.nrrd, picks the bone (--label or --segment; needed when
    there are several), meshes it with VTK and writes the mesh in the segmentation's coordinate
    system, tagged SPACE=LPS/RAS like 3D Slicer models. A mesh input is validated and repaired.
    """
    from comreg_core.io import MESH_EXTENSIONS, read_mesh, read_segmentation, write_mesh
    from comreg_core.io._files import check_output_file, file_extension, require_extension
    from comreg_core.surfaces.ct import SurfaceExtractionOptions, extract_bone_surface
    from comreg_core.surfaces.mesh_repair import prepare_bone_mesh

    require_extension(out, "mesh", MESH_EXTENSIONS)
    check_output_file(out, inputs=[segmentation], what="output mesh")
    if file_extension(segmentation) in MESH_EXTENSIONS:
        mesh = prepare_bone_mesh(read_mesh(segmentation), largest_component=largest_component)
    else:
        seg = read_segmentation(segmentation)
        chosen = seg.find_segment(name=segment, label=label)
        chosen_options = {"method": method.value if method else None, "smoothing": smoothing,
                          "decimation": decimation, "largest_component": largest_component}
        options = SurfaceExtractionOptions(
            **{key: value for key, value in chosen_options.items() if value is not None})
        mesh = extract_bone_surface(seg, segment=chosen, options=options)
    write_mesh(mesh, out)
    typer.echo(f"wrote {out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles, "
               f"SPACE={mesh.space}")


@app.command("simulate")
def simulate(
    ct_mesh: Path = typer.Argument(..., help="CT bone mesh (.stl, .ply, .obj, .vtk, .vtp), in mm."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    count: int = typer.Option(1, "--count", "-n", min=1, help="Number of sweeps."),
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed; the same seed gives the same "
                             "sweeps."),
    config: Optional[Path] = typer.Option(None, "--config", help="Simulation config YAML (e.g. "
                                          "the config.yaml of an earlier run)."),
) -> None:
    """Simulate tracked freehand US sweeps of a CT bone (paper, section 2).

    Rays are cast from a linear probe moving along trajectories drawn from the bone's geometry;
    only the first hit per ray is kept (acoustic shadowing), with the paper's probe tilts,
    non-uniform speed, dropped slices and false hits. Writes sweep_NNNN.ply (points in the mesh's
    frame), sweep_NNNN_slices.npy (slice index per point), sweep_NNNN_poses.npy (probe image
    poses) and config.yaml.
    """
    from comreg_core.simulation import simulate_to_directory

    with _progress_bar(count, "simulating") as advance:
        paths = simulate_to_directory(ct_mesh, out, count=count, seed=seed, config=config,
                                      progress=lambda done, total, note="": advance(done))
    typer.echo(f"wrote {len(paths)} sweep(s) and config.yaml to {out}")


class CompoundMode(str, Enum):
    mean = "mean"
    max = "max"


@app.command("extract-us")
def extract_us(
    sweep: Path = typer.Argument(
        ..., help="Tracked US sweep: PLUS sequence (.igs.mha, .seq.mha, .igs.nrrd, .seq.nrrd), a "
        "frame folder (PNG frames + tracking.csv + calibration.json), a 3D Slicer volume "
        "sequence (.seq.nrrd), or a reconstructed 3D US volume (.nrrd, .mha)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output point cloud (.ply, .pcd, .xyz, "
                             ".npy, ...), bone surface points in the tracking reference frame."),
    calibration: Optional[Path] = typer.Option(
        None, "--calibration", help="Image-to-probe calibration: a PLUS device-set XML "
        "(ImageToProbe) or calibration.json for a frame folder."),
    masks: Optional[Path] = typer.Option(
        None, "--masks", help="Bone label masks instead of detecting the bone in the B-mode "
        "frames: a folder of mask images named like the frames, a mask sequence or a label "
        "volume."),
    config: Optional[Path] = typer.Option(None, "--config", help="US extraction config YAML "
                                          "(detector and denoising parameters)."),
    compound: Optional[Path] = typer.Option(
        None, "--compound", help="Also compound the frames into this 3D volume (.nrrd, .mha) to "
        "look at."),
    compound_spacing: float = typer.Option(0.5, min=0.01, help="Voxel size of --compound (mm)."),
    compound_mode: CompoundMode = typer.Option(CompoundMode.mean, help="Voxel value of "
                                               "--compound where frames overlap."),
    beam_direction: str = typer.Option("auto", "--beam-direction", help="A reconstructed "
                                       "volume's beam: auto, or a voxel axis x, -x, y, -y, z, -z."),
) -> None:
    """Extract the bone surface seen by a tracked US sweep as a point cloud.

    Reads the frames and their image-to-reference poses, finds the bone in every frame (from
    --masks, or with the shadow-aware B-mode detector: a bright thin ridge with an acoustic shadow
    below it), maps the bone pixels to millimetres in the tracking reference frame and removes
    outliers (largest clusters, statistical outlier removal).
    """
    from comreg_core.io import write_volume
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import check_us_outputs, extract_us_to_file
    from comreg_core.surfaces.us_compounding import compound_sweep
    from comreg_core.surfaces.us_config import load_us_extraction_config

    from comreg_core.surfaces.us_volume import extract_volume_to_file, is_volume_file

    check_us_outputs(out, compound, inputs=[sweep, calibration, masks, config])
    if is_volume_file(sweep):
        typer.echo("wrote " + extract_volume_to_file(
            sweep, out, beam_direction=beam_direction, config=config,
            frame_options={"--calibration": calibration, "--masks": masks,
                           "--compound": compound}).summary())
        return
    settings = load_us_extraction_config(config)
    tracked = read_tracked_sweep(sweep, calibration=calibration, reference=settings.reference)
    with _progress_bar(len(tracked.frames), "detecting bone") as advance:
        result = extract_us_to_file(tracked, out, masks=masks, config=settings,
                                    progress=lambda done, total, note="": advance(done))
    typer.echo(f"wrote {result.summary()}")
    if compound is not None:
        volume = compound_sweep(tracked, compound_spacing, compound_mode.value)
        write_volume(volume, compound)
        typer.echo(f"wrote {compound}: compounded volume {' x '.join(map(str, volume.array.shape))}"
                   f" voxels of {compound_spacing} mm")


Preset = Enum("Preset", {name: name for name in choices.PRESETS}, type=str)


@app.command("pretrain")
def pretrain(
    ct_mesh: Path = typer.Argument(..., help="The patient's CT bone mesh (mm), a closed surface."),
    out: Path = typer.Option(..., "--out", "-o", help="Run folder (checkpoint, config.yaml, "
                             "training_log.csv, CT fingerprint)."),
    preset: Preset = typer.Option(Preset.cpu, help="Network size and schedule: 'cpu' (small, "
                                  "fast on a laptop) or 'paper' (the paper's, for a GPU)."),
    max_minutes: Optional[float] = typer.Option(None, "--max-minutes", min=0.1,
                                                help="Wall-clock budget of this whole command "
                                                "(set-up and validation included); less than "
                                                "one epoch in it is an error."),
    epochs: Optional[int] = typer.Option(None, "--epochs", min=1, help="Total epochs."),
    resume: bool = typer.Option(False, "--resume", help="Continue the run in --out from its "
                                "last checkpoint."),
    seed: Optional[int] = typer.Option(None, "--seed", min=0, help="Run seed (default 0)."),
    device: Device = typer.Option(Device.auto, help="Where to train."),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML overrides of the preset "
                                          "(sections model, simulation, data, training)."),
    calibration_sweeps: int = typer.Option(0, "--calibration-sweeps", min=0, help="Then also "
                                           "calibrate the verdict on this many simulated "
                                           "sweeps (as 'comreg calibrate'; about 3 s each) into "
                                           "the run folder; 0: not."),
) -> None:
    """Pretrain ComReg for one patient on US sweeps simulated from their CT bone.

    Each sample is a simulated sweep moved by a random rigid transform; the network learns shape
    completion and the inverse transform end to end (paper, section 2). Checkpoints are written
    atomically; a killed run continues with --resume. On several GPUs or machines: start it with
    torchrun (README, "Training on several GPUs or machines").
    """
    from comreg_core.training import pretrain as run_pretraining

    with _progress_bar(1000, "pretraining") as advance:
        result = run_pretraining(
            ct_mesh, out, preset=preset.value, config=config, max_minutes=max_minutes,
            epochs=epochs, resume=resume, seed=seed, device=device.value,
            progress=lambda done, total, note="": advance(int(1000 * done / max(total, 1))))
    if result.rank:
        return  # rank 0 reports for the job
    validation = result.validation or {}
    summary = ", ".join(f"{key} {value:.3g}" for key, value in validation.items()
                        if key in ("val_RTE_mm_median", "val_RRE_deg_median", "val_success_rate"))
    typer.echo(f"wrote {result.run_dir}: {result.epochs} epochs, {result.samples_seen} samples in "
               f"{result.elapsed_s / 60:.1f} min on {result.device}"
               + (f" x {result.world_size} processes" if result.world_size > 1 else "")
               + f" (stopped: {result.stopped})"
               + (f"; validation {summary}" if summary else ""))
    from comreg_core.training.checkpoint import network_warning

    warning = network_warning({"epoch": result.epochs, "validation": result.validation,
                               "initial_error": result.initial_error})
    if warning:
        typer.echo(f"warning: {warning}", err=True)
    if calibration_sweeps:
        from comreg_core.evaluation.calibrate import calibrate

        path = calibrate(ct_mesh, sweeps=calibration_sweeps).save(
            Path(result.run_dir) / runs.CALIBRATION)
        typer.echo(f"wrote {path}: register with this run judges by p_correct")


@app.command("register")
def register(
    inputs: list[Path] = typer.Argument(..., help="US bone surface points (.ply, .pcd, .xyz, "
                                        ".npy, ...), e.g. from 'comreg extract-us'; several "
                                        "files (sweeps in one tracker frame) are joined and "
                                        "registered as one. (The older form RUN_DIR US_POINTS "
                                        "is still accepted.)", metavar="US_POINTS..."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    ct_mesh: Optional[Path] = typer.Option(None, "--ct", help="The CT bone mesh (mm). Alone: "
                                           "register by the pose search, no network. With "
                                           "--model: checked to be the run's CT."),
    model: Optional[Path] = typer.Option(None, "--model", help="Run folder written by 'comreg "
                                         "pretrain': the network's pose first, then the "
                                         "search around it."),
    device: Device = typer.Option(Device.auto, help="Where to run the network."),
    seed: int = typer.Option(0, "--seed", min=0),
    hypotheses: bool = typer.Option(True, "--hypotheses/--no-hypotheses", help="After the "
                                    "network, also try the alternatives of its pose (flipped end "
                                    "to end, turned about the shaft, slid along it; around the "
                                    "coarse pose and a principal-axes solve too), keep the one "
                                    "that fits the CT best and flag the result ambiguous when "
                                    "another pose fits about as well. --no-hypotheses is the "
                                    "paper's plain pipeline."),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML with a 'hypotheses:' "
                                          "section (the pose search's settings), e.g. the "
                                          "config.yaml of an earlier registration."),
    sweep: Optional[Path] = typer.Option(None, "--sweep", help="The tracked sweep the points "
                                         "came from (one US points file only): the report "
                                         "shows its frames with the registered CT contour."),
    calibration: Optional[Path] = typer.Option(None, "--calibration", help="Its calibration."),
    verdict_calibration: Optional[Path] = typer.Option(
        None, "--verdict-calibration", help="calibration.json from 'comreg calibrate' (default: "
        "the run folder's own, if pretrain wrote one): result.json then gets p_correct and the "
        "verdict is OK only when p_correct >= 0.95."),
    init: Optional[Path] = INIT_OPTION,
    init_tolerance: Optional[str] = INIT_TOLERANCE_OPTION,
    landmarks: Optional[tuple[Path, Path]] = LANDMARKS_OPTION,
    landmark_tolerance: Optional[float] = LANDMARK_TOLERANCE_OPTION,
) -> None:
    """Register a US bone surface to the CT: with --ct alone by the pose search (principal axes,
    flips, turns and slides of the US cloud, refined by ICP and scored against the CT), with
    --model in one forward pass of the pretrained network (completion, coarse pose, ICP), then
    the search around its pose (unless --no-hypotheses).

    Writes result.json (T_ct_us 4x4 in mm, the coarse transform, timings, residuals, the
    chosen hypothesis, confidence and the ambiguous flag), transform.tfm (ITK, LPS, as 3D Slicer
    reads it), registered_us.ply and completion_ct.ply in the CT frame. A cloud of more than
    100,000 points is registered as a seeded uniform subset of 100,000 (said in a warning).
    --out must not be the run folder or inside it.
    """
    from comreg_core.register_output import (load_prior, register_inputs,
                                             register_to_directory, summary_lines)
    from comreg_core.registration.config import load_register_config

    run_dir, us_points = register_inputs(inputs, model)
    prior = load_prior(init, init_tolerance, landmarks, landmark_tolerance)
    search = load_register_config(config, {"hypotheses": {"enabled": False}} if not hypotheses
                                  else None).hypotheses
    result = register_to_directory(run_dir, us_points, out, device=device.value, seed=seed,
                                   ct_mesh=ct_mesh, hypotheses=search, sweep=sweep,
                                   sweep_calibration=calibration,
                                   calibration=verdict_calibration, prior=prior)
    for line in summary_lines(result, out, with_network=run_dir is not None):
        typer.echo(line)


@app.command("report")
def report(
    out_dir: Path = typer.Argument(..., help="Folder written by 'comreg register'."),
    ct_mesh: Optional[Path] = typer.Option(None, "--ct", help="CT mesh (default: the one the "
                                           "run was trained on)."),
    embed_images: bool = typer.Option(False, "--embed-images", help="One self-contained HTML."),
    transform: Optional[Path] = typer.Option(
        None, "--transform", help="Judge and show this T_ct_us (ITK .tfm/.h5, e.g. edited or "
        "from another tool) on the folder's US points and CT instead of the registration's."),
    sweep: Optional[Path] = typer.Option(None, "--sweep", help="The points' tracked sweep "
                                         "(default: register's): frames with the CT contour."),
    calibration: Optional[Path] = typer.Option(None, "--calibration", help="Its calibration."),
) -> None:
    """Judge the registration (Verdict: OK or CHECK, from the US points, the transform and the
    CT alone), render off-screen screenshots (US points coloured by distance to the CT, before
    and after, completion) and write report.html with the verdict, metrics, inputs, versions."""
    from comreg_core.report import write_report_for_registration

    path = write_report_for_registration(out_dir, ct_mesh=ct_mesh, transform=transform,
                                         embed_images=embed_images, sweep=sweep,
                                         sweep_calibration=calibration)
    typer.echo(f"wrote {path}")


@app.command("demo")
def demo(
    out: Path = typer.Option(Path("out/demo"), "--out", "-o", help="Output folder."),
    device: Device = typer.Option(Device.auto, help="Where to run the network."),
    trials: int = typer.Option(10, "--trials", min=0, help="Extra random starts evaluated into "
                               "metrics.json."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the misalignment and trials."),
    train_minutes: float = typer.Option(10.0, "--train-minutes", min=0.1, help="Pretraining "
                                        "budget if the bundled model does not fit."),
) -> None:
    """Run the whole job on the bundled sample (a cadaver fibula, CC BY 4.0): extract the CT and
    US bone surfaces, move the US points by a known misalignment, register them with the bundled
    pretrained model, evaluate, and write an HTML report with screenshots.

    The errors are measured against ICP from the recorded tracking (the paper's pseudo ground
    truth; the recording itself lies a little off the CT bone, and the summary says how far)."""
    from comreg_core.demo import run_demo, summary_lines

    result = run_demo(out, device=device.value, train_minutes=train_minutes, trials=trials,
                      seed=seed, step=lambda line: typer.echo(f"- {line}"))
    for line in summary_lines(result, trials):
        typer.echo(line)


@app.command("info")
def info(path: Path = typer.Argument(..., help="Any file ComReg reads.")) -> None:
    """Show what ComReg reads from a file: kind, size, spatial metadata, coordinate system."""
    from comreg_core.io import describe_file

    typer.echo(describe_file(path))


app.command("evaluate")(evaluate_command)
app.command("calibrate")(calibrate_command)
app.command("live")(live_command)
app.command("replay")(replay_command)
app.command("batch")(batch_command)


def main() -> None:
    """Entry point of the ``comreg`` console script."""
    app()


if __name__ == "__main__":
    main()
