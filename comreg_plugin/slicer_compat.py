"""The scripted-module bases, inside 3D Slicer and headless on slicer-core's MRML.

Inside the 3D Slicer application (``slicer.app`` exists) this module re-exports Slicer's own
``ScriptedLoadableModule``, ``ScriptedLoadableModuleWidget``, ``ScriptedLoadableModuleLogic``,
``ScriptedLoadableModuleTest``, ``VTKObservationMixin``, ``parameterNodeWrapper`` and its
validators ``Choice``, ``WithinRange``, ``Minimum``.

Outside the application (pytest, batch scripts) it provides stand-ins with the same method names
on top of the real MRML classes of the ``slicer-core`` wheel (``import slicer`` gives
``slicer.vtkMRMLScene``, ``slicer.vtkMRMLModelNode``, ... but no ``slicer.app``, no
``slicer.mrmlScene`` and no Qt):

- ``ScriptedLoadableModule``: stores the metadata on ``parent``; ``runTest()`` finds
  ``<ModuleName>Test`` in the module and runs it, as Slicer's self-test runner does.
- ``ScriptedLoadableModuleLogic``: ``getParameterNode()`` / ``createParameterNode()`` with
  Slicer's semantics (a singleton ``vtkMRMLScriptedModuleNode`` tagged with the module name), on
  the logic's own scene ``self.scene`` instead of the global ``slicer.mrmlScene``.
- ``ScriptedLoadableModuleTest``: a ``unittest.TestCase``; ``delayDisplay`` logs,
  ``takeScreenshot`` does nothing, ``runTest()`` runs the ``test_*`` methods.
- ``ScriptedLoadableModuleWidget``: refuses to be built (a widget needs the application's Qt).
- ``parameterNodeWrapper``: typed attributes (``str``, ``int``, ``float``, ``bool``, optionally
  ``Annotated`` with the validators ``Choice`` / ``WithinRange`` / ``Minimum``, and MRML node
  classes or a ``Union`` of them, with class-level defaults) stored in a
  ``vtkMRMLScriptedModuleNode`` as parameters and node references, like Slicer's decorator (a
  subset of what it supports: no GUI binding, which needs Qt).
- ``sequences_logic(scene)``: the Sequences module's logic (registers the sequence browser node
  class in a headless scene).

Nothing here imports or fakes Qt.
"""

import importlib
import logging
import typing
import unittest

from comreg_core.errors import ComRegError

log = logging.getLogger(__name__)

#: The slicer-core release the headless plugin is tested with (it pins the same VTK as ComReg).
SLICER_CORE_REQUIREMENT = "slicer-core==5.13.31053.0"

try:
    import slicer
except ImportError as _exc:  # neither the application nor slicer-core
    slicer = None
    _SLICER_IMPORT_ERROR = _exc
else:
    _SLICER_IMPORT_ERROR = None

#: True inside the 3D Slicer application (it has ``slicer.app``); False headless.
IN_SLICER_APP = slicer is not None and hasattr(slicer, "app")


def require_slicer():
    """Return the ``slicer`` module (application or slicer-core), or raise :class:`ComRegError`
    saying how to install slicer-core."""
    if slicer is None or not hasattr(slicer, "vtkMRMLScene"):
        raise ComRegError(
            f"The ComReg Slicer module needs 3D Slicer's MRML classes, which cannot be imported "
            f"({_SLICER_IMPORT_ERROR or 'the slicer package has no vtkMRMLScene'}).",
            f"Run it inside 3D Slicer, or install the headless MRML library with "
            f"'python -m pip install {SLICER_CORE_REQUIREMENT}' (scripts/setup-env.sh does).")
    return slicer


def register_segmentation_converters() -> None:
    """Register Slicer's segmentation representation converters (binary labelmap <-> closed
    surface, fractional labelmap -> closed surface) once. The application's Segmentations module
    does this at start-up; slicer-core's factory starts empty. Rules already present are kept."""
    sl = require_slicer()
    factory = sl.vtkSegmentationConverterFactory.GetInstance()
    present = {rule.GetName() for rule in factory.GetConverterRules()}
    for rule_class in (sl.vtkBinaryLabelmapToClosedSurfaceConversionRule,
                       sl.vtkClosedSurfaceToBinaryLabelmapConversionRule,
                       sl.vtkClosedSurfaceToFractionalLabelmapConversionRule,
                       sl.vtkFractionalLabelmapToClosedSurfaceConversionRule):
        rule = rule_class()
        if rule.GetName() not in present:
            factory.RegisterConverterRule(rule)
            present.add(rule.GetName())


