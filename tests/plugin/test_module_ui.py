"""The module's panel in the scripted-module template's shape, checked headless: the Qt
Designer file ``Resources/UI/ComReg.ui`` parses, every parameter node field is bound to exactly
one widget (``SlicerParameterName``) of a class Slicer's ``connectGui`` can pair with the field's
type, the node selectors follow the scene, every widget the panel code uses exists, the
parameter node refuses values its validators do not allow, and the icon exists."""

from __future__ import annotations

import re
import types
import typing
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

from comreg_plugin import ComReg as module  # noqa: E402
from comreg_plugin.logic import ComRegLogic  # noqa: E402
from comreg_plugin.parameter_node import ComRegParameterNode  # noqa: E402
from comreg_plugin.registration import TRANSFORM_NODE_NAME  # noqa: E402
from comreg_plugin.slicer_compat import Choice, parameterTypes  # noqa: E402

RESOURCES = Path(module.__file__).parent / "Resources"
UI_FILE = RESOURCES / "UI" / "ComReg.ui"
ICON = RESOURCES / "Icons" / "ComReg.png"

#: Widget classes Slicer's parameterNodeWrapper GUI connectors pair with each value type
#: (slicer/parameterNodeWrapper/guiConnectors.py); a QComboBox needs a Choice validator.
CONNECTABLE = {bool: {"QCheckBox", "QPushButton"}, int: {"QSpinBox", "QSlider"},
               float: {"QDoubleSpinBox", "ctkSliderWidget"}, str: {"QLineEdit", "QTextEdit"}}


def _widgets():
    root = ET.parse(UI_FILE).getroot()
    return root, {w.attrib["name"]: w for w in root.iter("widget")}


def _property(widget, name):
    prop = widget.find(f"property[@name='{name}']")
    if prop is None:
        return None
    value = prop[0]
    return [s.text for s in value] if value.tag == "stringlist" else value.text


def test_the_ui_file_parses_as_a_slicer_module_panel():
    root, widgets = _widgets()
    assert root.tag == "ui" and root.find("class").text == "ComReg"
    top = root.find("widget")
    assert top.attrib == {"class": "qMRMLWidget", "name": "ComReg"}
    custom = {c.find("class").text for c in root.iter("customwidget")}
    used = {w.attrib["class"] for w in widgets.values()}
    assert {c for c in used if c.startswith(("q", "ctk")) and not c.startswith("Q")} <= custom


def test_every_parameter_is_bound_to_one_widget_of_a_connectable_class():
    _, widgets = _widgets()
    bound = {}
    for name, widget in widgets.items():
        prop = widget.find("property[@name='SlicerParameterName']")
        if prop is not None:
            assert prop.attrib.get("stdset") == "0", f"{name}: a dynamic property"
            parameter = prop.find("string").text
            assert parameter not in bound, f"'{parameter}' bound twice"
            bound[parameter] = widget
    hints = typing.get_type_hints(ComRegParameterNode, include_extras=True)
    assert set(bound) == set(ComRegParameterNode.allParameters) == set(hints)
    assert len(bound) == 34
    for parameter, widget in bound.items():
        kinds, validators, isNode = parameterTypes(hints[parameter])
        cls = widget.attrib["class"]
        if isNode:
            assert cls == "qMRMLNodeComboBox", parameter
            assert _property(widget, "nodeTypes") == [k.__name__ for k in kinds], parameter
        elif cls == "QComboBox":
            assert any(isinstance(v, Choice) for v in validators), f"{parameter}: no Choice"
        else:
            assert cls in CONNECTABLE[kinds[0]], f"{parameter}: {cls} for {kinds[0]}"
    # the template's choices: Choice for method and preset, ranges for the numbers
    for parameter in ("method", "preset", "device"):
        assert bound[parameter].attrib["class"] == "QComboBox"
    assert _property(bound["outputTransform"], "baseName") == TRANSFORM_NODE_NAME
    assert _property(bound["outputTransform"], "addEnabled") == "true"


def test_node_selectors_follow_the_scene_and_the_code_uses_only_existing_widgets():
    root, widgets = _widgets()
    selectors = {n for n, w in widgets.items()
                 if w.attrib["class"] in ("qMRMLNodeComboBox", "qMRMLCheckableNodeComboBox")}
    connected = {c.find("receiver").text for c in root.iter("connection")
                 if c.find("signal").text == "mrmlSceneChanged(vtkMRMLScene*)"
                 and c.find("slot").text == "setMRMLScene(vtkMRMLScene*)"}
    assert selectors == connected and len(selectors) == 11
    source = Path(module.__file__).read_text(encoding="utf-8")
    used = set(re.findall(r"\bui\.([A-Za-z]\w*)", source))
    assert used and used <= set(widgets), used - set(widgets)


def test_the_parameter_node_validators_refuse_bad_values():
    p = ComRegLogic().getParameterNode()
    p.method, p.preset, p.maxMinutes = "search", "paper", 5.0
    assert (p.method, p.preset, p.maxMinutes) == ("search", "paper", 5.0)
    for name, value in (("method", "magic"), ("preset", "huge"), ("maxMinutes", -1.0),
                        ("epochs", -2), ("seed", -1), ("pretrainingProgress", 1.5),
                        ("device", "tpu"), ("beamDirection", "up")):
        with pytest.raises(ValueError):
            setattr(p, name, value)
    assert p.method == "search"  # unchanged by the refused value


def test_the_icon_exists_where_slicer_looks_for_it():
    import vtk

    parent = types.SimpleNamespace(path=module.__file__)
    assert Path(module.ComReg(parent).resourcePath("Icons/ComReg.png")) == ICON
    assert ICON.stat().st_size < 10_000
    reader = vtk.vtkPNGReader()
    assert reader.CanReadFile(str(ICON))
    reader.SetFileName(str(ICON))
    reader.Update()
    image = reader.GetOutput()
    assert image.GetDimensions()[:2] == (64, 64) and image.GetNumberOfScalarComponents() == 4
