"""``comreg extract-ct``, ``comreg extract-us`` and ``comreg info``: the bone surfaces ComReg
registers (from a CT segmentation, from a tracked US sweep) and what it reads from a file."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from comreg_core.cli.comreg import app
from comreg_core.cli.options import INPUTS, OUTPUT, progress_bar
from comreg_core.errors import ComRegError

#: The panel of these commands in 'comreg --help'.
PANEL = "Bone surfaces"
#: The panel of extract-ct's meshing options.
MESHING = "Meshing"
#: The panel of extract-us's --compound options.
COMPOUNDING = "Compounding"


class SurfaceMethod(str, Enum):
    flying_edges = "flying_edges"
    surface_nets = "surface_nets"


class CompoundMode(str, Enum):
    mean = "mean"
    max = "max"


# --- comreg extract-ct ---------------------------------------------------------------------------
CT_SEGMENTATION = typer.Argument(
    ..., help="CT bone segmentation: label map (.nrrd, .nhdr, .mha, .mhd), 3D Slicer "
    ".seg.nrrd, or a bone mesh (.stl, .ply, .obj, .vtk, .vtp) to validate and pass through.")
CT_OUT = typer.Option(..., "--out", "-o", rich_help_panel=OUTPUT,
                      help="Output mesh (.stl, .ply, .obj, .vtk, .vtp).")
CT_LABEL = typer.Option(None, "--label", rich_help_panel=INPUTS, help="Label value of the bone.")
CT_SEGMENT = typer.Option(None, "--segment", rich_help_panel=INPUTS,
                          help="Segment name (or ID) of the bone.")
CT_METHOD = typer.Option(None, rich_help_panel=MESHING, help="Meshing algorithm (default "
                         "flying_edges: discrete marching cubes).")
CT_SMOOTHING = typer.Option(None, min=0.0, max=1.0, rich_help_panel=MESHING, help="Smoothing "
                            "strength 0..1 (default keeps the surface within 0.2 mm of the "
                            "unsmoothed one).")
CT_DECIMATION = typer.Option(None, min=0.0, max=0.99, rich_help_panel=MESHING,
                             help="Fraction of triangles to remove (0 = none).")
CT_LARGEST_COMPONENT = typer.Option(False, "--largest-component/--all-components",
                                    rich_help_panel=MESHING,
                                    help="Keep only the largest connected piece.")


@app.command("extract-ct", rich_help_panel=PANEL)
def extract_ct(
    segmentation: Path = CT_SEGMENTATION,
    label: Optional[int] = CT_LABEL,
    segment: Optional[str] = CT_SEGMENT,
    method: Optional[SurfaceMethod] = CT_METHOD,
    smoothing: Optional[float] = CT_SMOOTHING,
    decimation: Optional[float] = CT_DECIMATION,
    largest_component: bool = CT_LARGEST_COMPONENT,
    out: Path = CT_OUT,
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


# --- comreg extract-us ---------------------------------------------------------------------------
US_SWEEP = typer.Argument(
    ..., help="Tracked US sweep: PLUS sequence (.igs.mha, .seq.mha, .igs.nrrd, .seq.nrrd), a "
    "frame folder (PNG frames + tracking.csv + calibration.json), a 3D Slicer volume "
    "sequence (.seq.nrrd), or a reconstructed 3D US volume (.nrrd, .mha).")
US_OUT = typer.Option(..., "--out", "-o", rich_help_panel=OUTPUT, help="Output point cloud "
                      "(.ply, .pcd, .xyz, .npy, ...), bone surface points in the tracking "
                      "reference frame.")
US_CALIBRATION = typer.Option(
    None, "--probe-calibration", "--calibration", rich_help_panel=INPUTS,
    help="Image-to-probe calibration: a PLUS device-set XML (ImageToProbe) or calibration.json "
    "for a frame folder. --calibration: its former name.")
US_MASKS = typer.Option(
    None, "--masks", rich_help_panel=INPUTS, help="Bone label masks instead of detecting the "
    "bone in the B-mode frames: a folder of mask images named like the frames, a mask sequence "
    "or a label volume.")
US_CONFIG = typer.Option(None, "--config", rich_help_panel=INPUTS, help="US extraction config "
                         "YAML (detector and denoising parameters).")
US_BEAM_DIRECTION = typer.Option("auto", "--beam-direction", rich_help_panel=INPUTS,
                                 help="A reconstructed volume's beam: auto, or a voxel axis x, "
                                 "-x, y, -y, z, -z.")
US_COMPOUND = typer.Option(None, "--compound", rich_help_panel=COMPOUNDING, help="Also "
                           "compound the frames into this 3D volume (.nrrd, .mha) to look at.")
US_COMPOUND_SPACING = typer.Option(0.5, min=0.01, rich_help_panel=COMPOUNDING,
                                   help="Voxel size of --compound (mm).")
US_COMPOUND_MODE = typer.Option(CompoundMode.mean, rich_help_panel=COMPOUNDING,
                                help="Voxel value of --compound where frames overlap.")


@app.command("extract-us", rich_help_panel=PANEL)
def extract_us(
    sweep: Path = US_SWEEP,
    calibration: Optional[Path] = US_CALIBRATION,
    masks: Optional[Path] = US_MASKS,
    config: Optional[Path] = US_CONFIG,
    beam_direction: str = US_BEAM_DIRECTION,
    out: Path = US_OUT,
    compound: Optional[Path] = US_COMPOUND,
    compound_spacing: float = US_COMPOUND_SPACING,
    compound_mode: CompoundMode = US_COMPOUND_MODE,
) -> None:
    """Extract the bone surface seen by a tracked US sweep as a point cloud.

    Reads the frames and their image-to-reference poses, finds the bone in every frame (from
    --masks, or with the shadow-aware B-mode detector: a bright thin ridge with an acoustic shadow
    below it), maps the bone pixels to millimetres in the tracking reference frame and removes
    outliers (largest clusters, statistical outlier removal).
    """
    from comreg_core.surfaces.us import check_us_outputs
    from comreg_core.surfaces.us_volume import (check_beam_direction, extract_volume_to_file,
                                                is_volume_file)

    check_us_outputs(out, compound, inputs=[sweep, calibration, masks, config])
    check_beam_direction(beam_direction)
    volume = is_volume_file(sweep)
    if beam_direction != "auto" and not volume:
        raise ComRegError(f"--beam-direction is for a reconstructed volume; '{sweep}' is a "
                          "sweep of frames (each frame's pose gives its beam).",
                          "Drop --beam-direction.")
    if volume:
        typer.echo("wrote " + extract_volume_to_file(
            sweep, out, beam_direction=beam_direction, config=config,
            frame_options={"--probe-calibration": calibration, "--masks": masks,
                           "--compound": compound}).summary())
        return
    tracked = _extract_frames(sweep, calibration, masks, config, out)
    if compound is not None:
        _compound(tracked, compound, compound_spacing, compound_mode)


def _extract_frames(sweep: Path, calibration, masks, config, out: Path):
    """extract-us of a sweep of frames: the bone points of every frame into ``out``; returns the
    tracked sweep read."""
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import extract_us_to_file
    from comreg_core.surfaces.us_config import load_us_extraction_config

    settings = load_us_extraction_config(config)
    tracked = read_tracked_sweep(sweep, calibration=calibration, reference=settings.reference)
    with progress_bar(len(tracked.frames), "detecting bone") as advance:
        result = extract_us_to_file(tracked, out, masks=masks, config=settings,
                                    progress=lambda done, total, note="": advance(done))
    typer.echo(f"wrote {result.summary()}")
    return tracked


def _compound(tracked, compound: Path, spacing: float, mode: CompoundMode) -> None:
    """extract-us --compound: the frames compounded into a volume to look at."""
    from comreg_core.io import write_volume
    from comreg_core.surfaces.us_compounding import compound_sweep

    volume = compound_sweep(tracked, spacing, mode.value)
    write_volume(volume, compound)
    typer.echo(f"wrote {compound}: compounded volume {' x '.join(map(str, volume.array.shape))}"
               f" voxels of {spacing} mm")


# --- comreg info ---------------------------------------------------------------------------------
INFO_PATH = typer.Argument(..., help="Any file ComReg reads.")


@app.command("info", rich_help_panel=PANEL)
def info(path: Path = INFO_PATH) -> None:
    """Show what ComReg reads from a file: kind, size, spatial metadata, coordinate system."""
    from comreg_core.io import describe_file

    typer.echo(describe_file(path))