def sequences_logic(scene):
    """The Sequences module's logic for ``scene``: the application's own for
    ``slicer.mrmlScene``, otherwise a ``vtkSlicerSequencesLogic`` set to ``scene`` (which
    registers the sequence browser node class there, as the module does at start-up)."""
    sl = require_slicer()
    if IN_SLICER_APP and scene is sl.mrmlScene:  # pragma: no cover - application only
        return sl.modules.sequences.logic()
    logic = sl.vtkSlicerSequencesLogic()
    logic.SetMRMLScene(scene)
    return logic


# --------------------------------------------------------------------------------------------
# Headless stand-ins
# --------------------------------------------------------------------------------------------

class _StandInModule:
    """Headless ``ScriptedLoadableModule``: keeps the metadata on ``parent``."""

    def __init__(self, parent):
        self.parent = parent
        self.moduleName = self.__class__.__name__
        parent.title = ""
        parent.categories = []
        parent.dependencies = []
        parent.contributors = []
        parent.helpText = ""
        parent.acknowledgementText = ""

    def resourcePath(self, filename):
        import os

        return os.path.join(os.path.dirname(self.parent.path), "Resources", filename)

    def runTest(self, msec=0, **kwargs):
        """Find ``<ModuleName>Test`` in this module and run it (Slicer's self-test runner)."""
        module = importlib.import_module(self.__module__)
        className = self.moduleName + "Test"
        try:
            TestCaseClass = getattr(module, className)
        except AttributeError:
            raise AssertionError(f"Test case class not found: {self.__module__}.{className}")
        testCase = TestCaseClass()
        testCase.messageDelay = msec
        testCase.runTest(**kwargs)


class _StandInWidget:
    """Headless ``ScriptedLoadableModuleWidget``: a widget needs the application's Qt."""

    def __init__(self, parent=None):
        raise ComRegError(
            f"{type(self).__name__} is the module's Qt user interface and exists only inside "
            "the 3D Slicer application.",
            "Use the module's Logic class for batch or headless work.")


class _StandInLogic:
    """Headless ``ScriptedLoadableModuleLogic`` on ``self.scene`` (set by the subclass)."""

    scene = None

    def __init__(self, parent=None):
        self.moduleName = self.__class__.__name__
        if self.moduleName.endswith("Logic"):
            self.moduleName = self.moduleName[:-5]
        self.isSingletonParameterNode = True

    def getParameterNode(self):
        """The module's singleton ``vtkMRMLScriptedModuleNode`` in ``self.scene`` (created on
        first use), as Slicer's logic base class does with ``slicer.mrmlScene``."""
        scene = self.scene
        if self.isSingletonParameterNode:
            node = scene.GetSingletonNode(self.moduleName, "vtkMRMLScriptedModuleNode")
            if node:
                if node.GetAttribute("ModuleName") != self.moduleName:
                    node.SetAttribute("ModuleName", self.moduleName)
                return node
        else:
            for node in self.getAllParameterNodes():
                return node
        return scene.AddNode(self.createParameterNode())

    def getAllParameterNodes(self):
        scene = self.scene
        nodes = []
        for i in range(scene.GetNumberOfNodesByClass("vtkMRMLScriptedModuleNode")):
            node = scene.GetNthNodeByClass(i, "vtkMRMLScriptedModuleNode")
            if node.GetAttribute("ModuleName") == self.moduleName:
                nodes.append(node)
        return nodes

    def createParameterNode(self):
        scene = self.scene
        node = scene.CreateNodeByClass("vtkMRMLScriptedModuleNode")
        node.UnRegister(None)  # the Python variable owns it
        if self.isSingletonParameterNode:
            node.SetSingletonTag(self.moduleName)
        node.SetAttribute("ModuleName", self.moduleName)
        node.SetName(scene.GenerateUniqueName(self.moduleName))
        return node


