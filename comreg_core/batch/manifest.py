"""The cohort manifest of ``comreg batch``: one case per row, read from CSV or YAML and checked
in full before anything runs.

Columns (the same keys in YAML, a list of mappings or ``{cases: [...]}``):

- ``case`` (required): the case's name, also its folder name under ``OUT/cases/``: letters,
  digits, ``.``, ``_`` and ``-``, starting with a letter or digit; unique (ignoring letter case,
  as some file systems do).
- ``ct`` (required): the CT bone: a label map (``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd``), a 3D
  Slicer ``.seg.nrrd`` (pick the bone with ``label`` or ``segment`` where there are several) or a
  mesh (``.stl``, ``.ply``, ``.obj``, ``.vtk``, ``.vtp``).
- ``us`` (required): a tracked sweep (frame folder, PLUS ``.igs.mha``/``.seq.mha``/...), a
  reconstructed US volume, or a US bone points file (``.ply``, ``.xyz``, ...).
- ``calibration``: the probe calibration of a tracked sweep (PLUS XML or ``calibration.json``).
- ``model``: a pretrained run folder (``comreg pretrain``) to register with.
- ``gt``: the true ``T_ct_us`` (ITK transform file) to evaluate against.
- ``init`` (ITK transform), ``init_tolerance`` (``"DEG,MM"``), ``landmarks_ct`` and
  ``landmarks_us`` (3D Slicer markups files): the priors of ``comreg register``.

Relative paths are read from the manifest's folder. Every problem found is one line naming
its row (data rows count from 1, the CSV header not counted; ``row 0`` is the header); all of
them are raised together as a :class:`ManifestError`.
"""

from __future__ import annotations

import csv
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from comreg_core.errors import ComRegError
from comreg_core.io import (MARKUPS_EXTENSIONS, MESH_EXTENSIONS, POINT_CLOUD_EXTENSIONS,
                            SEGMENTATION_READ_EXTENSIONS, TRANSFORM_EXTENSIONS)
from comreg_core.io._files import file_extension, is_run_folder
from comreg_core.io.sweeps import SWEEP_EXTENSIONS

#: Columns every row needs.
REQUIRED_COLUMNS = ("case", "ct", "us")
#: Columns a row may have.
OPTIONAL_COLUMNS = ("label", "segment", "calibration", "model", "gt", "init", "init_tolerance",
                    "landmarks_ct", "landmarks_us")
COLUMNS = REQUIRED_COLUMNS + OPTIONAL_COLUMNS
#: Columns holding paths, and what each must be: a "file", a "folder" or "either".
PATH_COLUMNS = {"ct": "file", "us": "either", "calibration": "file", "model": "either",
                "gt": "file", "init": "file", "landmarks_ct": "file", "landmarks_us": "file"}
#: A case name that is safe as a folder name on every file system.
CASE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")
#: File formats by column (extensions as :func:`~comreg_core.io._files.file_extension` gives).
_FORMATS = {"ct": ("a CT label map, .seg.nrrd or bone mesh",
                   [*SEGMENTATION_READ_EXTENSIONS, *MESH_EXTENSIONS]),
            "us": ("a tracked sweep, US volume or points file",
                   [*SWEEP_EXTENSIONS, *POINT_CLOUD_EXTENSIONS]),
            "gt": ("an ITK transform file", TRANSFORM_EXTENSIONS),
            "init": ("an ITK transform file", TRANSFORM_EXTENSIONS),
            "landmarks_ct": ("a 3D Slicer markups file", MARKUPS_EXTENSIONS),
            "landmarks_us": ("a 3D Slicer markups file", MARKUPS_EXTENSIONS)}


class ManifestError(ComRegError):
    """The manifest has problems; :attr:`lines` holds one line per problem, each naming the
    manifest and the row."""

    def __init__(self, path: str | Path, lines: list[str]):
        self.lines = list(lines)
        super().__init__(f"The manifest '{path}' has {len(lines)} problem(s): "
                         + " ".join(self.lines), "Fix them and run again.")


