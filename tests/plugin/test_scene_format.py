"""Saved scenes look to 3D Slicer 5 like its own: the ``<MRML>`` header in the form Slicer 5
writes it, a version Slicer 5 opens without its "may not load correctly" warning, and node
elements under MRML's own tags.

The reference is a scene saved by 3D Slicer 5.6.1, quoted in the public repository
transit-chd/brain-structural-pipeline (``run-brain-structural-pipeline.sh``): its root element is
``<MRML version="Slicer 5.6.1 32438" userTags="">`` (application, major.minor.patch, revision).
The warning rule is 3D Slicer's ``qSlicerSceneReader``: another application name, or a version
newer than the running one."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

import slicer  # noqa: E402

from comreg_plugin.logic import ComRegLogic  # noqa: E402
from comreg_plugin.scene_io import HEADLESS_SCENE_VERSION, sceneApplication  # noqa: E402

#: The root element of the real Slicer 5.6.1 scene (format facts only).
REAL_SLICER5_ROOT_ATTRIBUTES = {"version": "Slicer 5.6.1 32438", "userTags": ""}
#: "<application> <major>.<minor>.<patch> <revision>", the shape of that version string.
VERSION_FORM = re.compile(r"^(\S+) (\d+)\.(\d+)\.(\d+) (\d+)$")
#: Slicer 5 releases a user may open the scene with (oldest and the real scene's).
SLICER5_RELEASES = ("Slicer 5.0.0 0", "Slicer 5.6.1 32438")


def scene_version_warnings(loaded: str, running: str) -> list:
    """What 3D Slicer's scene reader would warn about (its two rules, reimplemented)."""
    loaded_app, loaded_version, _ = sceneApplication(loaded)
    running_app, running_version, _ = sceneApplication(running)
    warnings = []
    if loaded_app != running_app:
        warnings.append(f"saved with {loaded_app!r} (this is {running_app!r})")
    if loaded_version > running_version:
        warnings.append(f"saved with a newer version {loaded_version} > {running_version}")
    return warnings


def test_the_version_parser_reads_the_real_header_as_slicer_does():
    assert sceneApplication(REAL_SLICER5_ROOT_ATTRIBUTES["version"]) == ("Slicer", (5, 6, 1),
                                                                         32438)
    # slicer-core's default header is what Slicer 5 warns about
    assert scene_version_warnings(slicer.vtkMRMLScene().GetVersion(), SLICER5_RELEASES[1])
    assert sceneApplication("Slicer 5.0.0") == ("", (0, 0, 0), 0)  # no revision: unparsable


@pytest.fixture
def saved(tmp_path):
    """A small scene (points under a transform, the parameter node) saved headless."""
    logic = ComRegLogic()
    points = logic.addPointsModel(np.random.default_rng(0).normal(size=(20, 3)), "LPS")
    transform = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ReferenceToCT")
    points.SetAndObserveTransformNodeID(transform.GetID())
    logic.getParameterNode().usPoints = points
    return logic, logic.saveScene(tmp_path / "scene.mrml")


def test_the_saved_header_is_written_as_slicer5_writes_it(saved):
    _, path = saved
    root = ET.parse(path).getroot()
    assert root.tag == "MRML"
    assert set(root.attrib) == set(REAL_SLICER5_ROOT_ATTRIBUTES)
    assert root.attrib["userTags"] == REAL_SLICER5_ROOT_ATTRIBUTES["userTags"]
    version = root.attrib["version"]
    assert version == HEADLESS_SCENE_VERSION
    real = VERSION_FORM.match(REAL_SLICER5_ROOT_ATTRIBUTES["version"])
    ours = VERSION_FORM.match(version)
    assert ours and ours.group(1) == real.group(1) == "Slicer" and ours.group(2) == "5"
    for running in SLICER5_RELEASES:
        assert scene_version_warnings(version, running) == [], running


def test_a_reloaded_scene_remembers_the_header_and_keeps_its_classes(saved):
    logic, path = saved
    fresh = ComRegLogic(slicer.vtkMRMLScene())
    fresh.loadScene(path)
    assert fresh.scene.GetLastLoadedVersion() == HEADLESS_SCENE_VERSION
    # every element is MRML's own tag for the node's class, and the ids come back with them
    root = ET.parse(path).getroot()
    for element in root:
        node = fresh.scene.GetNodeByID(element.attrib["id"])
        assert node is not None, element.attrib["id"]
        assert fresh.scene.GetTagByClassName(node.GetClassName()) == element.tag
    tags = {element.tag for element in root}
    assert {"Model", "ModelDisplay", "ModelStorage", "LinearTransform",
            "ScriptedModule"} <= tags
    parameters = next(e for e in root if e.tag == "ScriptedModule")
    assert parameters.attrib["singletonTag"] == "ComReg"
    # the same scene saved again keeps the same header
    again = fresh.saveScene(path.parent / "again" / "scene.mrml")
    assert ET.parse(again).getroot().attrib == ET.parse(path).getroot().attrib
