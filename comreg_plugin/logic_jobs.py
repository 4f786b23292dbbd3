"""The ComReg module's background jobs, a part of :class:`comreg_plugin.logic.ComRegLogic`:
``comreg pretrain`` (:mod:`comreg_plugin.pretraining_job`) and ``comreg calibrate`` for the
verdict (:mod:`comreg_plugin.calibration_job`), each in its own process, polled from the GUI
and cancellable. Method names are camelCase, as in 3D Slicer modules."""

from pathlib import Path
from typing import Optional

from comreg_core.errors import ComRegError
from comreg_core.io._files import require_input_file
from comreg_core.registration.search.priors import prior_kind
from comreg_plugin.calibration_job import DEFAULT_SWEEPS, CalibrationJob, launchCalibration
from comreg_plugin.pretraining_job import (PretrainingJob, PretrainingStatus, checkRunFolder,
                                           launchPretraining)
from comreg_plugin.scene_inputs import priorFromNodes
from comreg_plugin.scene_io import requireNode, surfaceMeshFromModel


class JobsLogic:
    """The background jobs of the Logic (a mixin: it needs ``getParameterNode()``)."""

    pretrainingJob: Optional[PretrainingJob] = None
    calibrationJob: Optional[CalibrationJob] = None

    # -- pretraining ------------------------------------------------------------------------

    def startPretraining(self, ctModel=None, runDirectory=None, *, preset: Optional[str] = None,
                         maxMinutes: Optional[float] = None, epochs: Optional[int] = None,
                         seed: Optional[int] = None, device: Optional[str] = None,
                         config=None, resume: bool = False,
                         python: Optional[str] = None) -> PretrainingJob:
        """Start ``comreg pretrain`` in the background and return the :class:`PretrainingJob`.

        Args:
            ctModel: the CT bone model node (written to ``RUN_DIR/ct_bone.vtk``, LPS) or a mesh
                file path; default the parameter node's ``ctModel``.
            runDirectory: the run folder; default the parameter node's ``runDirectory``.
            preset, maxMinutes, epochs, seed, device: as ``comreg pretrain`` (defaults from the
                parameter node; ``epochs`` 0 = the preset's).
            config: YAML overrides file (or a dict, written to ``RUN_DIR/overrides.yaml``).
            resume: continue the run in ``runDirectory``.
            python: the Python to run ComReg with (default ``sys.executable``, which inside 3D
                Slicer is its PythonSlicer).

        Raises:
            ComRegError: another pretraining is running, no CT model, or the folder already
            holds a run (without ``resume``).
        """
        if self.pretrainingJob is not None and self.pretrainingJob.running:
            raise ComRegError("A pretraining is already running "
                              f"('{self.pretrainingJob.runDirectory}').",
                              "Wait for it to finish or cancel it first.")
        p = self.getParameterNode()
        runDirectory = runDirectory or p.runDirectory
        if not runDirectory:
            raise ComRegError("No run folder for the pretraining.",
                              "Choose an (empty) output folder.")
        runDirectory = checkRunFolder(runDirectory, resume)
        ctModel = ctModel if ctModel is not None else p.ctModel
        if ctModel is None:
            raise ComRegError("No CT bone model to pretrain on.",
                              "Load a CT segmentation or bone mesh first.")
        # every check before the run folder is made, so a refusal leaves nothing behind
        if isinstance(ctModel, (str, Path)):
            meshPath, mesh = require_input_file(ctModel, "CT mesh file"), None
        else:
            requireNode(ctModel, "vtkMRMLModelNode", "CT bone model",
                        "Pick the CT bone model (loaded from a segmentation or mesh).")
            meshPath, mesh = runDirectory / "ct_bone.vtk", surfaceMeshFromModel(ctModel)
        if config is not None and not isinstance(config, dict):
            require_input_file(config, "pretraining config")
        job = launchPretraining(
            mesh, meshPath, runDirectory, preset=preset or p.preset, device=device or p.device,
            maxMinutes=p.maxMinutes if maxMinutes is None else maxMinutes,
            epochs=(p.epochs or None) if epochs is None else epochs,
            seed=p.seed if seed is None else seed, config=config, resume=resume, python=python)
        self.pretrainingJob = job
        p.runDirectory = str(runDirectory)
        p.pretrainingState = "running"
        p.pretrainingProgress = 0.0
        return job

    def pollPretraining(self) -> PretrainingStatus:
        """The running (or last) pretraining's status, also stored in the parameter node."""
        if self.pretrainingJob is None:
            raise ComRegError("No pretraining was started.", "Start one first.")
        status = self.pretrainingJob.poll()
        p = self.getParameterNode()
        p.pretrainingState = status.state
        p.pretrainingProgress = status.progress
        if status.state == "finished":
            p.runDirectory = str(status.runDirectory)
        return status

    def cancelPretraining(self) -> PretrainingStatus:
        """Cancel the running pretraining (:meth:`PretrainingJob.cancel`)."""
        if self.pretrainingJob is None:
            raise ComRegError("No pretraining is running, so there is nothing to cancel.",
                              "Start a pretraining first.")
        self.pretrainingJob.cancel()
        return self.pollPretraining()

    # -- the verdict's calibration --------------------------------------------------------------

    def startCalibration(self, ctModel=None, outDirectory=None, *, sweeps: int = DEFAULT_SWEEPS,
                         seed: int = 0, lengths=(30.0, 80.0), prior: Optional[str] = None,
                         python: Optional[str] = None) -> CalibrationJob:
        """Start ``comreg calibrate`` for the verdict in the background on the CT bone model
        (default: the parameter node's ``ctModel``) into ``outDirectory`` (default: a
        ``verdict-calibration`` folder where registrations go), for registrations with a
        ``prior`` of that kind (default: the kind of the scene's prior, as registrations take
        it: landmarks, else an initial pose, else none); when it finishes,
        :meth:`pollCalibration` makes its ``calibration.json`` the parameter node's
        ``verdictCalibration``. Raises :class:`ComRegError` while one is running or without
        a CT model."""
        if self.calibrationJob is not None and self.calibrationJob.running:
            raise ComRegError("A verdict calibration is already running.",
                              "Wait for it to finish or cancel it first.")
        p = self.getParameterNode()
        ctModel = ctModel if ctModel is not None else p.ctModel
        if ctModel is None:
            raise ComRegError("No CT bone model to calibrate the verdict on.",
                              "Load a CT segmentation or bone mesh first.")
        requireNode(ctModel, "vtkMRMLModelNode", "CT bone model",
                    "Pick the CT bone model (loaded from a segmentation or mesh).")
        if outDirectory is None:
            outDirectory = Path(self.resultBase()) / "verdict-calibration"
        if prior is None:
            prior = prior_kind(priorFromNodes(parameters=p))
        job = launchCalibration(surfaceMeshFromModel(ctModel), Path(outDirectory),
                                sweeps=sweeps, seed=seed, lengths=lengths, prior=prior,
                                python=python)
        self.calibrationJob = job
        p.calibrationState, p.calibrationProgress = "running", 0.0
        return job

    def pollCalibration(self) -> PretrainingStatus:
        """The running (or last) calibration's status (``epoch``: sweeps done), also stored in
        the parameter node; once finished, its file judges the next registrations."""
        if self.calibrationJob is None:
            raise ComRegError("No verdict calibration was started.", "Start one first.")
        status = self.calibrationJob.poll()
        p = self.getParameterNode()
        p.calibrationState, p.calibrationProgress = status.state, status.progress
        if status.state == "finished":
            p.verdictCalibration = str(self.calibrationJob.calibrationPath)
        return status

    def cancelCalibration(self) -> PretrainingStatus:
        """Cancel the running verdict calibration (its folder keeps no calibration.json)."""
        if self.calibrationJob is None:
            raise ComRegError("No verdict calibration is running, so there is nothing to "
                              "cancel.", "Start one first.")
        self.calibrationJob.cancel()
        return self.pollCalibration()
