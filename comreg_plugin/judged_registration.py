"""The ComReg module's registration by the pose search or the network: ``comreg register``'s
own path, judged, and shown from its record.

:func:`registerJudged` registers one or several US points nodes (several sweeps in one
tracker frame: one rigid body) into a registration folder by
:func:`comreg_plugin.result_folder.registerIntoFolder` (``comreg register --out``), and
:func:`showJudged` shows what the folder's ``result.json`` says: the figures on the transform
node (:mod:`comreg_plugin.verdict_record`), the US points coloured by their distance to the CT,
the competing pose and the region to scan next (:mod:`comreg_plugin.result_views`).

Function names are camelCase, as in 3D Slicer modules.
"""

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

from comreg_core.transforms import apply_transform
from comreg_plugin import result_views
from comreg_plugin.bone_models import ATTRIBUTE_PREFIX
from comreg_plugin.result_folder import newRegistrationFolder, registerIntoFolder
from comreg_plugin.verdict_record import recordFigures, setFigureAttributes


@dataclass
class JudgedRegistration:
    """A registration made as ``comreg register`` makes it.

    Attributes:
        result: the :class:`~comreg_core.registration.search.result.RegistrationResult`.
        record: its ``result.json`` as read back from ``folder``.
        folder: the registration folder (``comreg register``'s files and ``inputs/``).
        figures: what the panel shows (:func:`comreg_plugin.verdict_record.recordFigures`;
            ``result_folder``: the folder's name, under the logic's registration folders).
        registrar: the :class:`~comreg_core.register.Registrar` it used.
        space: the CT's patient space of ``result`` ("LPS" unless the run says otherwise).
    """

    result: Any
    record: dict
    folder: Path
    figures: dict
    registrar: Any
    space: str

    def competitorPose(self) -> Optional[np.ndarray]:
        """``(4, 4)`` the competing pose the record names (its ``competitor``: its own
        ``T_ct_us``, else found by name among the search's refined candidates); None without
        one."""
        competitor = self.record.get("competitor") or {}
        if competitor.get("T_ct_us") is not None:
            return np.asarray(competitor["T_ct_us"], dtype=np.float64)
        candidates = getattr(getattr(self.result, "search", None), "candidates", ())
        for candidate in candidates:
            if competitor.get("name") is not None and candidate.name == competitor["name"]:
                return np.asarray(candidate.T_ct_us, dtype=np.float64)
        return None


def registerJudged(methods, usNodes: list, method: str, *, runDirectory, ctModelNode,
                   seed: int, device: str, prior, calibration, base) -> JudgedRegistration:
    """Register ``usNodes`` by ``method`` ("search": the pose search on ``ctModelNode``;
    "comreg": the run ``runDirectory``) into a new folder under ``base``; ``methods``: the
    logic's :class:`~comreg_plugin.registration.RegistrationMethods` (its prepared
    registrars); ``calibration``: the verdict's calibration file or None (the run's own)."""
    if method == "search":
        registrar, runDirectory = methods.searchRegistrar(ctModelNode), None
    else:
        registrar, ctModelNode = methods.registrar(runDirectory, device), None
    folder = newRegistrationFolder(base)
    result, record = registerIntoFolder(folder, usNodes, registrar, runDirectory=runDirectory,
                                        ctModelNode=ctModelNode, seed=seed, device=device,
                                        prior=prior, calibration=calibration)
    return JudgedRegistration(result, record, folder, recordFigures(record, folder.name),
                              registrar, registrar.space)


def showJudged(scene, judged: JudgedRegistration, usNodes: list, transformNode, ctModelNode,
               *, showCompetitor: bool = True) -> None:
    """Show ``judged`` in the scene: its figures on ``transformNode``, each US points node
    coloured by its distance to the CT, the competing pose (hidden unless
    ``showCompetitor``) and the patch to scan next on ``ctModelNode`` (when the record has
    one and the CT model is known)."""
    from comreg_plugin.scene_inputs import arrayFromPointsNode
    from comreg_core.transforms import space_change

    setFigureAttributes(transformNode, judged.figures)
    change = space_change("RAS", judged.space)
    joined = []
    for node in usNodes:
        points_us = apply_transform(change, arrayFromPointsNode(node))
        joined.append(points_us)
        if node.IsA("vtkMRMLModelNode"):
            distances = judged.registrar.surface.distance(
                apply_transform(judged.result.T_ct_us, points_us))
            result_views.colourByDistance(scene, node, distances)
    competitor = judged.competitorPose()
    node = result_views.showCompetitor(scene, np.vstack(joined), competitor, judged.space,
                                       showCompetitor)
    transformNode.SetAttribute(ATTRIBUTE_PREFIX + "competitor_T_ct_us", "" if competitor is None
                               else json.dumps(competitor.tolist()))
    if node is not None:
        node.SetAttribute(ATTRIBUTE_PREFIX + "competitor", judged.figures["competitor"]["name"])
    result_views.showScanNext(scene, ctModelNode, judged.figures.get("scan_next"),
                              judged.space)


def judgedOutput(judged: JudgedRegistration) -> tuple:
    """``(RegistrationOutput, T_ct_us, T_ct_us_ras, completion_ct)`` of ``judged``, as
    :func:`comreg_plugin.registration.runRegistration` gives them for other methods."""
    from comreg_core.evaluation.outputs import as_registration_output
    from comreg_core.transforms import space_change

    result = judged.result
    output = as_registration_output(result, result.runtime_s)
    output.info.pop("us_inputs", None)  # with absolute paths: the record and its folder have it
    T = np.asarray(result.T_ct_us, dtype=np.float64)
    C = space_change(judged.space, "RAS")
    completion = result.completion_ct
    if completion is not None and len(completion) == 0:
        completion = None
    return output, T, C @ T @ np.linalg.inv(C), completion
