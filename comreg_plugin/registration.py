"""Registration methods of the ComReg module and what a registration made.

- :class:`RegistrationMethods`: the methods :meth:`comreg_plugin.logic.ComRegLogic.register`
  runs: ``"comreg"`` (a pretrained run folder, :class:`comreg_core.register.Registrar`),
  ``"search"`` (the pose search alone on the CT model, no network:
  :meth:`comreg_core.register.Registrar.from_ct`), ``"ransac"`` (the Open3D RANSAC + ICP
  baseline on the CT model) or any callable; each is prepared once and reused while its inputs
  are unchanged.
- :func:`runRegistration`: one method on ``(N, 3)`` RAS points -> ``T_ct_us`` in its space and
  in RAS.
- :class:`RegistrationSummary`: the nodes and numbers a registration left in the scene.
"""

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.transforms import apply_transform, check_rigid, space_change
from comreg_plugin.pretraining_job import PretrainingJob
from comreg_plugin.scene_io import arraysFromModelMesh, requireNode

#: Default name of the output transform, SlicerIGT style ``<From>To<To>``: it maps the tracking
#: reference frame, in which the US points (and the sweep's ImageToReference poses) are given,
#: to the CT.
TRANSFORM_NODE_NAME = "ReferenceToCT"
COMPLETED_BONE_NODE_NAME = "ComReg completed bone"
COMPLETION_COLOR = (0.2, 0.8, 0.3)
METHODS = ("comreg", "search", "ransac")


@dataclass
class RegistrationSummary:
    """What :meth:`ComRegLogic.register` made.

    Attributes:
        transformNode: the US->CT ``vtkMRMLLinearTransformNode`` (to parent, RAS).
        completedBoneNode: the completed bone model (CT frame), or None (method without one).
        T_ct_us: ``(4, 4)`` the estimate as the library returned it (in ``space``).
        T_ct_us_ras: ``(4, 4)`` the same in RAS (= the node's to-parent matrix).
        space: the patient space the method worked in ("LPS" unless the run says otherwise).
        method: "comreg", "ransac" or the callable's name.
        runtimeSeconds: the method's own registration time.
        info: the method's extras (residuals, fitness, "ambiguous", "confidence", ...).
        record: ``result.json`` of a registration made as ``comreg register`` makes it
            ("comreg", "search"), None for other methods.
        figures: what the panel shows of it (:mod:`comreg_plugin.verdict_record`), or None.
        resultFolder: its registration folder, or None.
    """

    transformNode: Any
    completedBoneNode: Any
    T_ct_us: np.ndarray
    T_ct_us_ras: np.ndarray
    space: str
    method: str
    runtimeSeconds: float
    info: dict = field(default_factory=dict)
    record: Optional[dict] = None
    figures: Optional[dict] = None
    resultFolder: Optional[Path] = None

    def describe(self, ambiguous: bool, confidence: float) -> str:
        """One line for the user: method, runtime (s), median distance to the CT (mm), the
        ambiguity warning, confidence, the completed bone; ``ambiguous`` and ``confidence``
        (-1 = none) as the parameter node holds them."""
        text = f"{self.method}: {self.runtimeSeconds:.2f} s"
        residuals = self.info.get("residuals_mm") or {}
        if "median" in residuals:
            text += f", median distance to CT {residuals['median']:.2f} mm"
        if "ambiguous" in self.info and ambiguous:
            from comreg_core.registration.judgement.verdict import competitor_ruled_out

            competitor = ((self.record or {}).get("uncertainty") or {}).get("competitor")
            text += (", a close pose ruled out by the fit" if competitor_ruled_out(competitor)
                     else ", AMBIGUOUS (check the pose)")
        prior = self.info.get("prior") or {}
        if prior.get("reasons"):
            text += ", CHECK: " + " ".join(prior["reasons"])
        if confidence >= 0:
            text += f", confidence {confidence:.2f}"
        if self.completedBoneNode is not None:
            text += f"; '{COMPLETED_BONE_NODE_NAME}' added"
        if self.figures is not None:
            from comreg_plugin.verdict_record import describeFigures

            text += "\n" + "\n".join(describeFigures(self.figures))
        return text


