"""File helpers shared by every reader and writer: extension lookup, input checks, atomic writes."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from comreg_core.errors import InputFileNotFoundError, UnsupportedFormatError

# Multi-part extensions first so ".seg.nrrd" wins over ".nrrd".
_COMPOUND_SUFFIXES = (".seg.nrrd", ".igs.nrrd", ".seq.nrrd", ".igs.mha", ".seq.mha", ".nii.gz")


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


@contextlib.contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary file keeps the final extension (writers choose their format from it). If the
    block raises, the temporary file is removed and ``path`` is left as it was, so a failed write
    never leaves half-written output.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ext = file_extension(path) or path.suffix
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{ext}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
