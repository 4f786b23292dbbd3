"""Volumes: NRRD (``.nrrd``, ``.nhdr``) and MetaImage (``.mha``, ``.mhd``) 3D scalar images.
Label maps with named segments (3D Slicer ``.seg.nrrd``) are :mod:`comreg_core.io.segmentations`.

Geometry is kept as one ``(4, 4)`` matrix ``ijk_to_space`` mapping voxel indices ``(i, j, k)`` (the
array's axes in order, i.e. NRRD/ITK axis order with i fastest on disk) to patient millimetres in
``space`` ("LPS" or "RAS"): ``[x, y, z, 1] = ijk_to_space @ [i, j, k, 1]``. Voxel centres sit at
integer indices (NRRD "cell" centering is converted on read).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from comreg_core.io._files import require_extension, require_input_file
from comreg_core.io.image_files import single_volume_array
from comreg_core.io.metaimage_files import read_metaimage_grid, write_metaimage_grid
from comreg_core.io.nrrd_files import has_slicer_segment_fields, read_nrrd_grid, write_nrrd_grid
from comreg_core.transforms import check_space, space_change


@dataclass
class Volume:
    """A scalar image on a regular grid placed in patient millimetres.

    Attributes:
        array: ``(I, J, K)`` voxel values, indexed ``array[i, j, k]``.
        ijk_to_space: ``(4, 4)`` voxel index -> ``space`` mm.
        space: "LPS" or "RAS".
        path: the file it was read from, if any.
    """

    array: np.ndarray
    ijk_to_space: np.ndarray
    space: str = "LPS"
    path: Path | None = None

    def __post_init__(self) -> None:
        self.space = check_space(self.space)
        self.ijk_to_space = np.asarray(self.ijk_to_space, dtype=np.float64)

    @classmethod
    def from_geometry(
        cls,
        array: np.ndarray,
        spacing=(1.0, 1.0, 1.0),
        origin=(0.0, 0.0, 0.0),
        directions=np.eye(3),
        space: str = "LPS",
    ) -> "Volume":
        """Build from spacing ``(3,)`` mm, origin ``(3,)`` mm (centre of voxel 0,0,0) and a
        ``(3, 3)`` direction matrix whose columns are the unit i, j, k axes."""
        M = np.eye(4)
        M[:3, :3] = np.asarray(directions, dtype=np.float64) * np.asarray(spacing, dtype=np.float64)
        M[:3, 3] = origin
        return cls(np.asarray(array), M, space)

    @property
    def spacing(self) -> np.ndarray:
        """``(3,)`` voxel size in mm along i, j, k."""
        return np.linalg.norm(self.ijk_to_space[:3, :3], axis=0)

    @property
    def origin(self) -> np.ndarray:
        """``(3,)`` position in mm of the centre of voxel (0, 0, 0)."""
        return self.ijk_to_space[:3, 3].copy()

    @property
    def directions(self) -> np.ndarray:
        """``(3, 3)`` unit column vectors of the i, j, k axes in ``space``."""
        return self.ijk_to_space[:3, :3] / self.spacing

    def in_space(self, space: str) -> "Volume":
        """The same volume with its geometry expressed in ``space`` (voxels unchanged)."""
        space = check_space(space)
        return replace(self, ijk_to_space=space_change(self.space, space) @ self.ijk_to_space,
                       space=space)


#: Extensions :func:`read_volume` accepts; :func:`write_volume` writes all but ``.nhdr``.
VOLUME_READ_EXTENSIONS = [".nrrd", ".nhdr", ".mha", ".mhd"]
VOLUME_WRITE_EXTENSIONS = [".nrrd", ".mha", ".mhd"]


def read_volume(path: str | Path) -> Volume:
    """Read a 3D scalar volume from ``.nrrd``/``.nhdr`` (LPS or RAS, kept as stored) or
    ``.mha``/``.mhd`` (always LPS). Voxels keep their file type; ``array`` is ``(I, J, K)``."""
    ext = require_extension(path, "volume", VOLUME_READ_EXTENSIONS)
    path = require_input_file(path, "volume file")
    if ext in (".nrrd", ".nhdr"):
        array, header, ijk_to_space, space, list_kind = read_nrrd_grid(path)
        is_seg = has_slicer_segment_fields(header)
        return Volume(single_volume_array(path, array, list_kind, is_seg), ijk_to_space, space,
                      path)
    array, _, ijk_to_space = read_metaimage_grid(path)
    return Volume(single_volume_array(path, array, "channels", False), ijk_to_space, "LPS", path)


def write_volume(volume: Volume, path: str | Path, *, compress: bool = True) -> Path:
    """Write ``volume`` to ``.nrrd`` (gzip or raw encoding, in the volume's space) or
    ``.mha``/``.mhd`` (zlib-compressed or raw, converted to LPS). Atomic; returns the path."""
    ext = require_extension(path, "volume", VOLUME_WRITE_EXTENSIONS)
    path = Path(path)
    if np.ndim(volume.array) != 3:
        raise ValueError(f"A volume array must be (I, J, K), got shape {np.shape(volume.array)}.")
    if ext == ".nrrd":
        write_nrrd_grid(path, volume.array, volume.ijk_to_space, volume.space, compress=compress)
    else:
        lps = volume.in_space("LPS")
        write_metaimage_grid(path, ext, lps.array, lps.ijk_to_space, compress=compress)
    return path
