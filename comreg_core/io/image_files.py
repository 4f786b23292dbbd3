"""What the NRRD and MetaImage readers and writers share: the grid geometry matrix, the voxel
types ComReg writes, the translation of low-level parse failures into :class:`CorruptFileError`,
and the checks that a file holds one 3D scalar volume.

Geometry conventions: see :mod:`comreg_core.io.volumes`.
"""

from __future__ import annotations

import contextlib
import re
import zlib
from collections.abc import Iterator
from pathlib import Path

import nrrd
import numpy as np

from comreg_core.errors import ComRegError, CorruptFileError, InputFileNotFoundError

#: numpy dtype codes (``dtype.str[1:]``) of the voxel types ComReg writes to NRRD and MetaImage;
#: bool is stored as uint8.
STORABLE_DTYPE_CODES = ("i1", "u1", "i2", "u2", "i4", "u4", "i8", "u8", "f4", "f8")


def grid_matrix(path: Path, axes: np.ndarray, origin) -> np.ndarray:
    """``(4, 4)`` ijk -> space from ``axes`` ``(3, 3)`` (row n = mm step of one voxel along axis
    n, the layout of both NRRD 'space directions' and MetaImage 'TransformMatrix' x spacing) and
    ``origin`` ``(3,)`` mm (centre of voxel 0, 0, 0)."""
    axes = np.asarray(axes, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    if axes.shape != (3, 3) or origin.shape != (3,):
        raise CorruptFileError(path, f"the grid geometry has axes of shape {axes.shape} and an "
                                     f"origin of shape {origin.shape}, expected (3, 3) and (3,)")
    if not (np.isfinite(axes).all() and np.isfinite(origin).all()):
        raise CorruptFileError(path, "the voxel spacing, directions or origin are not finite")
    if abs(np.linalg.det(axes)) < 1e-12 * max(1.0, np.abs(axes).max() ** 3):
        raise CorruptFileError(path, "the voxel axes are degenerate (zero spacing or parallel "
                                     f"directions): {axes.tolist()}")
    M = np.eye(4)
    M[:3, :3] = axes.T
    M[:3, 3] = origin
    return M


def grid_axes(ijk_to_space: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`grid_matrix`: ``(axes (3, 3), origin (3,))`` of a ``(4, 4)`` matrix."""
    return ijk_to_space[:3, :3].T.copy(), ijk_to_space[:3, 3].copy()


def storable_array(array: np.ndarray, fmt: str) -> np.ndarray:
    """``array`` as little-endian with a type every reader knows (bool -> uint8)."""
    array = np.asarray(array)
    if array.dtype == np.bool_:
        array = array.astype(np.uint8)
    code = array.dtype.str[1:]
    if code not in STORABLE_DTYPE_CODES:
        raise TypeError(f"Cannot write voxels of type {array.dtype} to {fmt}; "
                        f"use one of {sorted(STORABLE_DTYPE_CODES)}.")
    return array.astype(array.dtype.newbyteorder("<"), copy=False)


@contextlib.contextmanager
def parse_errors_as_corrupt(path: Path) -> Iterator[None]:
    """Turn low-level parse failures (pynrrd, zlib, numpy, bad numbers) into
    :class:`CorruptFileError` naming ``path`` and the original detail."""
    try:
        yield
    except ComRegError:
        raise
    except FileNotFoundError as exc:
        raise InputFileNotFoundError(exc.filename or path, "data file named by the header") from exc
    except StopIteration as exc:  # pynrrd on an empty or header-only file
        raise CorruptFileError(path, "the file ends inside its header") from exc
    except (nrrd.NRRDError, zlib.error, OSError, EOFError, ValueError, KeyError, IndexError,
            TypeError) as exc:
        sizes = _PYNRRD_SIZE_MISMATCH.search(str(exc))
        if sizes:  # a truncated (or padded) data part
            raise CorruptFileError(path, f"the header's 'sizes' need {sizes[1]} voxel values but "
                                         f"the file holds {sizes[2]}") from exc
        raise CorruptFileError(path, f"{type(exc).__name__}: {str(exc).rstrip('.')}") from exc


#: pynrrd's message when the data part holds fewer (or more) values than the header's sizes.
_PYNRRD_SIZE_MISMATCH = re.compile(r"does not equal the product of all the dimensions: "
                                   r"(\d+)-(\d+)=")


def refuse_tracked_sequence(path: Path, keys) -> None:
    """Raise if header ``keys`` are those of a PLUS tracked-ultrasound sequence (a stack of 2D
    frames with per-frame poses, whose third axis is time, not space)."""
    if any(str(key).startswith("Seq_Frame") for key in keys):
        raise ComRegError(f"'{path}' is a tracked ultrasound sequence (2D frames over time), "
                          "not a 3D volume.",
                          "Reconstruct a volume from it first, or read it as an ultrasound "
                          "sequence.")


def single_volume_array(path: Path, array: np.ndarray, list_kind: str, is_segmentation: bool):
    """A ``(I, J, K)`` array from a 3D array or a 4D one with a single non-spatial component."""
    if array.ndim == 3:
        return array
    if array.shape[0] == 1:
        return array[0]
    if is_segmentation:
        hint = ("It is a 3D Slicer segmentation with several layers; read it as a segmentation "
                "(read_segmentation), not as a volume.")
    else:
        hint = "Export one 3D scalar volume (a single component, frame or channel) instead."
    raise ComRegError(f"'{path}' holds {array.shape[0]} values per voxel (a non-spatial "
                      f"'{list_kind}' axis), not a single 3D scalar volume.", hint)


def format_numbers(values) -> str:
    """Space-separated shortest round-trip text of floats (``repr``)."""
    return " ".join(repr(float(v)) for v in np.ravel(values))
