"""What a registration takes besides the US points and the CT: the operating room's prior
(an initial pose with tolerances, landmark pairs; read from files and parsed from the command
line), the verdict's calibration file, and several US clouds joined into one."""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Sequence

import numpy as np

from comreg_core.errors import ComRegError, InvalidGeometryError
from comreg_core.io import PointCloud
from comreg_core.io._files import require_near_origin
from comreg_core import runs
from comreg_core.registration.judgement.calibration import Calibration
from comreg_core.registration.search.priors import DEFAULT_LANDMARK_TOLERANCE_MM, Landmark, Prior
from comreg_core.transforms import apply_transform, check_rigid, space_change

log = logging.getLogger(__name__)


def find_calibration(calibration: str | Path | None, run_dir: str | Path | None
                     ) -> Calibration | None:
    """The calibration to judge with (:func:`calibration_path`), checked
    (:meth:`Calibration.load`), or None."""
    path = calibration_path(calibration, run_dir)
    return None if path is None else Calibration.load(path)


def calibration_path(calibration: str | Path | None, run_dir: str | Path | None
                     ) -> Path | None:
    """The calibration file to judge with: the one given, else the run folder's own
    ``calibration.json`` (written by ``pretrain``), else None."""
    if calibration is not None:
        return Path(calibration)
    own = None if run_dir is None else Path(run_dir) / runs.CALIBRATION
    return own if own is not None and own.is_file() else None


def join_clouds(clouds: list[PointCloud]) -> tuple[np.ndarray, np.ndarray | None, str | None]:
    """Several US clouds (one tracker frame, one space) as one: ``(points (N, 3), beam origins
    (N, 3) or None, a warning or None)``. The beam origins are kept only when every cloud has
    them: a point without one cannot be checked against its probe, so mixing would judge part
    of the cloud only (the warning says which files lack them)."""
    points = np.vstack([cloud.points for cloud in clouds])
    lacking = [cloud for cloud in clouds if cloud.beam_origins is None]
    if not lacking:
        return points, np.vstack([cloud.beam_origins for cloud in clouds]), None
    if len(lacking) == len(clouds):
        return points, None, None
    names = ", ".join(f"'{Path(cloud.path).name if cloud.path else '?'}'" for cloud in lacking)
    note = (f"Beam origins were not used: {names} has none (they are used only when every US "
            "points file has them, e.g. PLY files from 'comreg extract-us').")
    log.warning("%s", note)
    return points, None, note


def input_paths(us_points_path) -> list[Path]:
    """The US points file(s) as a list of Paths, each given once."""
    if isinstance(us_points_path, (str, Path)):
        return [Path(us_points_path)]
    paths = [Path(path) for path in us_points_path]
    if not paths:
        raise ComRegError("No US points file was given.", "Give at least one US points file.")
    seen = set()
    for path in paths:
        if path.resolve() in seen:
            raise ComRegError(f"The US points file '{path}' was given twice.",
                              "Give each sweep's points once.")
        seen.add(path.resolve())
    return paths


def load_prior(init: str | Path | None = None, init_tolerance=None,
               landmarks: Sequence[str | Path] | None = None,
               landmark_tolerance_mm: float | None = None) -> Prior | None:
    """The :class:`~comreg_core.registration.search.priors.Prior` of ``comreg register``'s ``--init
    TRANSFORM``, ``--init-tolerance DEG,MM``, ``--landmarks CT_POINTS US_POINTS`` and
    ``--landmark-tolerance MM`` (None when neither ``init`` nor ``landmarks`` is given), in LPS.

    ``init``: an ITK transform file as 3D Slicer writes it (or ``comreg register`` does:
    ``transform.tfm``), read as ``T_ct_us`` (:func:`~comreg_core.io.load_transform`; the file
    holds ITK's resampling direction, the inverse). ``init_tolerance``: ``"DEG,MM"`` or
    ``(deg, mm)`` (default 30 deg, 30 mm). ``landmarks``: two 3D Slicer markups files
    (``.mrk.json``, ``.fcsv``; :func:`~comreg_core.io.markups.read_markups`), CT points then US
    points, paired by label; a pair's tolerance: ``tol=5`` in a point's description, else
    ``landmark_tolerance_mm`` (default 10 mm). Raises a :class:`ComRegError` (exit 2) for a
    tolerance without what it belongs to, unreadable files, labels that do not pair up.
    """
    from comreg_core.errors import InvalidTransformError
    from comreg_core.io.markups import read_markups
    from comreg_core.io.transform_files import load_transform
    from comreg_core.registration.search.priors import DEFAULT_MAX_DEG, DEFAULT_MAX_MM

    if init is None and init_tolerance is not None:
        raise ComRegError("--init-tolerance was given without an initial pose.",
                          "Give the initial pose too (--init TRANSFORM), or drop "
                          "--init-tolerance.")
    if not landmarks and landmark_tolerance_mm is not None:
        raise ComRegError("--landmark-tolerance was given without landmarks.",
                          "Give --landmarks CT_POINTS US_POINTS too, or drop "
                          "--landmark-tolerance.")
    if init is None and not landmarks:
        return None
    if init_tolerance is None:
        deg, mm = DEFAULT_MAX_DEG, DEFAULT_MAX_MM
    elif isinstance(init_tolerance, str):
        deg, mm = parse_tolerance(init_tolerance)
    else:
        deg, mm = (float(v) for v in init_tolerance)
    T_init = None
    if init is not None:
        T_init = load_transform(init, space="LPS")
        require_near_origin(T_init[:3, 3], f"initial pose in '{init}' (its translation)")
        try:
            check_rigid(T_init)
        except InvalidTransformError:
            raise InvalidTransformError(f"The initial pose in '{init}' is not rigid (it scales, "
                                        "shears or mirrors).",
                                        "Give a rigid transform (rotation and translation), "
                                        "e.g. a registration's transform.tfm.") from None
    pairs = ()
    if landmarks:
        if len(landmarks) != 2:
            raise ComRegError(f"--landmarks takes two files (CT points, US points), not "
                              f"{len(landmarks)}.", "Give --landmarks CT_POINTS US_POINTS.")
        tolerance = (DEFAULT_LANDMARK_TOLERANCE_MM if landmark_tolerance_mm is None
                     else float(landmark_tolerance_mm))
        pairs = match_landmarks(read_markups(landmarks[0]), read_markups(landmarks[1]),
                                default_tolerance_mm=tolerance, space="LPS")
    return Prior(T_init, deg, mm, pairs, space="LPS",
                 init_file=None if init is None else str(Path(init).absolute()))


