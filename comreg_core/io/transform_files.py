"""ITK transform files as 3D Slicer reads and writes them: text ``.tfm``/``.txt`` and HDF5 ``.h5``.

What the file holds, and why it is the *inverse* of a registration result
-------------------------------------------------------------------------
ComReg names a transform ``T_<to>_<from>``: the registration result ``T_ct_us`` maps ultrasound
points to CT points, ``T_ct_us @ p_us = p_ct``, in LPS millimetres. An ITK transform file holds the
opposite direction, ITK's *resampling* direction: it maps points of the fixed ("parent", here CT)
space to the moving ("child", here US) space, so a file for ``T_ct_us`` holds ``inv(T_ct_us)``.
ITK files are always LPS. 3D Slicer works in RAS and converts on save:
``file_LPS = inv(T_RAS_LPS @ ToParent_RAS @ T_RAS_LPS)``, where ``ToParent`` is the transform from
the node placed *under* the transform (the US data) to the scene (CT). So a file saved here and
loaded into Slicer, with the US volume or model dragged under it, moves the US data onto the CT.

Use :func:`save_transform` / :func:`load_transform` with your point-mapping ``T_ct_us``; they do
the inversion (and the RAS/LPS change if you pass ``space="RAS"``). :func:`read_itk_transform` and
:func:`write_itk_transform` give the raw file matrix (LPS, resampling direction) with no inversion.

    T_ct_us = register(...)                            # US -> CT, LPS
    save_transform(T_ct_us, "us_to_ct.h5")             # file holds inv(T_ct_us); open in Slicer
    assert np.allclose(load_transform("us_to_ct.h5"), T_ct_us)

Registration results are rigid, but any invertible affine matrix round-trips. Reading accepts the
linear ITK types (Affine, MatrixOffsetTransformBase, Rigid3D, Euler3D, Versor, VersorRigid3D,
QuaternionRigid, Similarity3D, ScaleVersor3D, Scale, Translation, Identity; double or float) and a
CompositeTransform of them, which ITK applies last-listed first. Writing always produces an
``AffineTransform_double_3_3`` with centre 0, as Slicer does for linear transforms. Nonlinear
transforms (BSpline, displacement fields, thin-plate splines) are rejected.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from comreg_core.errors import ComRegError, CorruptFileError, InvalidTransformError
from comreg_core.io._files import atomic_output, require_extension, require_input_file
from comreg_core.transforms import check_affine, check_space, space_change

TRANSFORM_EXTENSIONS = [".tfm", ".txt", ".h5", ".hdf5"]
_HDF5_EXTENSIONS = (".h5", ".hdf5")
_WRITE_TYPE = "AffineTransform_double_3_3"
_TYPE_RE = re.compile(r"([A-Za-z0-9]+)_(double|float)_(\d+)_(\d+)")
_NONLINEAR_RE = re.compile(r"BSpline|DisplacementField|VelocityField|Kernel|Spline|Diffeomorphic",
                           re.IGNORECASE)
# Number of Parameters for each supported linear type (3-D); every centred type also takes the
# centre as 3 FixedParameters (Euler3D may add a 4th: its ComputeZYX flag).
_N_PARAMS = {
    "AffineTransform": 12, "MatrixOffsetTransformBase": 12, "Rigid3DTransform": 12,
    "Euler3DTransform": 6, "VersorTransform": 3, "VersorRigid3DTransform": 6,
    "QuaternionRigidTransform": 7, "Similarity3DTransform": 7, "ScaleVersor3DTransform": 9,
    "ScaleTransform": 3, "TranslationTransform": 3, "IdentityTransform": 0,
}
_UNCENTRED = ("TranslationTransform", "IdentityTransform")


@dataclass(frozen=True)
class ItkTransformFile:
    """The content of an ITK transform file.

    Attributes:
        matrix: ``(4, 4)`` float64 point-mapping matrix of the file's transform, in LPS and in
            ITK's resampling direction (fixed/parent -> moving/child), centre already folded in.
        transform_type: the top-level ITK type, e.g. ``"AffineTransform_double_3_3"``.
        path: the file it was read from.
        components: for a CompositeTransform, the types it holds in file order; else ``()``.
    """

    matrix: np.ndarray
    transform_type: str
    path: Path | None = None
    components: tuple[str, ...] = ()


# ----------------------------------------------------------------------------------- public API


def load_transform(path: str | Path, *, space: str = "LPS") -> np.ndarray:
    """Read an ITK/Slicer transform file as the point-mapping ``T_to_from`` (e.g. ``T_ct_us``).

    Returns ``inv(file matrix)`` expressed in ``space`` ("LPS" or "RAS", Slicer's scene).
    Raises InputFileNotFoundError, UnsupportedFormatError, CorruptFileError, InvalidTransformError.
    """
    to_space = space_change("LPS", check_space(space))
    T_lps = _invert_affine(read_itk_transform(path).matrix)
    return to_space @ T_lps @ to_space.T


def save_transform(T_to_from: np.ndarray, path: str | Path, *, space: str = "LPS") -> Path:
    """Write the point-mapping ``T_to_from`` (e.g. ``T_ct_us``, given in ``space``) as an ITK file.

    The file holds ``inv(T in LPS)`` as an ``AffineTransform_double_3_3``, which 3D Slicer applies
    to the node placed under it. Returns the path written.
    """
    to_lps = space_change(check_space(space), "LPS")
    T = check_affine(T_to_from)
    return write_itk_transform(_invert_affine(to_lps @ T @ to_lps.T), path)


def read_itk_transform(path: str | Path) -> ItkTransformFile:
    """Read the raw transform of an ITK ``.tfm``/``.txt``/``.h5`` file (no inversion, LPS).

    Raises InputFileNotFoundError, UnsupportedFormatError, CorruptFileError, InvalidTransformError.
    """
    path = require_input_file(path, "transform file")
    ext = require_extension(path, "transform", TRANSFORM_EXTENSIONS)
    entries = _read_h5(path) if ext in _HDF5_EXTENSIONS else _read_text(path)
    return _build(entries, path)


def write_itk_transform(matrix: np.ndarray, path: str | Path) -> Path:
    """Write ``matrix`` verbatim (it must already be LPS, resampling direction) as an ITK
    ``AffineTransform_double_3_3`` with centre 0, atomically. Returns the path written."""
    matrix = check_affine(matrix)
    ext = require_extension(path, "transform", TRANSFORM_EXTENSIONS)
    params = [*matrix[:3, :3].ravel(), *matrix[:3, 3]]
    writer = _write_text
    if ext in _HDF5_EXTENSIONS:
        _require_h5py()  # fail before creating anything
        writer = _write_h5
    with atomic_output(path) as tmp:
        writer(tmp, _WRITE_TYPE, params, [0.0, 0.0, 0.0])
    return Path(path)


# --------------------------------------------------------------------------------- file formats


def _read_text(path: Path) -> list[tuple[str, list[float] | None, list[float] | None]]:
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise CorruptFileError(path, "it is not a text ITK transform file (binary content)")
    entries: list[dict] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        key, sep, value = line.partition(":")
        key = key.strip()
        if not sep or key not in ("Transform", "Parameters", "FixedParameters"):
            raise CorruptFileError(
                path, f"line {lineno} ({line[:60]!r}) is not a 'Transform:', 'Parameters:' or "
                "'FixedParameters:' line of an ITK transform file")
        if key == "Transform":
            entries.append({"type": value.strip(), "Parameters": None, "FixedParameters": None})
        elif not entries:
            raise CorruptFileError(path, f"line {lineno} has {key} before any 'Transform:' line")
        else:
            entries[-1][key] = _parse_numbers(value, path, lineno)
    return [(e["type"], e["Parameters"], e["FixedParameters"]) for e in entries]


def _parse_numbers(text: str, path: Path, lineno: int) -> list[float]:
    try:
        return [float(tok) for tok in text.split()]
    except ValueError:
        raise CorruptFileError(path, f"line {lineno} holds something that is not a number")


def _format_number(x: float) -> str:
    s = repr(float(x) + 0.0)  # shortest exact repr; "+ 0.0" turns -0.0 into 0.0
    return s[:-2] if s.endswith(".0") else s


def _write_text(tmp: Path, transform_type: str, params, fixed) -> None:
    lines = [
        "#Insight Transform File V1.0",
        "#Transform 0",
        f"Transform: {transform_type}",
        "Parameters: " + " ".join(_format_number(p) for p in params),
        "FixedParameters: " + " ".join(_format_number(p) for p in fixed),
    ]
    tmp.write_text("\n".join(lines) + "\n", encoding="ascii")


def _require_h5py():
    try:
        import h5py
    except ImportError:
        raise ComRegError(
            "Reading or writing .h5 transform files needs the h5py package, which is not "
            "installed.",
            "Install it with `pip install h5py` (or `pip install comreg[h5]`), or use a .tfm file.",
        ) from None
    return h5py


def _write_h5(tmp: Path, transform_type: str, params, fixed) -> None:
    h5py = _require_h5py()
    str_type = h5py.string_dtype("ascii")
    with h5py.File(tmp, "w") as f:
        f.create_dataset("HDFVersion", data=np.array(
            [f"HDF5 library version: {h5py.version.hdf5_version}"], dtype=str_type))
        group = f.create_group("TransformGroup").create_group("0")
        group.create_dataset("TransformType", data=np.array([transform_type], dtype=str_type))
        group.create_dataset("TransformParameters", data=np.asarray(params, dtype=np.float64))
        group.create_dataset("TransformFixedParameters", data=np.asarray(fixed, dtype=np.float64))


def _read_h5(path: Path) -> list[tuple[str, list[float] | None, list[float] | None]]:
    h5py = _require_h5py()
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise CorruptFileError(path, "it is not a valid HDF5 file")
    entries = []
    try:
        with f:
            group = f.get("TransformGroup")
            if not isinstance(group, h5py.Group) or len(group) == 0:
                raise CorruptFileError(
                    path, "it has no '/TransformGroup' with transforms, so it is not an ITK "
                    "transform file")
            names = list(group.keys())
            if not all(n.isdigit() for n in names):
                raise CorruptFileError(path, "'/TransformGroup' has members not named 0, 1, ...")
            for name in sorted(names, key=int):
                item = group[name]
                if not isinstance(item, h5py.Group) or "TransformType" not in item:
                    raise CorruptFileError(path, f"'/TransformGroup/{name}' has no TransformType")
                entries.append((_h5_string(item["TransformType"][()]),
                                _h5_numbers(item, "TransformParameters"),
                                _h5_numbers(item, "TransformFixedParameters")))
    except (OSError, KeyError, ValueError, TypeError) as exc:  # damaged datasets
        raise CorruptFileError(path, f"its HDF5 content cannot be read ({exc})") from None
    return entries


def _h5_string(value) -> str:
    if isinstance(value, np.ndarray):
        value = value.ravel()[0] if value.size else b""
    if isinstance(value, bytes):
        value = value.decode("utf-8", errors="replace")
    return str(value).strip()


def _h5_numbers(group, name: str) -> list[float] | None:
    if name not in group:
        return None
    return [float(x) for x in np.asarray(group[name][()], dtype=np.float64).ravel()]


# ------------------------------------------------------------------------- parameters -> matrix


def _build(entries, path: Path) -> ItkTransformFile:
    if not entries:
        raise CorruptFileError(path, "it has no 'Transform:' line")
    top_type = entries[0][0]
    top_name = _type_name(top_type, path)
    if top_name == "CompositeTransform":
        subs = entries[1:]
        components = tuple(e[0] for e in subs)
    elif len(entries) > 1:
        raise InvalidTransformError(
            f"'{path}' holds {len(entries)} transforms that are not wrapped in a "
            "CompositeTransform, so it is unclear how to combine them.",
            "Harden the transforms into one in 3D Slicer and save that transform.",
        )
    else:
        subs, components = entries, ()
    matrix = np.eye(4)
    for transform_type, params, fixed in subs:  # ITK applies the last-listed transform first
        if _type_name(transform_type, path) == "CompositeTransform":
            raise InvalidTransformError(f"'{path}' has a CompositeTransform nested in another.",
                                        "Save the transform again from 3D Slicer.")
        matrix = matrix @ _linear_matrix(transform_type, params, fixed, path)
    if abs(np.linalg.det(matrix[:3, :3])) < 1e-12:
        raise InvalidTransformError(f"The transform in '{path}' is singular (it flattens space).",
                                    "Check the file; a registration transform must be invertible.")
    return ItkTransformFile(matrix=matrix, transform_type=top_type, path=path,
                            components=components)


def _type_name(transform_type: str, path: Path) -> str:
    """The ITK class name of ``transform_type`` after checking it is a supported 3-D linear type."""
    match = _TYPE_RE.fullmatch(transform_type)
    name = match.group(1) if match else transform_type
    if _NONLINEAR_RE.search(name):
        raise InvalidTransformError(
            f"'{path}' holds a nonlinear transform ({transform_type}); ComReg reads only linear "
            "(rigid or affine) transforms.",
            "Save a linear transform from 3D Slicer, e.g. the rigid registration result.",
        )
    if match is None or (name not in _N_PARAMS and name != "CompositeTransform"):
        raise InvalidTransformError(
            f"'{path}' holds an unsupported transform type '{transform_type}'.",
            f"Supported: {', '.join(sorted(_N_PARAMS))} (double or float, 3-D), optionally in a "
            "CompositeTransform.",
        )
    if match.group(3, 4) != ("3", "3"):
        raise InvalidTransformError(
            f"'{path}' holds a {match.group(3)}-D transform ({transform_type}).",
            "ComReg needs a 3-D transform (type name ending in _3_3).",
        )
    return name


def _linear_matrix(transform_type, params, fixed, path: Path) -> np.ndarray:
    """Point-mapping 4x4 of one linear ITK transform: ``p' = A (p - c) + t + c``."""
    name = _type_name(transform_type, path)
    n = _N_PARAMS[name]
    if params is None:
        if n:
            raise CorruptFileError(path, f"the {transform_type} has no Parameters")
        params = []
    if len(params) != n:
        raise CorruptFileError(
            path, f"{transform_type} needs {n} Parameters but the file has {len(params)}")
    fixed = [] if fixed is None else fixed
    centre = np.zeros(3)
    if name not in _UNCENTRED and fixed:  # missing centre: ITK's default 0
        allowed = (3, 4) if name == "Euler3DTransform" else (3,)
        if len(fixed) not in allowed:
            raise CorruptFileError(path, f"{transform_type} needs 3 FixedParameters (the "
                                   f"centre) but the file has {len(fixed)}")
        centre = np.asarray(fixed[:3], dtype=np.float64)
    values = np.asarray([*params, *centre], dtype=np.float64)
    if not np.isfinite(values).all():
        raise InvalidTransformError(
            f"'{path}' has non-finite (NaN or infinite) parameters in its {transform_type}.",
            "The transform is unusable; redo the registration or export it again.",
        )
    p = values[:n]
    A, t = np.eye(3), np.zeros(3)
    if name in ("AffineTransform", "MatrixOffsetTransformBase", "Rigid3DTransform"):
        A, t = p[:9].reshape(3, 3), p[9:12]
    elif name == "Euler3DTransform":
        compute_zyx = len(fixed) == 4 and fixed[3] != 0
        rx, ry, rz = _rot_x(p[0]), _rot_y(p[1]), _rot_z(p[2])
        A, t = (rz @ ry @ rx if compute_zyx else rz @ rx @ ry), p[3:6]
    elif name in ("VersorTransform", "VersorRigid3DTransform", "Similarity3DTransform",
                  "ScaleVersor3DTransform"):
        A = _versor_matrix(p[:3], transform_type, path)
        t = p[3:6] if n > 3 else t
        if name == "Similarity3DTransform":
            A = p[6] * A
        elif name == "ScaleVersor3DTransform":
            A = A + np.diag(p[6:9] - 1.0)  # ITK adds (scale - 1) to the diagonal
    elif name == "QuaternionRigidTransform":
        A, t = _quaternion_matrix(*p[:4]), p[4:7]  # ITK does not normalise the quaternion
    elif name == "ScaleTransform":
        A = np.diag(p[:3])
    elif name == "TranslationTransform":
        t = p[:3]
    M = np.eye(4)
    M[:3, :3] = A
    M[:3, 3] = t + centre - A @ centre
    return M


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _versor_matrix(v: np.ndarray, transform_type: str, path: Path) -> np.ndarray:
    """Rotation of ITK's versor ``(x, y, z)``, the vector part of a unit quaternion with w >= 0."""
    n2 = float(v @ v)
    if n2 > 1.0 + 1e-9:
        raise InvalidTransformError(
            f"'{path}' has a {transform_type} whose versor has norm {math.sqrt(n2):.6g} > 1.",
            "A versor is the vector part of a unit quaternion; export the transform again.",
        )
    if n2 > 1.0:
        v, n2 = v / math.sqrt(n2), 1.0
    return _quaternion_matrix(v[0], v[1], v[2], math.sqrt(1.0 - n2))


def _quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """``|q|^2`` times the rotation of quaternion ``(x, y, z, w)`` (ITK's unnormalised form)."""
    return np.array([
        [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
    ])


def _invert_affine(T: np.ndarray) -> np.ndarray:
    A_inv = np.linalg.inv(T[:3, :3])
    inv = np.eye(4)
    inv[:3, :3] = A_inv
    inv[:3, 3] = -A_inv @ T[:3, 3]
    return inv
