"""File helpers shared by every reader and writer: extension lookup, input checks, output-place
checks (made before any work), atomic writes."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from comreg_core import runs
import numpy as np

from comreg_core.errors import (InputFileNotFoundError, InvalidGeometryError, OutputPlaceError,
                              UnsupportedFormatError)

# Multi-part extensions first so ".seg.nrrd" wins over ".nrrd".
_COMPOUND_SUFFIXES = (".seg.nrrd", ".igs.nrrd", ".seq.nrrd", ".igs.mha", ".seq.mha", ".nii.gz",
                      ".mrk.json")


def file_extension(path: str | Path) -> str:
    """Lower-case extension of ``path``, keeping known compound ones (``.seg.nrrd``)."""
    name = Path(path).name.lower()
    for suffix in _COMPOUND_SUFFIXES:
        if name.endswith(suffix):
            return suffix
    return Path(name).suffix


def require_extension(path: str | Path, kind: str, supported: list[str]) -> str:
    """Return the extension of ``path`` if it is in ``supported`` (also matching the plain last
    suffix of a compound one), else raise :class:`UnsupportedFormatError`."""
    ext = file_extension(path)
    if ext in supported:
        return ext
    plain = Path(str(path).lower()).suffix
    if plain in supported:
        return plain
    raise UnsupportedFormatError(path, kind, supported)


def require_input_file(path: str | Path, what: str = "input file") -> Path:
    """``path`` as a Path if it is an existing regular file, else :class:`InputFileNotFoundError`."""
    path = Path(path)
    if not path.is_file():
        raise InputFileNotFoundError(path, what)
    return path


#: The farthest (mm) a coordinate or a translation given to ComReg may lie from the origin:
#: 1 km, beyond any scanner or tracked room. Larger finite numbers are a wrong unit or a broken
#: file, and would overflow the squared distances of the registration.
MAX_COORDINATE_MM = 1e6


def require_near_origin(values, what: str) -> None:
    """Raise :class:`InvalidGeometryError` when any of ``values`` (finite, mm; any shape) lies
    beyond :data:`MAX_COORDINATE_MM`; ``what`` names them (and their file)."""
    largest = float(np.abs(np.asarray(values, dtype=np.float64)).max(initial=0.0))
    if largest > MAX_COORDINATE_MM:
        raise InvalidGeometryError(f"The {what}: a coordinate of {largest:.3g} mm, more than "
                                   "1 km from the origin.",
                                   "Coordinates are millimetres; check the units and the file.")


#: Files ``comreg pretrain`` writes first into a run folder; a folder holding one of them is a run
#: folder, into which no other command writes.


def is_run_folder(path: str | Path) -> bool:
    """Whether ``path`` is a folder written by ``comreg pretrain``."""
    path = Path(path)
    return path.is_dir() and any((path / name).exists() for name in runs.RUN_FOLDER_MARKERS)


def check_output_file(path: str | Path, *, inputs=(), what: str = "output file") -> Path:
    """Check, before any work, that ``path`` can be written as a file: not an existing folder,
    inside a folder that exists (or can be made) and is writable, not one of ``inputs``, not in
    a run folder. Returns ``path`` as a Path; raises :class:`OutputPlaceError`."""
    path = Path(path)
    if path.is_dir():
        raise OutputPlaceError(f"The {what} '{path}' is an existing folder, not a file.",
                               "Give a file name (with its extension) that is not a folder.")
    _check_place(path, path.parent, inputs, what, run_folder_ok=False)
    return path


def check_output_folder(path: str | Path, *, inputs=(), what: str = "output folder",
                        run_folder_ok: bool = False) -> Path:
    """Check, before any work, that ``path`` can be used as an output folder: not an existing
    file, writable (or creatable in a writable folder), not one of ``inputs``, and neither a run
    folder nor inside one unless ``run_folder_ok`` (``comreg pretrain`` itself). Returns ``path``
    as a Path; raises :class:`OutputPlaceError`."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputPlaceError(f"The {what} '{path}' exists and is not a folder (a file).",
                               "Choose a folder name that is not taken by a file.")
    _check_place(path, path, inputs, what, run_folder_ok=run_folder_ok)
    return path


def _check_place(path: Path, folder: Path, inputs, what: str, *, run_folder_ok: bool) -> None:
    """The shared part of the output checks: ``folder`` is where ``path`` will be written."""
    existing = folder.absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent  # the nearest folder that exists: the new ones go in there
    if not existing.is_dir():
        raise OutputPlaceError(f"Cannot write the {what} '{path}': '{existing}' is a file, not a "
                               "folder.", "Choose an output place inside a folder.")
    problem = _unwritable(existing)
    if problem:
        raise OutputPlaceError(f"Cannot write the {what} '{path}': '{existing}' is not writable "
                               f"({problem}).", "Choose a folder you can write to.")
    target = path.resolve()
    if not run_folder_ok:
        for candidate in (target, *target.parents):
            if is_run_folder(candidate):
                where = "is" if candidate == target else "is inside"
                raise OutputPlaceError(
                    f"The {what} '{path}' {where} the pretraining run folder '{candidate}'.",
                    "Only 'comreg pretrain' writes into a run folder; choose an output place "
                    "outside it.")
    for given in inputs:  # paths only (an input may also be an object, e.g. a mesh)
        if isinstance(given, (str, os.PathLike)) and Path(given).resolve() == target:
            raise OutputPlaceError(f"The {what} '{path}' is also an input of this command.",
                                   "Write the output somewhere else, so the input is kept.")


def _unwritable(folder: Path) -> str:
    """Why no file can be created in ``folder`` ("" if one can): tried with an anonymous
    temporary file, which leaves nothing behind (read-only or immutable folders fail here even
    for root, where permission bits do not)."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        return (exc.strerror or str(exc)).lower()
    return ""


@contextlib.contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary file keeps the final extension (writers choose their format from it). If the
    block raises, the temporary file is removed and ``path`` is left as it was, so a failed write
    never leaves half-written output. The file gets the mode of any newly created file (0666
    less the user's umask, e.g. 0644 under umask 022), not mkstemp's private 0600.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ext = file_extension(path) or path.suffix
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{ext}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if tmp.exists():  # a writer may have replaced the file: set the mode on what is there
            os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def current_umask() -> int:
    """The process's umask (set and restored at once: the os module has no getter)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def parse_numbers(text: str, count: int, dtype=float):
    """The ``count`` numbers written (space separated) in ``text`` as a ``(count,)`` numpy array,
    or None when ``text`` does not hold exactly ``count`` numbers of that type (the caller says
    which file and field is wrong)."""
    import numpy as np

    try:
        values = np.array([dtype(v) for v in text.split()])
    except ValueError:
        return None
    return values if values.size == count else None