@dataclass(frozen=True)
class Case:
    """One row of the manifest, paths absolute.

    Attributes:
        name: the case's name (its folder under ``OUT/cases/``); row: its row (from 1).
        ct, us: the CT bone (label map, ``.seg.nrrd`` or mesh) and the US data (tracked sweep,
            US volume or points file).
        label, segment: which segment of ``ct`` is the bone (label maps only).
        calibration: the probe calibration of the sweep; model: a pretrained run to reuse;
        gt: the true ``T_ct_us`` (ITK transform file) for evaluation.
        init, init_tolerance, landmarks_ct, landmarks_us: the priors of ``comreg register``.
    """

    name: str
    row: int
    ct: Path
    us: Path
    label: int | None = None
    segment: str | None = None
    calibration: Path | None = None
    model: Path | None = None
    gt: Path | None = None
    init: Path | None = None
    init_tolerance: str | None = None
    landmarks_ct: Path | None = None
    landmarks_us: Path | None = None

    @property
    def ct_is_mesh(self) -> bool:
        """Whether ``ct`` is already a mesh (else a label map to mesh)."""
        return file_extension(self.ct) in MESH_EXTENSIONS

    @property
    def us_is_points(self) -> bool:
        """Whether ``us`` is a points file (registered as it is, no extraction)."""
        return self.us.is_file() and file_extension(self.us) in POINT_CLOUD_EXTENSIONS

    @property
    def us_is_tracked_sweep(self) -> bool:
        """Whether ``us`` is a tracked sweep (frames with poses), not a volume or points."""
        if self.us.is_dir():
            return True
        if self.us_is_points:
            return False
        from comreg_core.surfaces.us_volume import is_volume_file

        try:
            return not is_volume_file(self.us)
        except (ComRegError, OSError):  # unreadable: extract-us will say why, for this case
            return True


def read_rows(path: str | Path) -> tuple[list[str] | None, list[dict[str, Any]]]:
    """``(CSV header or None for YAML, rows)`` of a manifest file as given (values stripped,
    empty CSV cells dropped); a :class:`ManifestError` if the file cannot be read as one."""
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise ManifestError(path, [f"{path}: " + ("is a folder, not a manifest file"
                                                  if path.is_dir() else "does not exist")])
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError(path, [f"{path}: cannot be read as text ({exc})"]) from None
    if suffix == ".csv":
        reader = csv.DictReader(text.splitlines(), skipinitialspace=True, restkey="\0extra")
        header = [str(name).strip() for name in (reader.fieldnames or [])]
        rows = []
        for raw in reader:
            row = {str(key).strip(): value.strip() for key, value in raw.items()
                   if key != "\0extra" and isinstance(value, str) and value.strip()}
            if "\0extra" in raw:
                row["\0extra"] = raw["\0extra"]
            if row:
                rows.append(row)
        return header, rows
    if suffix in (".yaml", ".yml"):
        import yaml

        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ManifestError(path, [f"{path}: not valid YAML ({' '.join(str(exc).split())})"
                                       ]) from None
        if isinstance(data, dict) and set(data) == {"cases"}:
            data = data["cases"]
        if not isinstance(data, list) or not all(isinstance(row, dict) for row in data):
            raise ManifestError(path, [f"{path}: a YAML manifest is a list of cases (mappings "
                                       "with the columns as keys), or 'cases:' holding one"])
        return None, [{str(k): v for k, v in row.items() if v is not None and str(v).strip()}
                      for row in data]
    raise ManifestError(path, [f"{path}: a manifest is a .csv, .yaml or .yml file"])


def load_manifest(path: str | Path) -> list[Case]:
    """The cases of the manifest at ``path``, checked (module docstring); raises a
    :class:`ManifestError` listing every problem."""
    path = Path(path)
    header, rows = read_rows(path)
    problems: list[str] = []
    if header is not None:
        problems += [f"{path} row 0 (header): unknown column '{name}' (known: "
                     f"{', '.join(COLUMNS)})" for name in header if name not in COLUMNS]
        problems += [f"{path} row 0 (header): the required column '{name}' is missing"
                     for name in REQUIRED_COLUMNS if name not in header]
        if problems:
            raise ManifestError(path, problems)
    if not rows:
        raise ManifestError(path, [f"{path}: has no cases"])
    cases, seen = [], {}
    for number, row in enumerate(rows, start=1):
        row_problems: list[str] = []
        case = _check_row(row, path.parent, row_problems)
        name = str(row.get("case", ""))
        if name and name.casefold() in seen:
            row_problems.append(f"case '{name}' is also in row {seen[name.casefold()]}")
        elif name:
            seen[name.casefold()] = number
        problems += [f"{path} row {number}: {problem}" for problem in row_problems]
        if case is not None and not row_problems:
            cases.append(Case(row=number, **case))
    if problems:
        raise ManifestError(path, problems)
    return cases


