"""The ``comreg`` command line. Thin: every command calls library functions and prints results.

Heavy imports (VTK, torch) happen inside commands so ``comreg --help`` stays fast. Errors a user
can fix (:class:`comreg_core.errors.ComRegError`) are printed as one message and exit with status 2.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import sys
from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from comreg_core import __version__

app = typer.Typer(
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
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")


def _user_errors(command):
    """Turn ComRegError into a one-line message on stderr and exit status 2."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        from comreg_core.errors import ComRegError

        try:
            return command(*args, **kwargs)
        except ComRegError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None

    return wrapper


class SurfaceMethod(str, Enum):
    flying_edges = "flying_edges"
    surface_nets = "surface_nets"


@app.command("extract-ct")
@_user_errors
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
    from comreg_core.io._files import file_extension
    from comreg_core.surfaces.ct import (SurfaceExtractionOptions, extract_bone_surface,
                                         prepare_bone_mesh)

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
@_user_errors
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
                                      progress=lambda done, total: advance(done))
    typer.echo(f"wrote {len(paths)} sweep(s) and config.yaml to {out}")


class CompoundMode(str, Enum):
    mean = "mean"
    max = "max"


@app.command("extract-us")
@_user_errors
def extract_us(
    sweep: Path = typer.Argument(
        ..., help="Tracked US sweep: PLUS sequence (.igs.mha, .seq.mha, .igs.nrrd, .seq.nrrd), a "
        "frame folder (PNG frames + tracking.csv + calibration.json) or a 3D Slicer volume "
        "sequence (.seq.nrrd)."),
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
) -> None:
    """Extract the bone surface seen by a tracked US sweep as a point cloud.

    Reads the frames and their image-to-reference poses, finds the bone in every frame (from
    --masks, or with the shadow-aware B-mode detector: a bright thin ridge with an acoustic shadow
    below it), maps the bone pixels to millimetres in the tracking reference frame and removes
    outliers (largest clusters, statistical outlier removal).
    """
    from comreg_core.io import write_volume
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import (compound_sweep, extract_us_to_file,
                                         load_us_extraction_config)

    settings = load_us_extraction_config(config)
    tracked = read_tracked_sweep(sweep, calibration=calibration, reference=settings.reference)
    with _progress_bar(len(tracked.frames), "detecting bone") as advance:
        result = extract_us_to_file(tracked, out, masks=masks, config=settings,
                                    progress=lambda done, total: advance(done))
    typer.echo(f"wrote {result.summary()}")
    if compound is not None:
        volume = compound_sweep(tracked, compound_spacing, compound_mode.value)
        write_volume(volume, compound)
        typer.echo(f"wrote {compound}: compounded volume {' x '.join(map(str, volume.array.shape))}"
                   f" voxels of {compound_spacing} mm")


@app.command("info")
@_user_errors
def info(path: Path = typer.Argument(..., help="Any file ComReg reads.")) -> None:
    """Show what ComReg reads from a file: kind, size, spatial metadata, coordinate system."""
    from comreg_core.io import describe_file

    typer.echo(describe_file(path))


@contextlib.contextmanager
def _progress_bar(total: int, label: str):
    """A progress bar on stderr; yields ``advance(done)`` taking the number of items done."""
    with typer.progressbar(length=total, label=label, file=sys.stderr) as bar:
        state = {"done": 0}

        def advance(done: int) -> None:
            bar.update(done - state["done"])
            state["done"] = done

        yield advance


def main() -> None:
    """Entry point of the ``comreg`` console script."""
    app()


if __name__ == "__main__":
    main()
