"""The ComReg module's Logic: no GUI, batch-capable, on real MRML nodes.

``ComRegLogic(scene)`` works inside 3D Slicer (default scene: ``slicer.mrmlScene``) and headless
on slicer-core (default: a new ``vtkMRMLScene``). It checks its inputs and only calls
``comreg_core``: CT segmentation or bone mesh -> bone models, tracked US sweep, US volume or
point cloud -> US points (:mod:`comreg_plugin.bone_models`); ``comreg pretrain`` and ``comreg
calibrate`` in background processes (:mod:`comreg_plugin.logic_jobs`); registration ("search"
and "comreg" as ``comreg register --out``: :mod:`comreg_plugin.judged_registration`; others:
:mod:`comreg_plugin.registration`) -> the US->CT ``vtkMRMLLinearTransformNode`` (to parent,
RAS) with the US points under it, its verdict's figures and the completed bone
(:mod:`comreg_plugin.result_nodes`); the result folder and report; transform and scene files
(:mod:`comreg_plugin.scene_io`).

Coordinates: the scene is RAS (Slicer's convention); files are in the patient space they declare
(LPS unless tagged) and ComReg's library works in the CT's space (LPS by default). Every crossing
goes through :func:`comreg_core.transforms.space_change`.

Method names are camelCase here, as in 3D Slicer modules.
"""

import logging
from pathlib import Path
from typing import Optional

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.progress import Progress
from comreg_plugin import bone_models, result_nodes, result_views
from comreg_plugin.bone_models import (ATTRIBUTE_PREFIX, BONE_COLOR, US_POINTS_COLOR,
                                       US_POINTS_NODE_NAME)
from comreg_plugin.parameter_node import ComRegParameterNode
from comreg_plugin.logic_jobs import JobsLogic
from comreg_plugin.judged_registration import judgedOutput, registerJudged, showJudged
from comreg_plugin.registration import RegistrationMethods, RegistrationSummary, runRegistration
from comreg_plugin.result_folder import saveResultFolder, temporaryBase
from comreg_plugin.scene_io import addModelNode, readScene, requireNode, writeScene, writeTransform
from comreg_plugin.scene_inputs import (addSweepBrowser, arrayFromPointsNode, priorFromNodes,
                                        requirePointsNode, trackedSweepFromBrowser)
from comreg_plugin.slicer_compat import (IN_SLICER_APP, ScriptedLoadableModuleLogic,
                                         _StandInLogic, register_segmentation_converters,
                                         require_slicer, sequences_logic)

slicer = require_slicer()

log = logging.getLogger(__name__)