def prior_lines(record: dict | None) -> list[str]:
    """What ``comreg register`` prints about a prior: where the result lies in it, and its
    reasons for a CHECK."""
    if not record:
        return []
    parts = []
    if record["rotation_from_init_deg"] is not None:
        parts.append(f"{record['rotation_from_init_deg']:.1f} of {record['max_deg']:g} deg and "
                     f"{record['shift_from_init_mm']:.1f} of {record['max_mm']:g} mm from the "
                     "initial pose")
    parts += [f"landmark '{lm['label']}' {lm['error_mm']:.1f} of {lm['tolerance_mm']:g} mm"
              for lm in record["landmarks"]]
    return [f"prior: {'; '.join(parts)}" + ("; AT THE EDGE: check the result" if
                                            record["at_edge"] else ""), *record["reasons"]]


def prior_inputs(prior: Prior) -> dict:
    """``config.yaml``'s ``inputs.prior``: the initial pose's file and tolerances, the
    landmarks' labels and tolerances."""
    return {"init": prior.init_file,
            "init_tolerance": None if prior.T_init is None else [prior.max_deg, prior.max_mm],
            "landmarks": {lm.label: lm.tolerance_mm for lm in prior.landmarks}}


def parse_tolerance(text: str) -> tuple[float, float]:
    """``"DEG,MM"`` (e.g. ``"30,30"``, ``"20deg,15mm"``) -> ``(deg, mm)``; a clear
    :class:`ComRegError` otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        if len(parts) != 2:
            raise ValueError
        deg = float(re.sub(r"(?i)\s*deg$", "", parts[0]))
        mm = float(re.sub(r"(?i)\s*mm$", "", parts[1]))
    except ValueError:
        raise ComRegError(f"The initial pose's tolerance '{text}' is not DEG,MM.",
                          "Give two numbers, degrees then millimetres, e.g. "
                          "--init-tolerance 30,30.") from None
    return deg, mm


def match_landmarks(ct, us, *, default_tolerance_mm: float = DEFAULT_LANDMARK_TOLERANCE_MM,
                    space: str = "LPS") -> tuple[Landmark, ...]:
    """Pair the CT and US landmarks by label (objects with ``labels``, ``points`` ``(N, 3)``,
    ``space``, ``tolerances_mm`` and ``path``: :class:`comreg_core.io.markups.Markups`), both
    taken to ``space``. A pair's tolerance: its description's (``tol=5``; the smaller of the
    two when both have one), else ``default_tolerance_mm``.

    Raises:
        ComRegError: a label twice in one file, a label in only one of them, no pair.
    """
    sides = []
    for what, markups in (("CT", ct), ("US", us)):
        labels = list(markups.labels)
        twice = sorted({label for label in labels if labels.count(label) > 1})
        if twice:
            raise InvalidGeometryError(
                f"The {what} landmarks ('{markups.path}') name '{twice[0]}' more than once.",
                "Give each landmark its own label: the labels pair CT and US landmarks.")
        points = apply_transform(space_change(markups.space, space), markups.points)
        tolerances = list(markups.tolerances_mm) or [None] * len(labels)
        sides.append({label: (p, t) for label, p, t in zip(labels, points, tolerances)})
    only_ct = [label for label in sides[0] if label not in sides[1]]
    only_us = [label for label in sides[1] if label not in sides[0]]
    if only_ct or only_us:
        parts = ([f"{_names(only_ct)} only in the CT landmarks ('{ct.path}')"] if only_ct
                 else []) + ([f"{_names(only_us)} only in the US landmarks ('{us.path}')"]
                             if only_us else [])
        raise InvalidGeometryError(f"The landmarks do not pair up: {'; '.join(parts)}.",
                                   "Give each landmark the same label in both files.")
    pairs = []
    for label, (ct_point, ct_tol) in sides[0].items():
        us_point, us_tol = sides[1][label]
        given = [t for t in (ct_tol, us_tol) if t is not None]
        pairs.append(Landmark(label, ct_point, us_point,
                              min(given) if given else float(default_tolerance_mm)))
    return tuple(pairs)


def _names(labels: list[str]) -> str:
    return ", ".join(f"'{label}'" for label in labels)
