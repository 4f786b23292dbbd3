"""3D Slicer markups files (.mrk.json, .fcsv) as landmarks: read as Slicer writes them (by
slicer-core's own storage nodes where installed, and as literal files with known coordinates),
LPS and RAS (RAS x, y = -LPS x, y), per-point tolerances, pairing by label, clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from comreg_core.errors import (ComRegError, CorruptFileError, InputFileNotFoundError,
                                InvalidGeometryError, UnsupportedFormatError)
from comreg_core.io import describe_file
from comreg_core.io.markups import read_markups
from comreg_core.register.inputs import match_landmarks
from tests.helpers import assert_close

#: Known points in LPS (mm) and their labels; "knee" carries its own tolerance.
LPS = np.array([[12.5, -40.25, 101.0], [-3.0, 7.5, -250.125]])
LABELS = ("tip", "knee")
RAS = LPS * [-1.0, -1.0, 1.0]

FCSV_LPS = """# Markups fiducial file version = 5.6
# CoordinateSystem = LPS
# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID
1,12.5,-40.25,101,0,0,0,1,1,1,0,tip,,,2,0
2,-3,7.5,-250.125,0,0,0,1,1,1,0,knee,tol=5,,2,0
"""
#: Slicer 4.x: the coordinate system as a number (0 = RAS) and node-named ids.
FCSV_RAS_LEGACY = """# Markups fiducial file version = 4.10
# CoordinateSystem = 0
# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID
vtkMRMLMarkupsFiducialNode_0,-12.5,40.25,101,0,0,0,1,1,1,0,tip,,vtkMRMLModelNode5
vtkMRMLMarkupsFiducialNode_1,3,-7.5,-250.125,0,0,0,1,1,1,0,knee,tol = 5 mm,vtkMRMLModelNode5
"""


def _mrk_json(space: str, points, *, extra=None) -> str:
    controls = [{"id": str(i + 1), "label": label, "description": "tol=5" if i else "",
                 "associatedNodeID": "", "position": list(map(float, p)),
                 "orientation": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                 "selected": True, "locked": False, "visibility": True,
                 "positionStatus": "defined"} for i, (label, p) in enumerate(zip(LABELS, points))]
    controls += extra or []
    return json.dumps({"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/"
                       "Loadable/Markups/Resources/Schema/markups-schema-v1.0.3.json#",
                       "markups": [{"type": "Fiducial", "coordinateSystem": space,
                                    "coordinateUnits": "mm", "controlPoints": controls,
                                    "measurements": []}]}, indent=4)


def _check(markups, space):
    assert markups.labels == LABELS and markups.space == space
    assert markups.tolerances_mm == (None, 5.0)
    assert_close(markups.in_space("LPS").points, LPS, atol=1e-12, what="LPS points")
    assert_close(markups.in_space("RAS").points, RAS, atol=1e-12, what="RAS points")


@pytest.mark.parametrize("space", ["LPS", "RAS"])
def test_mrk_json_in_either_space(tmp_path, space):
    points = LPS if space == "LPS" else RAS
    unplaced = {"id": "3", "label": "later", "position": [0.0, 0.0, 0.0],
                "positionStatus": "undefined"}
    path = tmp_path / "ct.mrk.json"
    path.write_text(_mrk_json(space, points, extra=[unplaced]), encoding="utf-8")
    _check(read_markups(path), space)  # the point never placed is left out


def test_fcsv_lps_and_legacy_ras(tmp_path):
    (tmp_path / "a.fcsv").write_text(FCSV_LPS, encoding="utf-8")
    (tmp_path / "b.fcsv").write_text(FCSV_RAS_LEGACY, encoding="utf-8")
    _check(read_markups(tmp_path / "a.fcsv"), "LPS")
    _check(read_markups(tmp_path / "b.fcsv"), "RAS")
    described = describe_file(tmp_path / "b.fcsv")  # comreg info
    assert "space: RAS" in described and "'knee': 3 -7.5 -250.125 (tol 5 mm)" in described


@pytest.mark.parametrize("storage", ["vtkMRMLMarkupsFiducialStorageNode",
                                     "vtkMRMLMarkupsJsonStorageNode"])
@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_files_written_by_slicer_itself(tmp_path, storage, system):
    """slicer-core's own writers (the scene is RAS; the file in the chosen system)."""
    pytest.importorskip("slicer_core")
    import slicer

    scene = slicer.vtkMRMLScene()
    node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "CT")
    for label, point in zip(LABELS, RAS):
        node.AddControlPoint(point.tolist(), label)
    node.SetNthControlPointDescription(1, "tol=5")
    writer = getattr(slicer, storage)()
    scene.AddNode(writer)
    writer.SetCoordinateSystem(1 if system == "LPS" else 0)  # Slicer's LPS = 1, RAS = 0
    path = tmp_path / ("ct.fcsv" if "Fiducial" in storage else "ct.mrk.json")
    writer.SetFileName(str(path))
    assert writer.WriteData(node)
    assert f"{system}" in path.read_text()
    _check(read_markups(path), system)


