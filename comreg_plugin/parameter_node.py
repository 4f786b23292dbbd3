"""The ComReg module's parameter node: its typed state, saved with the scene.

Defined apart from ``ComReg.py`` so that batch code can use :class:`ComRegLogic` without the
module file; ``ComReg.py`` re-exports it in the template's place. Decorated with Slicer's
``@parameterNodeWrapper`` inside the application, with the headless stand-in otherwise.
"""

from comreg_plugin.slicer_compat import parameterNodeWrapper, require_slicer

slicer = require_slicer()


@parameterNodeWrapper
class ComRegParameterNode:
    """The module's state, saved with the scene.

    segmentation: the CT segmentation. ctModel: the CT bone model registered to.
    usPoints: the US bone points (a model of vertices). outputTransform: US->CT (to parent, RAS).
    completedBone: the network's completed bone in the CT frame.
    method: "comreg" (pretrained run) or "ransac" (RANSAC + ICP baseline).
    runDirectory: the pretraining run folder. preset, maxMinutes, epochs (0 = preset's), seed,
    device: pretraining settings. pretrainingState: idle/running/finished/failed/cancelled;
    pretrainingProgress: 0..1. ambiguous, confidence (-1 = not reported), runtimeSeconds: of
    the last registration.
    """

    segmentation: slicer.vtkMRMLSegmentationNode
    ctModel: slicer.vtkMRMLModelNode
    usPoints: slicer.vtkMRMLModelNode
    outputTransform: slicer.vtkMRMLLinearTransformNode
    completedBone: slicer.vtkMRMLModelNode
    method: str = "comreg"
    runDirectory: str = ""
    preset: str = "cpu"
    maxMinutes: float = 30.0
    epochs: int = 0
    seed: int = 0
    device: str = "auto"
    pretrainingState: str = "idle"
    pretrainingProgress: float = 0.0
    ambiguous: bool = False
    confidence: float = -1.0
    runtimeSeconds: float = 0.0
