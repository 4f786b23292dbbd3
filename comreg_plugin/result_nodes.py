"""A registration's result in the scene.

- the output ``vtkMRMLLinearTransformNode`` (default name ``ReferenceToCT``): its to-parent
  matrix is ``T_ct_us`` in RAS, and the US points node is placed under it (:func:`showResult`);
- the completed bone, a model node of points in the CT frame (:func:`addCompletedBone`);
- the record of the registration: ``ComReg.*`` attributes on the transform node (``method``,
  ``runtime_s``, ``info``, ``run``, ``ambiguous``, ``confidence``) and the parameter node's
  result fields (:func:`recordResult`).

Function names are camelCase, as in 3D Slicer modules.
"""

from comreg_plugin.bone_models import ATTRIBUTE_PREFIX, addPointsModel
from comreg_plugin.registration import (COMPLETED_BONE_NODE_NAME, COMPLETION_COLOR,
                                        TRANSFORM_NODE_NAME, resultAttributes)
from comreg_plugin.scene_io import requireNode, uniqueName, vtkMatrixFromArray
from comreg_plugin.verdict_record import FIGURE_NAMES, setFigureAttributes


def outputNodes(parameters, outputTransformNode, completedBoneNode) -> tuple:
    """``(transformNode, completedBoneNode)`` a registration writes into: the given ones, else
    the parameter node's (``outputTransform``, ``completedBone``); None where a new node is to
    be made. Checked before the registration runs, not after."""
    transformNode = outputTransformNode if outputTransformNode is not None \
        else parameters.outputTransform
    if transformNode is not None:
        requireNode(transformNode, "vtkMRMLLinearTransformNode", "output transform",
                    "Pick a linear transform node for the result, or none for a new one.")
    completedBoneNode = completedBoneNode if completedBoneNode is not None \
        else parameters.completedBone
    if completedBoneNode is not None:
        requireNode(completedBoneNode, "vtkMRMLModelNode", "completed bone output",
                    "Pick a model node for the completed bone, or none for a new one.")
    return transformNode, completedBoneNode


def showResult(scene, transformNode, usPointsNode, T_ras):
    """Set ``T_ras`` ``(4, 4)`` as ``transformNode``'s to-parent matrix (None: a new
    ``ReferenceToCT`` node) and place ``usPointsNode`` under it; returns the transform node."""
    if transformNode is None:
        transformNode = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode",
                                                uniqueName(scene, TRANSFORM_NODE_NAME))
    transformNode.SetMatrixTransformToParent(vtkMatrixFromArray(T_ras))
    usPointsNode.SetAndObserveTransformNodeID(transformNode.GetID())
    return transformNode


def addCompletedBone(scene, completion_ct, space: str, node=None):
    """The completed bone ``(M, 3)`` (CT frame, in ``space``) as a model node of points (role
    ``completed_bone``; ``node`` updated in place if given), or None when there is none."""
    if completion_ct is None or not len(completion_ct):
        return None
    node = addPointsModel(scene, completion_ct, space, COMPLETED_BONE_NODE_NAME,
                          COMPLETION_COLOR, node)
    node.SetAttribute(ATTRIBUTE_PREFIX + "role", "completed_bone")
    return node


def recordResult(parameters, transformNode, usPointsNode, completedNode, output,
                 methodName: str, runDirectory) -> None:
    """Record a registration (its
    :class:`~comreg_core.evaluation.outputs.RegistrationOutput`) on the transform node
    (:func:`comreg_plugin.registration.resultAttributes`; ``info["ambiguous"]`` and
    ``info["confidence"]`` when the method gives them) and in the parameter node."""
    info = output.info
    for key, value in resultAttributes(output, methodName, runDirectory).items():
        transformNode.SetAttribute(ATTRIBUTE_PREFIX + key, value)
    parameters.outputTransform = transformNode
    parameters.usPoints = usPointsNode
    parameters.completedBone = completedNode
    parameters.runtimeSeconds = float(output.runtime_s)
    if "ambiguous" in info:
        parameters.ambiguous = bool(info["ambiguous"])
        transformNode.SetAttribute(ATTRIBUTE_PREFIX + "ambiguous",
                                   "true" if parameters.ambiguous else "false")
    if "confidence" in info and info["confidence"] is not None:
        parameters.confidence = float(info["confidence"])
        transformNode.SetAttribute(ATTRIBUTE_PREFIX + "confidence", repr(parameters.confidence))


def recordVerdict(parameters, transformNode, figures: dict) -> None:
    """The figures of a judged registration (:func:`comreg_plugin.verdict_record.recordFigures`;
    empty: not judged) on ``transformNode`` (every figure, none lingering from an earlier one;
    not judged: the method's own confidence and ambiguity kept) and its verdict, ``p_correct`` (-1: none) and uncertainty (mm; -1: none) in the parameter
    node."""
    setFigureAttributes(transformNode, figures, FIGURE_NAMES if figures else [
        name for name in FIGURE_NAMES if name not in ("confidence", "ambiguous")])  # the method's
    parameters.verdict = figures.get("verdict") or ""
    parameters.pCorrect = -1.0 if figures.get("p_correct") is None \
        else float(figures["p_correct"])
    parameters.uncertaintyMm = -1.0 if figures.get("uncertainty_mm") is None \
        else float(figures["uncertainty_mm"])