def _check_row(row: dict[str, Any], base: Path, problems: list[str]) -> dict[str, Any] | None:
    """The :class:`Case` fields of one row (paths resolved against ``base``), appending what is
    wrong with it to ``problems``."""
    if "\0extra" in row:
        problems.append(f"{len(row.pop(chr(0) + 'extra'))} more value(s) than the header has "
                        "columns (a comma inside a value needs quotes)")
    problems += [f"unknown column '{key}' (known: {', '.join(COLUMNS)})" for key in row
                 if key not in COLUMNS]
    problems += [f"'{key}' is missing or empty" for key in REQUIRED_COLUMNS if key not in row]
    fields: dict[str, Any] = {}
    name = str(row.get("case", ""))
    if name and not CASE_NAME.fullmatch(name):
        problems.append(f"case name '{name}' cannot be a folder name: use up to 100 letters, "
                        "digits, '.', '_' and '-', starting with a letter or digit")
    fields["name"] = name
    for key, kind in PATH_COLUMNS.items():
        if key in row:
            fields[key] = _check_path(key, row[key], kind, base, problems)
    if "label" in row:
        try:
            fields["label"] = int(str(row["label"]))
            if fields["label"] < 0:
                raise ValueError
        except ValueError:
            problems.append(f"'label' is '{row['label']}', not a whole number >= 0")
    if "segment" in row:
        fields["segment"] = str(row["segment"])
    if ("label" in row or "segment" in row) and fields.get("ct") is not None and \
            file_extension(fields["ct"]) in MESH_EXTENSIONS:
        problems.append("'label'/'segment' pick a segment of a label map, but 'ct' is a mesh")
    _check_priors(row, fields, problems)
    us, calibration = fields.get("us"), fields.get("calibration")
    if calibration is not None and us is not None and us.is_file() and \
            file_extension(us) in POINT_CLOUD_EXTENSIONS:
        problems.append("'calibration' belongs to a tracked sweep, but 'us' is a points file")
    model = fields.get("model")
    if model is not None and model.is_dir() and not is_run_folder(model):
        problems.append(f"'model' ('{row['model']}') is not a run folder of 'comreg pretrain' "
                        "(no checkpoint.pt in it)")
    return None if problems else fields


def _check_priors(row: dict[str, Any], fields: dict[str, Any], problems: list[str]) -> None:
    """The priors' columns: a tolerance needs its pose, landmarks come in pairs."""
    if "init_tolerance" in row:
        from comreg_core.register import parse_tolerance  # (imports torch: only here)

        fields["init_tolerance"] = str(row["init_tolerance"])
        if "init" not in row:
            problems.append("'init_tolerance' is given without 'init'")
        try:
            parse_tolerance(fields["init_tolerance"])
        except ComRegError:
            problems.append(f"'init_tolerance' is '{row['init_tolerance']}', not DEG,MM "
                            "(e.g. 30,30)")
    if ("landmarks_ct" in row) != ("landmarks_us" in row):
        given, missing = (("landmarks_ct", "landmarks_us") if "landmarks_ct" in row
                          else ("landmarks_us", "landmarks_ct"))
        problems.append(f"'{given}' is given without '{missing}' (landmarks come in pairs)")


def _check_path(key: str, value: Any, kind: str, base: Path, problems: list[str]
                ) -> Path | None:
    """``value`` as an absolute path (relative ones from ``base``) if it exists as ``kind``
    (and in a format the column takes), else None with the problem appended."""
    path = Path(str(value)).expanduser()
    path = Path(os.path.abspath(path if path.is_absolute() else base / path))  # no '..' left
    if not path.exists():
        problems.append(f"'{key}' path '{value}' does not exist")
        return None
    if kind == "file" and not path.is_file():
        problems.append(f"'{key}' ('{value}') is a folder, not a file")
        return None
    if key in _FORMATS and path.is_file():
        what, extensions = _FORMATS[key]
        if file_extension(path) not in extensions and path.suffix.lower() not in extensions:
            problems.append(f"'{key}' ('{value}') is not {what} (takes "
                            f"{', '.join(sorted(set(extensions)))})")
            return None
    return path
