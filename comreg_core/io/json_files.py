"""The JSON files ComReg writes (``result.json``, ``metrics.json``, ``calibration.json``, ...)
and reads back: strict JSON (RFC 8259), which has no NaN or Infinity.

**Writing** (:func:`write_json`, atomic): numpy scalars and arrays become numbers and lists,
paths and other objects their text, and every float that is not finite becomes ``null``. When
the top level is an object, ``null_reasons`` (:data:`NULL_REASONS`) then maps the place of each
such null, as a JSON Pointer (RFC 6901: ``/search/scores_mm/flip``), to why it is
null: ``"not finite (NaN)"``, ``"not finite (+Infinity)"`` or ``"not finite (-Infinity)"``.
A file without such a null has no ``null_reasons``.

**Reading** (:func:`read_json`): refuses the NaN/Infinity tokens Python's ``json`` accepts and
numbers too large for a float, so what is read is strict JSON with finite numbers only.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from comreg_core.errors import CorruptFileError
from comreg_core.io._files import atomic_output, require_input_file

#: The top-level key that says why values are null (module docstring).
NULL_REASONS = "null_reasons"


def strict_json(value: Any) -> tuple[Any, dict[str, str]]:
    """``value`` as plain JSON data (dicts, lists, str, int, finite float, bool, None) and the
    reasons of the nulls put in place of non-finite floats, keyed by JSON Pointer."""
    reasons: dict[str, str] = {}
    return _plain(value, "", reasons), reasons


def write_json(data: Any, path: str | Path) -> Path:
    """Write ``data`` to ``path`` as indented strict JSON (module docstring), atomically."""
    plain, reasons = strict_json(data)
    if reasons and isinstance(plain, dict):
        plain[NULL_REASONS] = {**plain.get(NULL_REASONS, {}), **reasons}
    text = json.dumps(plain, indent=2, allow_nan=False)
    path = Path(path)
    with atomic_output(path) as tmp:
        tmp.write_text(text + "\n", encoding="utf-8")
    return path


def read_json(path: str | Path, what: str = "JSON file") -> Any:
    """The content of a strict JSON file (module docstring); a :class:`CorruptFileError` for a
    file that is not one."""
    path = require_input_file(path, what)
    try:
        return json.loads(path.read_bytes().decode("utf-8-sig"),
                          parse_constant=_refuse_constant, parse_float=_finite_float)
    except UnicodeDecodeError:
        raise CorruptFileError(path, "it is not a text JSON file (binary content)") from None
    except json.JSONDecodeError as exc:
        raise CorruptFileError(path, f"it is not valid JSON ({exc.msg}, line {exc.lineno})") \
            from None
    except ValueError as exc:
        raise CorruptFileError(path, str(exc)) from None


def _refuse_constant(token: str):
    raise ValueError(f"it holds '{token}', which is not a number in JSON")


def _finite_float(token: str) -> float:
    value = float(token)
    if not math.isfinite(value):
        raise ValueError(f"it holds the number {token[:40]}, too large for a float")
    return value


def _plain(value: Any, pointer: str, reasons: dict[str, str]) -> Any:
    if isinstance(value, dict):
        return {str(k): _plain(v, f"{pointer}/{_escape(str(k))}", reasons)
                for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{pointer}/{i}", reasons) for i, v in enumerate(value)]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist(), pointer, reasons)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        if math.isfinite(value):
            return float(value)
        reasons[pointer] = ("not finite (NaN)" if math.isnan(value) else
                            f"not finite ({'+' if value > 0 else '-'}Infinity)")
        return None
    if value is None or isinstance(value, str):
        return value
    return str(value)


def _escape(key: str) -> str:
    """A key as a JSON Pointer reference token (RFC 6901: ``~`` -> ``~0``, ``/`` -> ``~1``)."""
    return key.replace("~", "~0").replace("/", "~1")
