"""The ComReg module's parameter node: its typed state, saved with the scene.

Defined apart from ``ComReg.py`` so that batch code can use :class:`ComRegLogic` without the
module file; ``ComReg.py`` re-exports it in the template's place. Decorated with Slicer's
``@parameterNodeWrapper`` inside the application, with the headless stand-in otherwise.
"""

from typing import Annotated, Union

from comreg_core.choices import DEVICES, PRESETS
from comreg_core.surfaces.us_volume import BEAM_DIRECTIONS
from comreg_plugin.registration import METHODS
from comreg_plugin.slicer_compat import (Choice, Minimum, WithinRange, parameterNodeWrapper,
                                         require_slicer)

slicer = require_slicer()

#: Pretraining states (set by the Logic, shown read-only).
PRETRAINING_STATES = ("idle", "running", "finished", "failed", "cancelled")


@parameterNodeWrapper
class ComRegParameterNode:
    """The module's state, saved with the scene.

    sweep: the tracked US sweep (Sequence browser: frames + ImageToReference poses).
    segmentation: the CT segmentation. ctModel: the CT bone model registered to.
    usPoints: the US bone points (model vertices or markups control points).
    usVolume: a reconstructed 3D US volume (instead of a sweep); beamDirection: its beam,
    "auto" or a volume axis ("-y", ...).
    outputTransform: the result, tracking reference -> CT (to parent, RAS; "ReferenceToCT").
    completedBone: the network's completed bone in the CT frame.
    initialTransform: an optional rough initial pose, US -> CT, as the result is (to world,
    RAS); initialToleranceDeg, initialToleranceMm: how far the result may be from it (its
    rotation, and where it places the US points' centroid). ctLandmarks, usLandmarks: optional
    landmarks picked on the CT and in the US data (the US points' own frame), paired by label;
    landmarkToleranceMm: how far apart a pair may end (a point's "tol=5" description
    overrides it). Together the prior of the pose search
    (:mod:`comreg_core.registration.search.priors`).
    method: "comreg" (pretrained run), "search" (pose search on the CT alone, no network) or
    "ransac" (RANSAC + ICP baseline).
    runDirectory: the pretraining run folder. preset, maxMinutes, epochs (0 = preset's), seed,
    device: pretraining settings. pretrainingState: idle/running/finished/failed/cancelled;
    pretrainingProgress: 0..1. ambiguous, confidence (-1 = not reported), runtimeSeconds: of
    the last registration.
    verdictCalibration: the verdict's calibration.json ("": the run's own, if any).
    resultDirectory: where registrations write their folders ("": a temporary folder).
    showCompetitor: draw the competing pose. verdict ("ok"/"check"/""), pCorrect and
    uncertaintyMm (-1 = none): of the last judged registration. calibrationState,
    calibrationProgress: the background verdict calibration's, as the pretraining's.
    """

    sweep: slicer.vtkMRMLSequenceBrowserNode
    segmentation: slicer.vtkMRMLSegmentationNode
    ctModel: slicer.vtkMRMLModelNode
    usPoints: Union[slicer.vtkMRMLModelNode, slicer.vtkMRMLMarkupsFiducialNode]
    usVolume: slicer.vtkMRMLScalarVolumeNode
    beamDirection: Annotated[str, Choice(BEAM_DIRECTIONS)] = "auto"
    outputTransform: slicer.vtkMRMLLinearTransformNode
    completedBone: slicer.vtkMRMLModelNode
    initialTransform: slicer.vtkMRMLLinearTransformNode
    initialToleranceDeg: Annotated[float, WithinRange(0.1, 180.0)] = 30.0
    initialToleranceMm: Annotated[float, WithinRange(0.1, 1000.0)] = 30.0
    ctLandmarks: slicer.vtkMRMLMarkupsFiducialNode
    usLandmarks: slicer.vtkMRMLMarkupsFiducialNode
    landmarkToleranceMm: Annotated[float, WithinRange(0.1, 1000.0)] = 10.0
    method: Annotated[str, Choice(METHODS)] = "comreg"
    runDirectory: str = ""
    preset: Annotated[str, Choice(PRESETS)] = "cpu"
    maxMinutes: Annotated[float, WithinRange(0.0, 100000.0)] = 30.0
    epochs: Annotated[int, WithinRange(0, 100000)] = 0
    seed: Annotated[int, Minimum(0)] = 0
    device: Annotated[str, Choice(DEVICES)] = "auto"
    pretrainingState: Annotated[str, Choice(PRETRAINING_STATES)] = "idle"
    pretrainingProgress: Annotated[float, WithinRange(0.0, 1.0)] = 0.0
    ambiguous: bool = False
    confidence: Annotated[float, Minimum(-1.0)] = -1.0
    runtimeSeconds: Annotated[float, Minimum(0.0)] = 0.0
    verdictCalibration: str = ""
    resultDirectory: str = ""
    showCompetitor: bool = True
    verdict: str = ""
    pCorrect: Annotated[float, Minimum(-1.0)] = -1.0
    uncertaintyMm: Annotated[float, Minimum(-1.0)] = -1.0
    calibrationState: Annotated[str, Choice(PRETRAINING_STATES)] = "idle"
    calibrationProgress: Annotated[float, WithinRange(0.0, 1.0)] = 0.0