class ComRegLogic(ScriptedLoadableModuleLogic, JobsLogic):
    """All ComReg computations on MRML nodes, without GUI (batch-capable).

    Args:
        scene: the ``vtkMRMLScene`` to work in; default ``slicer.mrmlScene`` inside 3D Slicer,
            a new empty scene headless.
    """

    def __init__(self, scene=None):
        ScriptedLoadableModuleLogic.__init__(self)
        if scene is None:
            scene = slicer.mrmlScene if IN_SLICER_APP else slicer.vtkMRMLScene()
        self.scene = scene
        register_segmentation_converters()
        result_views.registerLegendClass(scene)
        self.sequencesLogic = sequences_logic(scene)
        self.pretrainingJob = self.calibrationJob = None  # JobsLogic's
        self._methods = RegistrationMethods()
        self._temporaryBase: Optional[Path] = None

    # -- parameter node ---------------------------------------------------------------------

    def getParameterNode(self) -> ComRegParameterNode:
        """The module's singleton parameter node in this logic's scene, typed."""
        # Slicer's base class looks in slicer.mrmlScene; this logic may own another scene.
        return ComRegParameterNode(_StandInLogic.getParameterNode(self))

    # -- nodes ------------------------------------------------------------------------------

    def addModel(self, points_ras: np.ndarray, faces: Optional[np.ndarray], name: str,
                 color=BONE_COLOR, pointSize: float = 3.0, node=None):
        """A model node (with display node) of RAS ``points`` and triangle ``faces`` (or of
        vertices only when ``faces`` is None); ``node`` is updated in place if given."""
        return addModelNode(self.scene, points_ras, faces, name, color, pointSize, node)

    def addBoneModel(self, mesh, name: str, color=BONE_COLOR):
        """A closed-surface model node of a :class:`~comreg_core.io.SurfaceMesh` (any space)."""
        return bone_models.addBoneModel(self.scene, mesh, name, color)

    def addPointsModel(self, points: np.ndarray, space: str, name: str = US_POINTS_NODE_NAME,
                       color=US_POINTS_COLOR, node=None):
        """A model node of vertices from ``(N, 3)`` points given in ``space``."""
        return bone_models.addPointsModel(self.scene, points, space, name, color, node)

    # -- CT ---------------------------------------------------------------------------------

    def loadSegmentation(self, path, segmentNames=None, options=None,
                         progress: Optional[Progress] = None) -> tuple:
        """Load a CT segmentation and make one closed-surface bone model per segment.

        Args:
            path: a label map (``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd``; each label value is a
                segment) or a 3D Slicer ``.seg.nrrd`` (read by Slicer's own storage node).
            segmentNames: only these segments get models (default: all).
            options: :class:`comreg_core.surfaces.ct.SurfaceExtractionOptions`.
            progress: ``progress(done, total, note)`` (:class:`comreg_core.progress.Progress`):
                reading, then one step per segment.

        Returns:
            ``(segmentationNode, [modelNode, ...])``; the first model becomes the parameter
            node's ``ctModel``.

        Raises:
            InputFileNotFoundError, UnsupportedFormatError, CorruptFileError,
            LabelNotFoundError, EmptyMaskError (from comreg_core).
        """
        segNode, models = bone_models.loadSegmentationModels(self.scene, path, segmentNames,
                                                             options, progress)
        self._useCT(segNode, models)
        return segNode, models

    def boneModelsFromSegmentation(self, segmentationNode=None, segmentNames=None, options=None,
                                   progress: Optional[Progress] = None) -> list:
        """Closed-surface bone models (one per segment, or per name in ``segmentNames``) of a
        segmentation node already in the scene (default: the parameter node's
        ``segmentation``), by the same extraction as :meth:`loadSegmentation`."""
        segmentationNode = segmentationNode if segmentationNode is not None \
            else self.getParameterNode().segmentation
        models = bone_models.segmentationNodeModels(self.scene, segmentationNode, segmentNames,
                                                    options, progress)
        self._useCT(segmentationNode, models)
        return models

    def _useCT(self, segNode, models) -> None:
        p = self.getParameterNode()
        p.segmentation = segNode
        if models:
            p.ctModel = models[0]

    def loadBoneMesh(self, path, name: Optional[str] = None):
        """Load a bone mesh file (``.stl``, ``.ply``, ``.obj``, ``.vtk``, ``.vtp``; LPS unless
        its ``SPACE=`` tag says otherwise) as the CT bone model."""
        model = bone_models.loadMeshModel(self.scene, path, name)
        self.getParameterNode().ctModel = model
        return model

    # -- US ---------------------------------------------------------------------------------

    def loadTrackedSweep(self, path, calibration=None, config=None, name=US_POINTS_NODE_NAME,
                         progress: Optional[Progress] = None) -> tuple:
        """Read a tracked US sweep, extract its bone surface points and add them as a model.

        Args:
            path: PLUS sequence (``.igs.mha``, ``.seq.nrrd``, ...), frame folder or Slicer volume
                sequence (:func:`comreg_core.io.read_tracked_sweep`).
            calibration: PLUS device-set XML or ``calibration.json`` (if not beside the data).
            config: :class:`comreg_core.surfaces.us_config.USExtractionConfig` or its YAML file.
            progress: ``progress(done_frames, total_frames, note)``.

        Returns:
            ``(pointsNode, USExtractionResult)``; the node becomes the parameter node's
            ``usPoints``.
        """
        node, result = bone_models.loadSweepPointsModel(self.scene, path, calibration, config,
                                                        name, progress)
        return self._useUSPoints(node), result

    def usPointsFromSequence(self, browserNode=None, imageSequence=None, transformSequence=None,
                             config=None, name=US_POINTS_NODE_NAME,
                             progress: Optional[Progress] = None) -> tuple:
        """Extract the bone surface points of a tracked sweep held in the scene as a Sequence
        browser (default: the parameter node's ``sweep``): frames from its volume sequence,
        poses from its ``ImageToReference`` transform sequence
        (:func:`comreg_plugin.scene_inputs.trackedSweepFromBrowser`); the points are in the
        tracking reference frame. Returns ``(pointsNode, USExtractionResult)``."""
        config = bone_models.extractionConfig(config)
        browserNode = browserNode if browserNode is not None else self.getParameterNode().sweep
        sweep = trackedSweepFromBrowser(browserNode, imageSequence, transformSequence)
        self.getParameterNode().sweep = browserNode
        node, result = bone_models.sweepPointsModel(self.scene, sweep, config, name,
                                                    browserNode.GetName(), progress)
        return self._useUSPoints(node), result

    def usPointsFromVolume(self, volumeNode, beamDirection: str = "auto", config=None,
                           name=US_POINTS_NODE_NAME, progress: Optional[Progress] = None
                           ) -> tuple:
        """Bone surface points of a reconstructed 3D US volume (a scalar volume node, e.g.
        from SlicerIGT's volume reconstruction;
        :func:`comreg_core.surfaces.us_volume.extract_volume_surface`): the beam ``"auto"`` or a
        voxel axis (``"-y"``, ...). Returns ``(pointsNode, USExtractionResult)``."""
        node, result = bone_models.volumePointsModel(self.scene, volumeNode, beamDirection,
                                                     config, name, progress)
        self.getParameterNode().usVolume = volumeNode
        return self._useUSPoints(node), result

    def addSweepSequence(self, path, calibration=None, name: str = "Sweep"):
        """Read a tracked sweep file or frame folder and show it as a Sequence browser (frames
        + ``ImageToReference`` poses), as a PLUS recording appears in Slicer; it becomes the
        parameter node's ``sweep``."""
        from comreg_core.io import read_tracked_sweep

        browser = addSweepBrowser(self.scene, self.sequencesLogic,
                                  read_tracked_sweep(path, calibration=calibration), name)
        self.getParameterNode().sweep = browser
        return browser

    def _useUSPoints(self, node):
        self.getParameterNode().usPoints = node
        return node

    def loadUSPoints(self, path, name=US_POINTS_NODE_NAME):
        """Load US bone points from a point cloud file (``.ply``, ``.pcd``, ``.xyz``, ``.npy``,
        ...; LPS unless tagged) as the parameter node's ``usPoints``."""
        return self._useUSPoints(bone_models.loadPointsModel(self.scene, path, name))

    # -- registration -----------------------------------------------------------------------

    def registrar(self, runDirectory, device: str = "auto"):
        """The :class:`comreg_core.register.Registrar` of a run folder (cached while its
        checkpoint is unchanged)."""
        return self._methods.registrar(runDirectory, device)

    def ransacBaseline(self, ctModelNode, seed: int = 0):
        """The RANSAC + ICP baseline prepared for a CT model node (cached while it is
        unchanged)."""
        return self._methods.ransacBaseline(ctModelNode, seed)

    def register(self, usPointsNode=None, method=None, *, runDirectory=None, ctModelNode=None,
                 outputTransformNode=None, completedBoneNode=None, seed: int = 0,
                 device: Optional[str] = None, initialTransformNode=None,
                 ctLandmarksNode=None, usLandmarksNode=None,
                 verdictCalibration=None) -> RegistrationSummary:
        """Register the US points to the CT, judge the result and show it in the scene.

        Args:
            usPointsNode: the US points model or markups (default: the parameter node's
                ``usPoints``), or a list of them and of Sequence browsers (their bone points
                are extracted first): several sweeps in one tracker frame, registered as one
                rigid body (``comreg register A B``); a node's own coordinates (without any
                parent transform) are the US frame.
            method: ``"comreg"`` (needs ``runDirectory``), ``"search"`` or ``"ransac"`` (need
                the CT model), or a callable taking ``(N, 3)`` LPS points and returning a
                result with ``T_ct_us``. Default: the parameter node's ``method``.
            runDirectory, ctModelNode: the pretrained run, the CT bone model (default: the
                parameter node's).
            outputTransformNode, completedBoneNode: where the result goes (default: the
                parameter node's, else new "ReferenceToCT" / "ComReg completed bone" nodes).
            seed: registration seed. device: torch device for "comreg".
            initialTransformNode, ctLandmarksNode, usLandmarksNode: the pose search's prior
                (:func:`comreg_plugin.scene_inputs.priorFromNodes`; default: the parameter
                node's, with its tolerances); ``info["prior"]`` says where the result lies.
            verdictCalibration: the verdict's ``calibration.json`` (default: the parameter
                node's, else the run's own): ``p_correct`` then.

        "comreg" and "search" register exactly as ``comreg register --out`` does, into a new
        registration folder (:mod:`comreg_plugin.judged_registration`; under the parameter
        node's ``resultDirectory``, else a temporary one): the summary's ``record`` is its
        ``result.json`` and the transform node carries its figures (``ComReg.verdict``,
        ``ComReg.p_correct``, ...: :mod:`comreg_plugin.verdict_record`). Sets ``T_ct_us`` as
        the output transform's to-parent matrix (RAS), places the US points under it, colours
        them by their distance to the CT and adds the completed bone, the competing pose and
        the patch to scan next when there are.
        """
        p = self.getParameterNode()
        usNodes = self._usPointsToRegister(usPointsNode, ctModelNode)
        transformNode, completedBoneNode = result_nodes.outputNodes(p, outputTransformNode,
                                                                    completedBoneNode)
        method = method if method is not None else p.method
        seed, device = int(seed), device or p.device
        prior = priorFromNodes(initialTransformNode, ctLandmarksNode, usLandmarksNode,
                               parameters=p)
        space, run, methodName, runDirectory = self._methods.prepare(
            method, p, runDirectory=runDirectory, ctModelNode=ctModelNode, seed=seed,
            device=device, prior=prior)
        ctModelNode = ctModelNode if ctModelNode is not None else p.ctModel
        judged = None
        if methodName in ("comreg", "search"):
            judged = registerJudged(self._methods, usNodes, methodName,
                                    runDirectory=runDirectory, ctModelNode=ctModelNode,
                                    seed=seed, device=device, prior=prior,
                                    calibration=verdictCalibration or p.verdictCalibration
                                    or None, base=self.resultBase())
        output, T, T_ras, completion_ct = judgedOutput(judged) if judged is not None else \
            runRegistration(run, np.vstack([arrayFromPointsNode(n) for n in usNodes]), space)
        for node in usNodes:
            transformNode = result_nodes.showResult(self.scene, transformNode, node, T_ras)
        completedNode = result_nodes.addCompletedBone(self.scene, completion_ct, space,
                                                      completedBoneNode)
        result_nodes.recordResult(p, transformNode, usNodes[0], completedNode, output,
                                  methodName, runDirectory)
        if judged is not None:
            showJudged(self.scene, judged, usNodes, transformNode, ctModelNode,
                       showCompetitor=p.showCompetitor)
        result_nodes.recordVerdict(p, transformNode, {} if judged is None else judged.figures)
        log.info("Registered %d node(s) with %s in %.3f s", len(usNodes), methodName,
                 output.runtime_s)
        return RegistrationSummary(transformNode, completedNode, T, T_ras, space, methodName,
                                   float(output.runtime_s), dict(output.info),
                                   None if judged is None else judged.record,
                                   None if judged is None else judged.figures,
                                   None if judged is None else judged.folder)

    def resultBase(self) -> Path:
        """Where registrations write their folders: the parameter node's ``resultDirectory``,
        else a temporary folder of this logic."""
        directory = self.getParameterNode().resultDirectory
        if directory:
            return Path(directory)
        if self._temporaryBase is None:
            self._temporaryBase = temporaryBase()
        return self._temporaryBase

    def _usPointsToRegister(self, usPointsNode, ctModelNode) -> list:
        """The US points nodes to register (the parameter node's unless given), checked with
        the CT model node when one is given."""
        usPointsNode = usPointsNode if usPointsNode is not None \
            else self.getParameterNode().usPoints
        nodes = list(usPointsNode) if isinstance(usPointsNode, (list, tuple)) else \
            [] if usPointsNode is None else [usPointsNode]
        if not nodes:
            raise ComRegError("There are no US points to register.",
                              "Load a tracked sweep or a US point cloud first.")
        if len({node.GetID() for node in nodes}) != len(nodes):
            raise ComRegError("A US points node was given twice.", "Give each sweep once.")
        for k, node in enumerate(nodes):
            if node.IsA("vtkMRMLSequenceBrowserNode"):  # a sweep: its bone points first
                nodes[k] = self.usPointsFromSequence(node, name=f"{node.GetName()} points")[0]
            requirePointsNode(nodes[k])
        if ctModelNode is not None:
            requireNode(ctModelNode, "vtkMRMLModelNode", "CT bone model",
                        "Pick the CT bone model (loaded from a segmentation or mesh).")
        return nodes

    # -- the registration's folder and report ------------------------------------------------

    def resultFolder(self, transformNode=None) -> Path:
        """The registration folder of ``transformNode`` (default: the parameter node's output
        transform): the one its ``ComReg.result_folder`` attribute names (a folder name: node
        attributes hold no absolute paths) under :meth:`resultBase`."""
        node = transformNode if transformNode is not None \
            else self.getParameterNode().outputTransform
        name = node.GetAttribute(ATTRIBUTE_PREFIX + "result_folder") if node else None
        if not name:
            raise ComRegError("This transform has no registration folder.",
                              "Register with the 'search' or 'comreg' method first.")
        folder = Path(self.resultBase()) / name
        if not (folder / "result.json").is_file():
            raise ComRegError(f"The registration folder '{folder}' is gone.",
                              "Register again, or open the folder saved from it.")
        return folder

    def saveResultFolder(self, path, transformNode=None) -> Path:
        """Save the registration as ``comreg register --out`` writes it (``result.json``,
        ``transform.tfm``, ``registered_us*.ply``, ``config.yaml``; a report if written),
        with the inputs the panel registered in ``inputs/``, into ``path``."""
        return saveResultFolder(self.resultFolder(transformNode), path)

    def writeReport(self, outDirectory=None, transformNode=None, embedImages: bool = False,
                    progress: Optional[Progress] = None) -> Path:
        """``comreg report`` of the registration (``report.html`` and its screenshots, rendered
        off-screen) in its folder, or in ``outDirectory`` after saving the folder there;
        returns the page's path."""
        from comreg_core.report import write_report_for_registration

        folder = self.resultFolder(transformNode)
        if outDirectory is not None:
            folder = saveResultFolder(folder, outDirectory)
        return write_report_for_registration(folder, embed_images=embedImages,
                                             progress=progress)

    def setCompetitorVisible(self, visible: bool) -> None:
        """Show or hide the competing pose (and keep the choice in the parameter node)."""
        self.getParameterNode().showCompetitor = bool(visible)
        node = result_views.roleNode(self.scene, "competitor")
        if node is not None and node.GetDisplayNode() is not None:
            node.GetDisplayNode().SetVisibility(bool(visible))

    # -- files ------------------------------------------------------------------------------

    def saveTransform(self, transformNode, path) -> Path:
        """Write a linear transform node as an ITK ``.tfm``/``.txt``/``.h5`` file, LPS, in ITK's
        resampling direction, exactly as 3D Slicer saves it (atomic write)."""
        if transformNode is None:
            raise ComRegError("There is no linear transform to save.", "Register first.")
        requireNode(transformNode, "vtkMRMLLinearTransformNode", "transform to save",
                    "Pick the registration's transform (register first).")
        return writeTransform(transformNode, path)

    def saveScene(self, path) -> Path:
        """Save the scene as a ``.mrml`` file with one data file per node beside it (written by
        the nodes' storage nodes: segmentations ``.seg.nrrd``, models ``.vtk`` with
        ``SPACE=LPS``, transforms ``.h5``), every file written atomically. 3D Slicer opens the
        ``.mrml`` (File > Add Data or drag and drop)."""
        return writeScene(self.scene, path)

    def loadScene(self, path):
        """Replace this logic's scene content with a saved ``.mrml`` scene (data files are read
        by their storage nodes). Returns the scene."""
        readScene(self.scene, path)
        self._methods.clear()
        return self.scene
