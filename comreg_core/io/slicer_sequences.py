"""3D Slicer volume sequences (``.seq.nrrd``) -> :class:`TrackedSweep`: a 4D NRRD of 2D frames
sharing one geometry (no per-frame pose). Frame conventions: see :mod:`comreg_core.io.sweeps`.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import nrrd
import numpy as np

from comreg_core.errors import ComRegError, CorruptFileError
from comreg_core.io._files import require_input_file
from comreg_core.io.image_files import parse_errors_as_corrupt
from comreg_core.io.sweeps import TrackedSweep, frames_to_grey, parse_float
from comreg_core.transforms import check_space, space_change

log = logging.getLogger(__name__)


def read_slicer_volume_sequence(path: str | Path) -> TrackedSweep:
    """Read a 3D Slicer volume sequence ``.seq.nrrd``: a 4D NRRD of 2D frames (one spatial axis
    of size 1) with a list axis first or last. All frames share the file's geometry (a volume
    sequence has no per-frame pose), converted to LPS; ``axis N index values`` give timestamps.
    """
    path = require_input_file(path, "volume sequence")
    with parse_errors_as_corrupt(path):
        array, header = nrrd.read(str(path), index_order="F")
    if array.ndim != 4:
        raise CorruptFileError(path, f"a volume sequence has 4 axes (3 spatial + frames); this "
                                     f"one has {array.ndim}")
    directions = np.asarray(header.get("space directions"), dtype=np.float64)
    if directions.shape != (4, 3) or "space origin" not in header or "space" not in header:
        raise CorruptFileError(path, "a volume sequence needs 'space', 'space origin' and "
                                     "'space directions' for its 3 spatial axes")
    spatial = [i for i in range(4) if np.isfinite(directions[i]).all()]
    if len(spatial) != 3:
        raise CorruptFileError(path, f"expected 3 spatial axes and one list axis, found "
                                     f"{len(spatial)} spatial ones")
    frame_axis = next(i for i in range(4) if i not in spatial)
    flat = [i for i in spatial if array.shape[i] == 1]
    if not flat:
        raise ComRegError(f"'{path}' is a sequence of 3D volumes "
                          f"({' x '.join(str(array.shape[i]) for i in spatial)}), not of 2D "
                          "ultrasound frames.", "Export the 2D image sequence instead.")
    normal_axis = flat[-1]
    x_axis, y_axis = [i for i in spatial if i != normal_axis]
    frames = np.moveaxis(array, (frame_axis, y_axis, x_axis, normal_axis), (0, 1, 2, 3))[..., 0]
    space = check_space(str(header["space"]))
    to_lps = space_change(space, "LPS")
    T_pixel = np.eye(4)
    T_pixel[:3, 0] = directions[x_axis]
    T_pixel[:3, 1] = directions[y_axis]
    normal = directions[normal_axis]
    T_pixel[:3, 2] = normal / max(np.linalg.norm(normal), 1e-12)
    T_pixel[:3, 3] = np.asarray(header["space origin"], dtype=np.float64)
    T_pixel = to_lps @ T_pixel
    spacing = np.linalg.norm(T_pixel[:3, :2], axis=0)
    T_image = T_pixel @ np.diag([1 / spacing[0], 1 / spacing[1], 1.0, 1.0])
    n = frames.shape[0]
    stamps = np.full(n, np.nan)
    for key, value in header.items():
        if re.fullmatch(rf"axis {frame_axis} index values", str(key)):
            values = [parse_float(v) for v in str(value).split()]
            if len(values) == n:
                stamps = np.array(values)
    log.warning("%s is a 3D Slicer volume sequence: all %d frames share one geometry (it holds "
                "no per-frame tracking); for a freehand sweep use the PLUS recording", path, n)
    return TrackedSweep(np.ascontiguousarray(frames_to_grey(frames)), spacing,
                        np.repeat(T_image[None], n, axis=0), stamps, np.ones(n, dtype=bool),
                        space, [f"Frame{i:04d}" for i in range(n)], path)