class RegistrationMethods:
    """The registration methods of one logic, each prepared once: a Registrar per run folder
    and device (while its checkpoint is unchanged), the RANSAC + ICP baseline of the last CT
    model (while it is unchanged)."""

    def __init__(self):
        self._registrars: dict = {}
        self._baselines: dict = {}

    def clear(self) -> None:
        """Forget every prepared method (the scene was replaced)."""
        self._registrars.clear()
        self._baselines.clear()

    def registrar(self, runDirectory, device: str = "auto"):
        """The :class:`comreg_core.register.Registrar` of a run folder (cached while its
        checkpoint is unchanged)."""
        from comreg_core.register import Registrar

        run = Path(runDirectory)
        checkpoint = run / PretrainingJob.CHECKPOINT_NAME if run.is_dir() else run
        key = (str(run.resolve()), device)
        stamp = checkpoint.stat().st_mtime_ns if checkpoint.is_file() else None
        cached = self._registrars.get(key)
        if cached is None or cached[0] != stamp or stamp is None:
            self._registrars[key] = (stamp, Registrar.from_run(run, device))
        return self._registrars[key][1]

    def ransacBaseline(self, ctModelNode, seed: int = 0):
        """The RANSAC + ICP baseline prepared for a CT model node (cached while it is
        unchanged)."""
        from comreg_core.evaluation.baselines import RansacIcpBaseline

        return self._onCtModel("ransac", ctModelNode, seed,
                               lambda mesh: RansacIcpBaseline(mesh, seed=seed))

    def searchRegistrar(self, ctModelNode):
        """The pose search alone (:meth:`comreg_core.register.Registrar.from_ct`) prepared for
        a CT model node (cached while it is unchanged)."""
        from comreg_core.register import Registrar

        return self._onCtModel("search", ctModelNode, 0, Registrar.from_ct)

    def _onCtModel(self, kind: str, ctModelNode, seed: int, build):
        """``build((vertices, faces))`` of the CT model in LPS mm, cached per kind while the
        model (and seed) is unchanged."""
        requireNode(ctModelNode, "vtkMRMLModelNode", "CT bone model",
                    "Pick the CT bone model (loaded from a segmentation or mesh).")
        polydata = ctModelNode.GetPolyData()
        key = (kind, ctModelNode.GetID(), polydata.GetMTime() if polydata else 0, int(seed))
        if key not in self._baselines:
            vertices, faces = arraysFromModelMesh(ctModelNode)
            lps = apply_transform(space_change("RAS", "LPS"), vertices)
            self._baselines = {k: v for k, v in self._baselines.items() if k[0] != kind}
            self._baselines[key] = build((lps, faces))
        return self._baselines[key]

    def prepare(self, method, parameters, *, runDirectory, ctModelNode, seed: int,
                device: str, prior=None) -> tuple:
        """``(space, run, name, runDirectory)`` of ``method`` ("comreg", "ransac" or a callable,
        see :meth:`ComRegLogic.register <comreg_plugin.logic.ComRegLogic.register>`): ``run``
        takes ``(N, 3)`` points in ``space`` and returns a result with ``T_ct_us``.
        ``runDirectory`` and ``ctModelNode`` default to the ``parameters`` node's. ``prior``
        (:class:`~comreg_core.registration.search.priors.Prior`, or None) goes to the pose search of
        "comreg" and "search"; the other methods refuse it."""
        if prior is not None and (callable(method) or method == "ransac"):
            name = getattr(method, "__name__", "custom") if callable(method) else method
            raise ComRegError(f"The '{name}' method cannot use an initial pose or landmarks.",
                              "Use the 'comreg' or 'search' method, or clear the prior.")
        if callable(method):
            space, run = "LPS", method
            methodName = getattr(method, "name", getattr(method, "__name__", "custom"))
        elif method == "comreg":
            runDirectory = runDirectory or parameters.runDirectory
            if not runDirectory:
                raise ComRegError("No pretrained run folder to register with.",
                                  "Pretrain on this CT first, or choose the run folder.")
            registrar = self.registrar(runDirectory, device)
            space, methodName = registrar.space, "comreg"

            def run(points):
                return registrar.register(points, seed=seed, prior=prior)
        elif method in ("ransac", "search"):
            ctModelNode = ctModelNode if ctModelNode is not None else parameters.ctModel
            if ctModelNode is None:
                raise ComRegError(f"The '{method}' method needs the CT bone model.",
                                  "Load a CT segmentation or bone mesh first.")
            if method == "ransac":
                baseline = self.ransacBaseline(ctModelNode, seed)
                baseline.reseed(seed)
                space, run, methodName = "LPS", baseline, "ransac"
            else:
                registrar = self.searchRegistrar(ctModelNode)
                space, methodName = "LPS", "search"

                def run(points):
                    return registrar.register(points, seed=seed, prior=prior)
        else:
            raise ComRegError(f"Unknown registration method '{method}'.",
                              f"Use one of: {', '.join(METHODS)}, or pass a callable.")
        return space, run, methodName, runDirectory


def runRegistration(run, points_ras: np.ndarray, space: str) -> tuple:
    """Run a prepared method on ``(N, 3)`` RAS points taken to ``space``.

    Returns ``(output, T_ct_us, T_ct_us_ras, completion_ct)``: the
    :class:`~comreg_core.evaluation.outputs.RegistrationOutput` (its runtime is the call's own),
    the rigid ``(4, 4)`` estimate in ``space`` and in RAS, and the completed bone ``(M, 3)`` in
    the CT frame (``space``) or None.
    """
    from comreg_core.evaluation.outputs import as_registration_output

    points = apply_transform(space_change("RAS", space), points_ras)
    start = time.perf_counter()
    raw = run(points)
    output = as_registration_output(raw, time.perf_counter() - start)
    T = check_rigid(output.T_ct_us)
    C = space_change(space, "RAS")
    T_ras = C @ T @ np.linalg.inv(C)
    completion_ct = getattr(raw, "completion_ct", None)
    if completion_ct is None and output.completion is not None:
        completion_ct = apply_transform(T, output.completion)
    if completion_ct is not None and len(completion_ct) == 0:  # a method without a completion
        completion_ct = None
    return output, T, T_ras, completion_ct


def resultAttributes(output, methodName: str, runDirectory) -> dict:
    """The transform node attributes (names without the ``ComReg.`` prefix) that record a
    registration: ``method``, ``runtime_s``, ``info`` (JSON), and for "comreg" ``run`` (the run
    folder's name, not its path: a saved scene moves between machines). The node itself is RAS,
    like every Slicer transform node."""
    attributes = {"method": methodName, "runtime_s": f"{output.runtime_s:.6g}",
                  "info": json.dumps(dict(output.info), default=_jsonable)}
    if methodName == "comreg":
        attributes["run"] = Path(runDirectory).name
    return attributes


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    return str(value)
