"""The README's headless 3D Slicer example runs as written (on the bundled sample) and does what
the README says: a transform node with T_ct_us near the truth, a .tfm and a scene on disk."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

REPO = Path(__file__).resolve().parents[2]


def _readme_example() -> str:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    example = [b for b in blocks if "ComRegLogic()" in b]
    assert len(example) == 1, "the README should hold one ComRegLogic example"
    return example[0]


def test_the_readme_slicer_example_runs(tmp_path):
    pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)
    (tmp_path / "resources").symlink_to(REPO / "resources")
    namespace: dict = {}
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(compile(_readme_example(), "README.md", "exec"), namespace)
    finally:
        os.chdir(cwd)
    assert (tmp_path / "out" / "T_ct_us.tfm").stat().st_size > 0
    assert (tmp_path / "out" / "scene" / "comreg.mrml").stat().st_size > 0
    node = namespace["summary"].transformNode
    assert node.GetName() == "ReferenceToCT"
    from vtkmodules.vtkCommonMath import vtkMatrix4x4

    matrix = vtkMatrix4x4()
    node.GetMatrixTransformToParent(matrix)
    T = np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])
    # the sample's US points are recorded in the CT frame: the truth is about the identity
    # (ICP from it lands ~3.5 mm / 3 deg away: the tracking's own error)
    from vtkmodules.util.numpy_support import vtk_to_numpy

    bone = vtk_to_numpy(namespace["models"][0].GetPolyData().GetPoints().GetData())  # RAS mm
    centre = np.append(bone.mean(axis=0), 1.0)
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
    shift = np.linalg.norm((T @ centre)[:3] - centre[:3])
    assert angle < 10.0 and shift < 25.0, (angle, shift)
