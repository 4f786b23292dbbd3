"""Tracked freehand ultrasound sweeps: 2D B-mode frames with one image-to-reference pose each.

:func:`read_tracked_sweep` reads any of these formats into one
:class:`~comreg_core.io.sweeps.TrackedSweep` (conventions there):

- PLUS sequence metafiles ``.igs.mha`` / ``.seq.mha`` (zlib-compressed or raw) and their NRRD form
  ``.igs.nrrd`` / ``.seq.nrrd`` (custom fields ``key:=value``), with per-frame ``*ToTracker`` /
  ``*ToReference`` transforms, their status, ``UltrasoundImageOrientation`` and timestamps; the
  image-to-probe calibration comes from the sequence itself or from a PLUS device-set XML
  (``<Transform From="Image" To="Probe" Matrix=...>``):
  :func:`~comreg_core.io.plus_sequences.read_plus_sequence` (file parts:
  :mod:`comreg_core.io.plus_files`).
- A frame folder as in UltraBones100k: ``frames/<timestamp>.png``, ``tracking.csv`` (positions
  and Euler angles of the probe), ``calibration.json``:
  :func:`~comreg_core.io.frame_folders.read_frame_folder`.
- A 3D Slicer volume sequence ``.seq.nrrd`` (a 4D NRRD, list axis first or last, frames sharing
  one geometry): :func:`~comreg_core.io.slicer_sequences.read_slicer_volume_sequence`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from comreg_core.errors import InputFileNotFoundError
from comreg_core.io._files import require_extension
from comreg_core.io.frame_folders import read_frame_folder
from comreg_core.io.nrrd_files import read_nrrd_header
from comreg_core.io.plus_files import has_plus_frame_fields
from comreg_core.io.plus_sequences import read_plus_sequence
from comreg_core.io.slicer_sequences import read_slicer_volume_sequence
from comreg_core.io.sweeps import SWEEP_EXTENSIONS, TrackedSweep

log = logging.getLogger(__name__)


def read_tracked_sweep(path: str | Path, *, calibration: str | Path | None = None,
                       reference: str = "Reference") -> TrackedSweep:
    """Read a tracked sweep from a PLUS sequence file, a 3D Slicer volume sequence, or a frame
    folder (a directory). ``calibration`` is a PLUS device-set XML (sequence files) or a
    ``calibration.json`` (frame folders); ``reference`` names the output coordinate frame of a
    PLUS file.

    Raises:
        InputFileNotFoundError, UnsupportedFormatError, CorruptFileError,
        CalibrationMismatchError, NoValidFramesError, ComRegError (no transform chain).
    """
    path = Path(path)
    if path.is_dir():
        return read_frame_folder(path, calibration=calibration)
    if not path.exists():
        raise InputFileNotFoundError(path, "ultrasound sweep (file or frame folder)")
    ext = require_extension(path, "tracked ultrasound sweep", SWEEP_EXTENSIONS)
    if ext in (".igs.nrrd", ".seq.nrrd", ".nrrd", ".nhdr"):
        if not has_plus_frame_fields(read_nrrd_header(path)):
            if calibration is not None:
                log.warning("%s is a 3D Slicer volume sequence: its geometry is in the file, so "
                            "the calibration '%s' is not used", path, calibration)
            return read_slicer_volume_sequence(path)
    return read_plus_sequence(path, calibration=calibration, reference=reference)
