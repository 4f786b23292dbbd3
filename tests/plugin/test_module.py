"""The module file in the 3D Slicer template's shape: imports headless without Qt, module
metadata, the typed parameter node, the Widget refusing to exist without the application, the
file loading as Slicer loads it, and the module's own self test (ComRegTest) run headless the way
Slicer's self-test runner runs it."""

from __future__ import annotations

import importlib.util
import sys
import types

import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

import slicer  # noqa: E402

from comreg_core.errors import ComRegError  # noqa: E402
from comreg_plugin import ComReg as module  # noqa: E402
from comreg_plugin.logic import ComRegLogic  # noqa: E402
from comreg_plugin.parameter_node import ComRegParameterNode  # noqa: E402
from comreg_plugin.slicer_compat import IN_SLICER_APP  # noqa: E402


def test_the_module_file_imports_headless_without_qt():
    assert not IN_SLICER_APP
    assert "qt" not in sys.modules and "ctk" not in sys.modules
    for name in ("ComReg", "ComRegParameterNode", "ComRegWidget", "ComRegLogic", "ComRegTest"):
        assert hasattr(module, name), name
    parent = types.SimpleNamespace(path=module.__file__)
    module.ComReg(parent)
    assert parent.title == "ComReg" and parent.categories == ["Registration"]
    assert "ultrasound" in parent.helpText


def test_the_module_file_loads_as_slicer_loads_it():
    # Slicer imports <folder>/ComReg.py as the top-level module "ComReg"
    spec = importlib.util.spec_from_file_location("ComReg", module.__file__)
    loaded = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(loaded)
    assert loaded.ComRegLogic is ComRegLogic and loaded.ComRegTest.__name__ == "ComRegTest"


def test_the_widget_needs_the_application():
    with pytest.raises(ComRegError, match="only inside the 3D Slicer application"):
        module.ComRegWidget()


def test_parameter_node_is_typed_and_saved_in_the_scene():
    logic = ComRegLogic()
    p = logic.getParameterNode()
    assert isinstance(p, ComRegParameterNode)
    assert p.method == "comreg" and p.preset == "cpu" and p.maxMinutes == 30.0
    assert p.epochs == 0 and p.ambiguous is False and p.confidence == -1.0 and p.usPoints is None
    p.maxMinutes, p.epochs, p.ambiguous, p.runDirectory = 2.5, 3, True, "/tmp/run"
    raw = p.parameterNode
    assert raw.IsA("vtkMRMLScriptedModuleNode") and raw.GetSingletonTag() == "ComReg"
    assert raw.GetParameter("maxMinutes") == "2.5" and raw.GetParameter("ambiguous") == "true"
    model = logic.scene.AddNewNodeByClass("vtkMRMLModelNode", "m")
    p.usPoints = model
    assert raw.GetNodeReferenceID("usPoints") == model.GetID()
    with pytest.raises(TypeError):
        p.outputTransform = model  # not a linear transform node
    assert set(ComRegParameterNode.allParameters) >= {"usPoints", "method", "maxMinutes"}
    # the same node (singleton) and values through a new wrapper
    q = logic.getParameterNode()
    assert q.parameterNode is raw and q.epochs == 3 and q.ambiguous is True
    assert q.usPoints is model and q.runDirectory == "/tmp/run"
    p.usPoints = None
    assert q.usPoints is None
    assert logic.scene.GetNumberOfNodesByClass("vtkMRMLScriptedModuleNode") == 1


def test_the_module_self_test_runs_headless(caplog):
    """ComRegTest builds its own data with a known transform and asserts mm/deg errors, transform
    files and a scene round trip; run through the module's runTest like Slicer's runner."""
    import logging

    caplog.set_level(logging.INFO, logger="comreg_plugin")
    parent = types.SimpleNamespace(path=module.__file__)
    module.ComReg(parent).runTest()
    messages = [r.getMessage() for r in caplog.records]
    assert any("Registration error" in m for m in messages)
    assert any("Test passed" in m for m in messages)
    assert any("Bad inputs give clear errors" in m for m in messages)
    print(next(m for m in messages if "Registration error" in m))
