"""Strict JSON files: non-finite floats become null with their reasons by JSON Pointer; reading
refuses NaN, Infinity and numbers too large for a float."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from comreg_core.errors import CorruptFileError
from comreg_core.io.json_files import NULL_REASONS, read_json, strict_json, write_json


def _strict(text: str):
    def refuse(token):
        raise ValueError(token)

    return json.loads(text, parse_constant=refuse)


def test_non_finite_floats_become_null_with_their_reasons(tmp_path):
    data = {"a": math.nan, "b": [1.0, np.float32(np.inf), {"c/d": -math.inf}],
            "e": np.array([[0.5, np.nan]]), "f~": {"g": np.float64("nan")}, "ok": 2,
            "n": np.int64(3), "flag": np.bool_(True), "none": None, "path": tmp_path}
    path = write_json(data, tmp_path / "out" / "result.json")
    saved = _strict(path.read_text())
    assert saved["a"] is None and saved["b"] == [1.0, None, {"c/d": None}]
    assert saved["e"] == [[0.5, None]] and saved["f~"] == {"g": None}
    assert (saved["ok"], saved["n"], saved["flag"], saved["none"]) == (2, 3, True, None)
    assert saved["path"] == str(tmp_path)
    assert saved[NULL_REASONS] == {"/a": "not finite (NaN)", "/b/1": "not finite (+Infinity)",
                                   "/b/2/c~1d": "not finite (-Infinity)",
                                   "/e/0/1": "not finite (NaN)", "/f~0/g": "not finite (NaN)"}
    assert not list(path.parent.glob(".*tmp*"))


def test_a_file_without_non_finite_values_has_no_reasons(tmp_path):
    path = write_json({"x": [1.5, 2], "y": "z"}, tmp_path / "plain.json")
    assert _strict(path.read_text()) == {"x": [1.5, 2], "y": "z"}
    assert strict_json([math.nan]) == ([None], {"/0": "not finite (NaN)"})


@pytest.mark.parametrize("text, message", [
    ('{"w": NaN}', "'NaN'"), ('{"w": [1, -Infinity]}', "'-Infinity'"),
    ('{"w": 1e999}', "too large for a float"), ('{"w": ', "not valid JSON"),
])
def test_reading_refuses_what_is_not_strict_json_with_finite_numbers(tmp_path, text, message):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(CorruptFileError, match=message):
        read_json(path)
    assert read_json(write_json({"w": [1e300, -2]}, tmp_path / "ok.json")) == {"w": [1e300, -2]}
