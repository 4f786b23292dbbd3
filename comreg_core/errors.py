"""Typed errors for problems a user can cause and fix.

Every error carries a message that says what is wrong *and* what to do about it. The CLI prints
``str(error)`` and exits with status 2; it never shows a traceback for these. Errors that are bugs
in ComReg itself are ordinary Python exceptions and are not caught.
"""

from __future__ import annotations

from pathlib import Path


class ComRegError(Exception):
    """Base class of all user-fixable errors: ``problem`` plus a ``hint`` on what to do."""

    def __init__(self, problem: str, hint: str = ""):
        self.problem = problem
        self.hint = hint
        super().__init__(f"{problem} {hint}".strip())


class InputFileNotFoundError(ComRegError, FileNotFoundError):
    """An input path does not exist or is not a regular file (e.g. a folder)."""

    def __init__(self, path: str | Path, what: str = "input file"):
        if Path(path).is_dir():
            super().__init__(f"The {what} '{path}' is a folder, not a file.",
                             "Pass the file inside it.")
        elif Path(path).exists():  # a device, a pipe, a socket
            super().__init__(f"The {what} '{path}' is not a regular file.",
                             "Pass a file saved on disk.")
        else:
            super().__init__(
                f"The {what} '{path}' does not exist.",
                "Check the path (relative paths are resolved from the current directory).",
            )
        self.path = Path(path)


class OutputPlaceError(ComRegError):
    """An output path cannot be used: it exists as the wrong kind, cannot be written, is one of
    the inputs, or lies in a pretraining run folder. Raised before any work is done."""


class UnsupportedFormatError(ComRegError):
    """The file extension is not one ComReg reads or writes for this kind of data."""

    def __init__(self, path: str | Path, kind: str, supported: list[str]):
        super().__init__(
            f"'{path}' has an extension ComReg cannot use for a {kind}.",
            f"Use one of: {', '.join(supported)}.",
        )
        self.path = Path(path)


class CorruptFileError(ComRegError):
    """A file exists and has a known extension but its content cannot be parsed."""

    def __init__(self, path: str | Path, detail: str):
        super().__init__(
            f"Cannot read '{path}': {detail}.",
            "The file looks corrupt or truncated; export it again from the program that made it.",
        )
        self.path = Path(path)


class MissingSpatialMetadataError(ComRegError):
    """A volume file lacks the geometry (spacing, origin, directions) needed to place it in mm."""

    def __init__(self, path: str | Path, missing: str):
        super().__init__(
            f"'{path}' has no spatial metadata ({missing}), so its voxels cannot be placed in "
            "patient millimetres.",
            "Save the volume from 3D Slicer or ITK, which write 'space', 'space directions' and "
            "'space origin' for NRRD files.",
        )
        self.path = Path(path)


class LabelNotFoundError(ComRegError):
    """The requested label value or segment name is not in the segmentation."""


class EmptyMaskError(ComRegError):
    """The selected label or segment has no voxels, so there is no surface to extract."""


class InvalidGeometryError(ComRegError):
    """Coordinates or connectivity are unusable: non-finite values, no faces, too few points."""


class InvalidTransformError(ComRegError):
    """A transform is not a usable rigid (or affine) 4x4 matrix or has an unsupported type."""
