"""NRRD files (``.nrrd``, ``.nhdr``, also 3D Slicer's ``.seg.nrrd``) on a 3D patient grid: read
with full geometry, written atomically. Geometry conventions: see :mod:`comreg_core.io.volumes`.
"""

from __future__ import annotations

import re
from pathlib import Path

import nrrd
import numpy as np

from comreg_core.errors import ComRegError, CorruptFileError, MissingSpatialMetadataError
from comreg_core.io._files import atomic_output
from comreg_core.io.image_files import (grid_axes, grid_matrix, parse_errors_as_corrupt,
                                        refuse_tracked_sequence, storable_array)
from comreg_core.transforms import check_space

_NRRD_SPACE_NAMES = {"LPS": "left-posterior-superior", "RAS": "right-anterior-superior"}
#: A 3D Slicer segment header field, ``Segment<index>_<Property>`` (groups: index, property).
SLICER_SEGMENT_FIELD = re.compile(r"^Segment(\d+)_(\w+)$")


def has_slicer_segment_fields(header) -> bool:
    """True when a NRRD header (its keys) describes 3D Slicer segments."""
    return any(SLICER_SEGMENT_FIELD.match(key) for key in header)


def read_nrrd_grid(path: Path) -> tuple[np.ndarray, dict, np.ndarray, str, str]:
    """Read a NRRD file with full 3D geometry.

    Returns ``(array, header, ijk_to_space, space, list_kind)``: ``array`` is ``(I, J, K)``, or
    ``(L, I, J, K)`` when the file has one non-spatial axis (moved first, of kind ``list_kind``).
    NRRD's 'space origin' is the centre of the first sample whatever the axis centering
    ('cell' or 'node'), which is already our convention, so centering needs no shift.
    """
    with parse_errors_as_corrupt(path):
        array, header = nrrd.read(str(path), index_order="F")
    refuse_tracked_sequence(path, header)
    required = ("space", "space directions", "space origin")
    missing = [name for name in required if name not in header]
    if missing == ["space"] and "space dimension" in header:
        raise ComRegError(
            f"'{path}' gives its geometry in an unnamed space ('space dimension' without "
            "'space'), so ComReg cannot tell whether it is LPS or RAS.",
            "Save it from 3D Slicer or ITK, which write 'space: left-posterior-superior'.")
    if missing:
        raise MissingSpatialMetadataError(path, "no " + ", ".join(f"'{m}'" for m in missing))
    try:
        space = check_space(header["space"])
    except ComRegError:
        raise ComRegError(
            f"'{path}' is in the NRRD space '{header['space']}'; ComReg reads only patient "
            "spaces LPS (left-posterior-superior) and RAS (right-anterior-superior).",
            "Resample or save the volume in patient coordinates (e.g. from 3D Slicer).") from None
    with parse_errors_as_corrupt(path):
        directions = np.asarray(header["space directions"], dtype=np.float64)
        origin = np.asarray(header["space origin"], dtype=np.float64)
    if directions.ndim != 2 or directions.shape != (array.ndim, 3):
        raise CorruptFileError(path, f"'space directions' has shape {directions.shape} for a "
                                     f"{array.ndim}D array in 3D space")
    kinds = header.get("kinds") or ["domain"] * array.ndim
    spatial = [ax for ax in range(array.ndim) if not np.isnan(directions[ax]).any()]
    other = [ax for ax in range(array.ndim) if ax not in spatial]
    if len(spatial) != 3 or len(other) > 1:
        raise ComRegError(
            f"'{path}' has {len(spatial)} spatial and {len(other)} non-spatial axes "
            f"(kinds {' '.join(kinds)}); ComReg needs a 3D volume, optionally with one "
            "list of layers.", "Export a plain 3D volume or a 3D Slicer segmentation.")
    ijk_to_space = grid_matrix(path, directions[spatial], origin)
    list_kind = ""
    if other:
        list_kind = kinds[other[0]] if other[0] < len(kinds) else "none"
        array = np.moveaxis(array, other[0], 0)
    return array, header, ijk_to_space, space, list_kind


def write_nrrd_grid(path: Path, array: np.ndarray, ijk_to_space: np.ndarray, space: str, *,
                compress: bool, extra: dict | None = None) -> None:
    """Write ``array`` ``(I, J, K)`` or ``(L, I, J, K)`` (a leading list axis) atomically."""
    array = storable_array(array, "NRRD")
    axes, origin = grid_axes(ijk_to_space)
    n_list = array.ndim - 3
    header = {
        "dimension": array.ndim,
        "space": _NRRD_SPACE_NAMES[check_space(space)],
        "space directions": np.vstack([np.full((n_list, 3), np.nan), axes]),
        "kinds": ["list"] * n_list + ["domain"] * 3,
        "endian": "little",
        "encoding": "gzip" if compress else "raw",
        "space origin": origin,
        **(extra or {}),
    }
    with atomic_output(path) as tmp:
        nrrd.write(str(tmp), array, header, index_order="F", compression_level=6)


def read_nrrd_header(path: Path) -> dict:
    """The header of a NRRD file (pynrrd's dict); :class:`CorruptFileError` if unreadable."""
    try:
        return nrrd.read_header(str(path))
    except (nrrd.NRRDError, OSError, ValueError, StopIteration, KeyError, IndexError) as exc:
        raise CorruptFileError(path, f"bad NRRD header ({type(exc).__name__}: {exc})") from None