class _StandInTest(unittest.TestCase):
    """Headless ``ScriptedLoadableModuleTest``: messages go to the log."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.enableScreenshots = False
        self.screenshotScaleFactor = 1.0

    def delayDisplay(self, message, requestedDelay=None, msec=None):
        log.info("%s: %s", type(self).__name__, message)

    def takeScreenshot(self, name, description, type=-1):
        self.delayDisplay(description)

    def runTest(self):
        """Run every ``test_*`` method (``setUp`` before each)."""
        for name in sorted(n for n in dir(self) if n.startswith("test_")):
            self.setUp()
            try:
                getattr(self, name)()
            finally:
                self.tearDown()


class _StandInObservationMixin:
    """``VTKObservationMixin`` (``addObserver`` / ``removeObserver(s)``) without Slicer."""

    def __init__(self):
        self.Observations = []

    def addObserver(self, obj, event, method, group="none", priority=0.0):
        tag = obj.AddObserver(event, method, priority)
        self.Observations.append((obj, event, method, group, tag, priority))

    def removeObserver(self, obj, event, method):
        for entry in list(self.Observations):
            if entry[0] is obj and entry[1] == event and entry[2] == method:
                obj.RemoveObserver(entry[4])
                self.Observations.remove(entry)

    def removeObservers(self, method=None):
        for entry in list(self.Observations):
            if method is None or entry[2] == method:
                entry[0].RemoveObserver(entry[4])
                self.Observations.remove(entry)


_NO_DEFAULT = object()
_SCALARS = (bool, int, float, str)


class Choice:
    """Validator (Slicer's ``parameterNodeWrapper.Choice``): the value is one of ``choices``."""

    def __init__(self, choices):
        self.choices = tuple(choices)

    def validate(self, value) -> None:
        if value not in self.choices:
            raise ValueError(f"{value!r} is not one of {list(self.choices)}")


class WithinRange:
    """Validator (Slicer's ``parameterNodeWrapper.WithinRange``): ``minimum <= value <=
    maximum``."""

    def __init__(self, minimum, maximum):
        self.minimum, self.maximum = minimum, maximum

    def validate(self, value) -> None:
        if not self.minimum <= value <= self.maximum:
            raise ValueError(f"{value!r} is not within [{self.minimum}, {self.maximum}]")


class Minimum:
    """Validator (Slicer's ``parameterNodeWrapper.Minimum``): ``value >= minimum``."""

    def __init__(self, minimum):
        self.minimum = minimum

    def validate(self, value) -> None:
        if value < self.minimum:
            raise ValueError(f"{value!r} is less than {self.minimum}")


def _format(value, kind) -> str:
    if kind is bool:
        return "true" if value else "false"
    if kind is float:
        return repr(float(value))
    return str(kind(value))


def _parse(text: str, kind):
    if kind is bool:
        return text.strip().lower() in ("true", "1", "yes")
    return kind(text)


def parameterTypes(annotation) -> tuple:
    """``(types, validators, isNode)`` of a parameter annotation: ``Annotated[T, v, ...]``
    unwrapped, ``Union[NodeA, NodeB]`` as ``(NodeA, NodeB)``."""
    validators = []
    if typing.get_origin(annotation) is typing.Annotated:
        annotation, *extras = typing.get_args(annotation)
        validators = [v for v in extras if hasattr(v, "validate")]
    kinds = typing.get_args(annotation) if typing.get_origin(annotation) is typing.Union \
        else (annotation,)
    isNode = all(isinstance(k, type) and slicer is not None and issubclass(k, slicer.vtkMRMLNode)
                 for k in kinds)
    return tuple(kinds), validators, isNode


def _standin_parameter_node_wrapper(cls):
    """Typed access to a ``vtkMRMLScriptedModuleNode``: each annotated attribute is a parameter
    (``str``/``int``/``float``/``bool``, optionally ``Annotated`` with validators such as
    :class:`Choice` or :class:`WithinRange`) or a node reference (a ``vtkMRMLNode`` subclass or
    a ``Union`` of them); a class-level value is the default. ``cls(parameterNode)`` wraps the
    node; the node is ``.parameterNode``. A value a validator refuses raises ValueError."""
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = {}
    for name, annotation in hints.items():
        if name.startswith("_"):
            continue
        default = cls.__dict__.get(name, _NO_DEFAULT)
        kinds, validators, is_node = parameterTypes(annotation)
        if not is_node and (len(kinds) != 1 or kinds[0] not in _SCALARS):
            raise TypeError(f"{cls.__name__}.{name}: unsupported parameter type {annotation!r}")
        kind = kinds if is_node else kinds[0]
        if default is not _NO_DEFAULT:
            for validator in validators:
                validator.validate(default)
        fields[name] = (kind, default, is_node, validators)

    def make_property(name, kind, default, is_node, validators):
        if is_node:
            def getter(self):
                return self.parameterNode.GetNodeReference(name)

            def setter(self, value):
                if value is not None and not isinstance(value, kind):
                    raise TypeError(f"{cls.__name__}.{name} must be a "
                                    f"{' or '.join(k.__name__ for k in kind)}, "
                                    f"not {type(value).__name__}")
                self.parameterNode.SetNodeReferenceID(name, value.GetID() if value else None)
        else:
            def getter(self):
                node = self.parameterNode
                if node.HasParameter(name):
                    return _parse(node.GetParameter(name), kind)
                return None if default is _NO_DEFAULT else default

            def setter(self, value):
                for validator in validators:
                    validator.validate(kind(value))
                self.parameterNode.SetParameter(name, _format(value, kind))
        return property(getter, setter, doc=f"{name}: {getattr(kind, '__name__', kind)}")

    def __init__(self, parameterNode):
        self.parameterNode = parameterNode
        for name, (kind, default, is_node, _) in fields.items():
            if not is_node and default is not _NO_DEFAULT and not parameterNode.HasParameter(name):
                parameterNode.SetParameter(name, _format(default, kind))

    for name, (kind, default, is_node, validators) in fields.items():
        setattr(cls, name, make_property(name, kind, default, is_node, validators))
    cls.__init__ = __init__
    # the same names as Slicer's wrapper (class-level parameter table, node pass-throughs)
    cls.allParameters = {name: hints[name] for name in fields}
    cls.StartModify = lambda self: self.parameterNode.StartModify()
    cls.EndModify = lambda self, wasModified: self.parameterNode.EndModify(wasModified)
    cls.AddObserver = lambda self, event, callback, priority=0.0: \
        self.parameterNode.AddObserver(event, callback, priority)
    cls.RemoveObserver = lambda self, tag: self.parameterNode.RemoveObserver(tag)
    cls.Modified = lambda self: self.parameterNode.Modified()
    return cls


if IN_SLICER_APP:  # pragma: no cover - only inside the 3D Slicer application
    from slicer.ScriptedLoadableModule import (ScriptedLoadableModule,
                                               ScriptedLoadableModuleLogic,
                                               ScriptedLoadableModuleTest,
                                               ScriptedLoadableModuleWidget)
    from slicer.util import VTKObservationMixin

    try:
        from slicer.parameterNodeWrapper import (Choice, Minimum, WithinRange,  # noqa: F811
                                                 parameterNodeWrapper)
    except ImportError:  # Slicer before 5.2
        parameterNodeWrapper = _standin_parameter_node_wrapper
else:
    ScriptedLoadableModule = _StandInModule
    ScriptedLoadableModuleWidget = _StandInWidget
    ScriptedLoadableModuleLogic = _StandInLogic
    ScriptedLoadableModuleTest = _StandInTest
    VTKObservationMixin = _StandInObservationMixin
    parameterNodeWrapper = _standin_parameter_node_wrapper

__all__ = [
    "Choice", "IN_SLICER_APP", "Minimum", "SLICER_CORE_REQUIREMENT", "ScriptedLoadableModule",
    "ScriptedLoadableModuleLogic", "ScriptedLoadableModuleTest", "ScriptedLoadableModuleWidget",
    "VTKObservationMixin", "WithinRange", "parameterNodeWrapper", "parameterTypes",
    "register_segmentation_converters", "require_slicer", "sequences_logic", "slicer",
]
