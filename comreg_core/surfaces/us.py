"""Ultrasound bone surfaces: a tracked sweep -> bone surface points in the reference frame (mm).

Two sources:

- **Label masks** (:mod:`comreg_core.surfaces.us_masks`): bone pixels of mask frames, or of a
  label volume resampled onto the frames.
- **Raw B-mode** (:mod:`comreg_core.surfaces.us_detector`): a classical, shadow-aware detector, no
  trained network.

The points are then cleaned up (:mod:`comreg_core.surfaces.us_denoise`); settings in
:mod:`comreg_core.surfaces.us_config`. :func:`extract_us_surface` runs it all;
:func:`extract_us_to_file` is the library side of ``comreg extract-us``, whose ``--compound``
volume is :mod:`comreg_core.surfaces.us_compounding`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from comreg_core.progress import Progress
from comreg_core.errors import OutputPlaceError
from comreg_core.io._files import check_output_file, require_extension
from comreg_core.io.pointclouds import POINT_CLOUD_EXTENSIONS, PointCloud, write_points
from comreg_core.io.sweeps import TrackedSweep
from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.io.volumes import VOLUME_WRITE_EXTENSIONS
from comreg_core.surfaces.us_config import USExtractionConfig, load_us_extraction_config
from comreg_core.surfaces.us_denoise import denoise_points
from comreg_core.surfaces.us_detector import detect_sweep_surface
from comreg_core.surfaces.us_masks import read_masks, surface_from_masks
from comreg_core.surfaces.us_points import USSurfacePoints, beam_origins

log = logging.getLogger(__name__)


@dataclass
class USExtractionResult:
    """What :func:`extract_us_surface` found.

    Attributes:
        points: the final (denoised) :class:`USSurfacePoints`.
        raw: the points before denoising.
        source: "masks" or "detector".
        frames_total, frames_valid: frames in the sweep, and with a valid pose.
        output: the file written by :func:`extract_us_to_file`, if any.
    """

    points: USSurfacePoints
    raw: USSurfacePoints
    source: str
    frames_total: int
    frames_valid: int
    output: Path | None = None

    def summary(self) -> str:
        """One line for the command line."""
        where = f" -> {self.output}" if self.output else ""
        return (f"{len(self.points.points)} bone points ({len(self.raw.points)} before denoising)"
                f" from {self.points.frames_with_bone} of {self.raw.frames_examined} frames "
                f"({self.source}; {self.frames_valid} of {self.frames_total} frames tracked)"
                f"{where}")


def extract_us_surface(sweep: TrackedSweep, config: USExtractionConfig | None = None, *,
                       masks: np.ndarray | None = None, progress: Progress | None = None
                       ) -> USExtractionResult:
    """Bone surface points of ``sweep``: from ``masks`` ``(N, H, W)`` when given, else from the
    B-mode detector; then denoised."""
    config = config or USExtractionConfig()
    if masks is not None:
        raw = surface_from_masks(sweep, masks, top_edge=config.mask_top_edge,
                                 frame_step=config.frame_step)
        source = "masks"
    else:
        raw = detect_sweep_surface(sweep, config.detector, frame_step=config.frame_step,
                                   progress=progress)
        source = "detector"
    return USExtractionResult(denoise_points(raw, config.denoise), raw, source, sweep.n_frames,
                              int(sweep.valid.sum()))


def extract_us_to_file(sweep: str | Path | TrackedSweep, out: str | Path, *,
                       calibration: str | Path | None = None, masks: str | Path | None = None,
                       config: str | Path | USExtractionConfig | None = None,
                       progress: Progress | None = None) -> USExtractionResult:
    """``comreg extract-us SWEEP --out POINTS [--probe-calibration FILE] [--masks DIR] [--config FILE]``:
    read the sweep, extract and denoise its bone surface, write the points (``.ply``, ``.pcd``,
    ``.xyz``, ``.npy``, ... in the sweep's reference frame, tagged LPS) atomically; a ``.ply``
    also keeps each point's beam origin (:func:`~comreg_core.surfaces.us_points.beam_origins`),
    which ``comreg register`` uses to rule out poses the probe could not have seen."""
    check_us_outputs(out, inputs=[sweep, calibration, masks, config])  # fail before the work
    if not isinstance(config, USExtractionConfig):
        config = load_us_extraction_config(config)
    if not isinstance(sweep, TrackedSweep):
        sweep = read_tracked_sweep(sweep, calibration=calibration, reference=config.reference)
    mask_frames = read_masks(masks, sweep) if masks is not None else None
    result = extract_us_surface(sweep, config, masks=mask_frames, progress=progress)
    result.output = write_surface_points(result.points, sweep, out, "LPS")
    log.info("%s", result.summary())
    return result


def write_surface_points(found: USSurfacePoints, sweep: TrackedSweep, out: str | Path,
                         space: str) -> Path:
    """Write ``found`` (points of ``sweep``'s frames, in ``space``) to ``out`` with each point's
    beam origin (:func:`~comreg_core.surfaces.us_points.beam_origins`; a ``.ply`` keeps them)."""
    origins = None
    if (found.frame_index >= 0).all():
        origins = beam_origins(found.points, sweep.T_ref_image[found.frame_index])
    return write_points(PointCloud(found.points, space, beam_origins=origins), out)


def check_us_outputs(out: str | Path, compound: str | Path | None = None, *, inputs=()) -> None:
    """Check the outputs of ``comreg extract-us`` before any work: the point cloud ``out`` and
    the optional compounded volume ``compound`` (extensions, places, not an input, distinct)."""
    inputs = [i for i in inputs if isinstance(i, (str, Path))]
    require_extension(out, "point cloud", POINT_CLOUD_EXTENSIONS)
    check_output_file(out, inputs=inputs, what="output point cloud")
    if compound is not None:
        require_extension(compound, "compounded volume", VOLUME_WRITE_EXTENSIONS)
        check_output_file(compound, inputs=inputs, what="compounded volume")
        if Path(compound).absolute() == Path(out).absolute():
            raise OutputPlaceError(f"--out and --compound are the same file '{out}'.",
                                   "Give them different names.")
