"""3D Slicer markups files (point lists, e.g. anatomical landmarks): ``.mrk.json`` and ``.fcsv``.

Both as 3D Slicer writes them (``vtkMRMLMarkupsJsonStorageNode``,
``vtkMRMLMarkupsFiducialStorageNode``):

- ``.mrk.json``: ``{"markups": [{"type": "Fiducial", "coordinateSystem": "LPS" | "RAS",
  "controlPoints": [{"label", "description", "position": [x, y, z], "positionStatus"}, ...]},
  ...]}``; the first markup is read. Control points whose ``positionStatus`` is ``undefined``
  or ``missing`` (placed in the list but never positioned) are skipped. A markup without
  ``coordinateSystem`` is LPS (the schema's default).
- ``.fcsv`` (Slicer's legacy fiducial CSV): header lines starting with ``#``, among them
  ``# CoordinateSystem = LPS`` / ``RAS`` (or ``= 1`` / ``= 0``, as Slicer 4.x wrote it) and
  ``# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID``; then one
  comma-separated row per point (Slicer appends more values after ``associatedNodeID``, which
  are ignored). A file without a ``CoordinateSystem`` line is RAS (Slicer before 4.11 wrote
  RAS and no such line).

:func:`read_markups` returns :class:`Markups`: labels, ``(N, 3)`` mm points in the file's space
(:meth:`Markups.in_space` converts: RAS x, y = -LPS x, y), descriptions and per-point
tolerances: a description holding ``tol=5`` (or ``tol=5mm``) gives that point a tolerance of 5 mm
(used by ``comreg register --landmarks``: how far the registered US landmark may lie from its CT
landmark).
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from comreg_core.errors import CorruptFileError, InvalidGeometryError, UnsupportedFormatError
from comreg_core.io._files import file_extension, require_input_file, require_near_origin
from comreg_core.transforms import apply_transform, check_space, space_change

MARKUPS_EXTENSIONS = [".mrk.json", ".json", ".fcsv"]
#: ``tol=5``, ``tol = 2.5 mm`` in a control point's description: its tolerance (mm).
_TOLERANCE_RE = re.compile(r"\btol\s*=\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(?:mm)?",
                           re.IGNORECASE)
#: fcsv ``# CoordinateSystem = ...`` values (Slicer 4.x wrote the numbers).
_FCSV_SPACES = {"ras": "RAS", "0": "RAS", "lps": "LPS", "1": "LPS"}
_FCSV_COLUMNS = ["id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock", "label",
                 "desc", "associatedNodeID"]


@dataclass(frozen=True)
class Markups:
    """Named points of a markups file.

    Attributes:
        labels: each point's label (as shown in Slicer).
        points: ``(N, 3)`` float64 mm in ``space``.
        space: "LPS" or "RAS".
        descriptions: each point's description ("" when none).
        tolerances_mm: each point's tolerance from its description (``tol=5``), None if none.
        path: the file read (or what the points came from), if any.
    """

    labels: tuple[str, ...]
    points: np.ndarray
    space: str = "LPS"
    descriptions: tuple[str, ...] = ()
    tolerances_mm: tuple[float | None, ...] = ()
    path: Path | None = None

    def in_space(self, space: str) -> Markups:
        """The same points expressed in ``space``."""
        space = check_space(space)
        return replace(self, points=apply_transform(space_change(self.space, space),
                                                    self.points), space=space)


def read_markups(path: str | Path) -> Markups:
    """Read a 3D Slicer ``.mrk.json`` or ``.fcsv`` point list (module docstring).

    Raises:
        InputFileNotFoundError, UnsupportedFormatError; CorruptFileError (not JSON/CSV, no
        markup, a point without three numbers, an unknown coordinate system);
        InvalidGeometryError (no positioned point, an empty label).
    """
    path = require_input_file(path, "markups file")
    ext = file_extension(path)
    if ext in (".mrk.json", ".json"):
        labels, points, descriptions, space = _read_json(path)
    elif ext == ".fcsv":
        labels, points, descriptions, space = _read_fcsv(path)
    else:
        raise UnsupportedFormatError(path, "markups (landmarks) file", MARKUPS_EXTENSIONS)
    if not labels:
        raise InvalidGeometryError(f"The markups file '{path}' holds no placed point.",
                                   "Place the landmarks in 3D Slicer and save the point list "
                                   "again.")
    unnamed = [i + 1 for i, label in enumerate(labels) if not label]
    if unnamed:
        raise InvalidGeometryError(f"Point {unnamed[0]} of '{path}' has no label.",
                                   "Name every landmark in 3D Slicer (the labels pair CT and "
                                   "US landmarks).")
    array = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(array).all():
        raise CorruptFileError(path, "a point has a coordinate that is not a finite number")
    require_near_origin(array, f"points in '{path}'")
    return Markups(tuple(labels), array, space, tuple(descriptions),
                   tuple(description_tolerance(d, path, lab)
                         for d, lab in zip(descriptions, labels)),
                   path)


def description_tolerance(description: str, source, label: str) -> float | None:
    """The tolerance (mm) a control point's description gives (``tol=5``, ``tol = 2.5 mm``),
    None if none; ``source`` and ``label`` name the point in the error for a value <= 0."""
    match = _TOLERANCE_RE.search(description or "")
    if match is None:
        return None
    value = float(match.group(1))
    if not (value > 0 and math.isfinite(value)):
        raise InvalidGeometryError(f"The landmark '{label}' in '{source}' has tolerance "
                                   f"{value:g} mm.", "Give a tolerance above 0 (tol=5).")
    return value


def _read_text(path: Path) -> str:
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        raise CorruptFileError(path, "it is not a text markups file (binary content)") from None


def _read_json(path: Path):
    try:
        content = json.loads(_read_text(path))
    except json.JSONDecodeError as exc:
        raise CorruptFileError(path, f"it is not valid JSON ({exc.msg}, line {exc.lineno})") \
            from None
    markups = content.get("markups") if isinstance(content, dict) else None
    if not isinstance(markups, list) or not markups or not isinstance(markups[0], dict):
        raise CorruptFileError(path, "it has no 'markups' list, so it is not a 3D Slicer "
                               "markups file")
    markup = markups[0]
    space = _space(markup.get("coordinateSystem", "LPS"), path)
    points, labels, descriptions = [], [], []
    control_points = markup.get("controlPoints") or []
    if not isinstance(control_points, list):
        raise CorruptFileError(path, "its 'controlPoints' is not a list")
    for i, point in enumerate(control_points):
        if not isinstance(point, dict):
            raise CorruptFileError(path, f"control point {i + 1} is not an object")
        if str(point.get("positionStatus", "defined")).lower() in ("undefined", "missing"):
            continue  # listed but never placed
        points.append(_xyz(point.get("position"), path, i + 1))
        labels.append(str(point.get("label", "")).strip())
        descriptions.append(str(point.get("description", "") or ""))
    return labels, points, descriptions, space


def _read_fcsv(path: Path):
    text = _read_text(path)
    space, columns = "RAS", _FCSV_COLUMNS
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            key, sep, value = stripped.lstrip("#").partition("=")
            key = key.strip().lower()
            if sep and key == "coordinatesystem":
                value = value.strip()
                if value.lower() not in _FCSV_SPACES:
                    raise CorruptFileError(path, f"line {lineno} names the coordinate system "
                                           f"'{value}' (LPS, RAS, 1 or 0 expected)")
                space = _FCSV_SPACES[value.lower()]
            elif sep and key == "columns":
                columns = [c.strip() for c in value.split(",")]
            continue
        rows.append((lineno, line))
    if not {"x", "y", "z"} <= set(columns):
        raise CorruptFileError(path, "its '# columns =' line has no x, y, z columns")
    at = {name: columns.index(name) for name in ("x", "y", "z")}
    label_at = columns.index("label") if "label" in columns else None
    desc_at = columns.index("desc") if "desc" in columns else None
    labels, points, descriptions = [], [], []
    for lineno, line in rows:
        fields = next(csv.reader(io.StringIO(line)))
        if len(fields) <= max(at.values()):
            raise CorruptFileError(path, f"line {lineno} has {len(fields)} values, not the "
                                   "columns its header names")
        try:
            points.append([float(fields[at[c]]) for c in "xyz"])
        except ValueError:
            raise CorruptFileError(path, f"line {lineno} has a coordinate that is not a "
                                   "number") from None
        labels.append(fields[label_at].strip() if label_at is not None
                      and label_at < len(fields) else f"F-{len(labels) + 1}")
        descriptions.append(fields[desc_at] if desc_at is not None and desc_at < len(fields)
                            else "")
    return labels, points, descriptions, space


def _space(value, path: Path) -> str:
    text = str(value).strip().upper()
    if text not in ("LPS", "RAS"):
        raise CorruptFileError(path, f"its coordinateSystem is '{value}' (LPS or RAS expected)")
    return text


def _xyz(position, path: Path, index: int) -> list[float]:
    """A control point's ``position``: a list of three JSON numbers (not strings or
    booleans)."""
    if not (isinstance(position, list) and len(position) == 3 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in position)):
        raise CorruptFileError(path, f"control point {index} has no position [x, y, z] of "
                               "three numbers")
    return [float(v) for v in position]