def test_landmarks_pair_by_label_in_the_ct_space(tmp_path):
    (tmp_path / "ct.fcsv").write_text(FCSV_LPS, encoding="utf-8")
    us = tmp_path / "us.mrk.json"  # the US points in another order, in RAS, no tolerances
    us.write_text(json.dumps({"markups": [{"coordinateSystem": "RAS", "controlPoints": [
        {"label": "knee", "position": [1.0, 2.0, 3.0]},
        {"label": "tip", "position": [-4.0, -5.0, 6.0]}]}]}), encoding="utf-8")
    pairs = match_landmarks(read_markups(tmp_path / "ct.fcsv"), read_markups(us),
                            default_tolerance_mm=12.0, space="LPS")
    assert [p.label for p in pairs] == ["tip", "knee"]
    assert [p.tolerance_mm for p in pairs] == [12.0, 5.0]
    assert_close(pairs[0].ct, LPS[0], atol=1e-12)
    assert_close(pairs[0].us, [4.0, 5.0, 6.0], atol=1e-12, what="RAS -> LPS")
    ras = match_landmarks(read_markups(tmp_path / "ct.fcsv"), read_markups(us), space="RAS")
    assert_close(ras[1].ct, RAS[1], atol=1e-12)


def test_bad_landmark_files_are_clear_errors(tmp_path):
    ct = tmp_path / "ct.fcsv"
    ct.write_text(FCSV_LPS, encoding="utf-8")
    other = tmp_path / "other.fcsv"
    other.write_text(FCSV_LPS.replace(",tip,", ",apex,"), encoding="utf-8")
    with pytest.raises(ComRegError, match="do not pair up: 'tip' only in the CT.*'apex' only "
                                          "in the US"):
        match_landmarks(read_markups(ct), read_markups(other))
    twice = tmp_path / "twice.fcsv"
    twice.write_text(FCSV_LPS.replace(",knee,", ",tip,"), encoding="utf-8")
    with pytest.raises(ComRegError, match="'tip' more than once"):
        match_landmarks(read_markups(twice), read_markups(ct))
    cases = {
        "empty.fcsv": ("# CoordinateSystem = LPS\n", InvalidGeometryError, "no placed point"),
        "words.fcsv": (FCSV_LPS.replace("12.5", "abc"), CorruptFileError, "not a number"),
        "space.fcsv": (FCSV_LPS.replace("= LPS", "= IJK"), CorruptFileError, "IJK"),
        "nolabel.fcsv": (FCSV_LPS.replace(",tip,", ",,"), InvalidGeometryError, "no label"),
        "zero.fcsv": (FCSV_LPS.replace("tol=5", "tol=0"), InvalidGeometryError, "tolerance 0"),
        "broken.mrk.json": ('{"markups": [', CorruptFileError, "not valid JSON"),
        "other.json": ('{"points": []}', CorruptFileError, "no 'markups' list"),
        "nopos.mrk.json": ('{"markups": [{"controlPoints": [{"label": "a"}]}]}',
                           CorruptFileError, "no position"),
        "binary.fcsv": (b"\xff\xfe\x00garbage", CorruptFileError, "binary"),
    }
    for name, (content, error, message) in cases.items():
        path = tmp_path / name
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content, encoding="utf-8")
        with pytest.raises(error, match=message):
            read_markups(path)
    (tmp_path / "points.csv").write_text("1,2,3\n", encoding="utf-8")
    with pytest.raises(UnsupportedFormatError, match=r"\.mrk\.json"):
        read_markups(tmp_path / "points.csv")
    with pytest.raises(InputFileNotFoundError):
        read_markups(tmp_path / "missing.fcsv")
