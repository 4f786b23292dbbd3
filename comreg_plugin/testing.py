"""Small test data with a known transform and the checks on it, shared by the module's in-Slicer
self test (``ComRegTest``) and the headless pytest suite (``tests/plugin``).

:func:`buildSyntheticCase` makes, from the bundled sample CT segmentation
(``resources/sample/fibula.seg.nrrd``) only, a US bone point cloud with a known ``T_ct_us``: it
extracts the CT bone surface, simulates one freehand US sweep of it (ray casting, first hits,
the paper's perturbations) and moves the points into a "US frame" by the inverse of a fixed rigid
transform. The checks compare the scene's transform node with that ground truth in millimetres
and degrees (scipy's ``Rotation`` as the independent reference) and compare two scenes node by
node.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from comreg_core.transforms import T_RAS_LPS, apply_transform, invert_rigid

#: The bundled sample CT segmentation (CC BY 4.0 fibula, see resources/).
SAMPLE_SEGMENTATION = Path(__file__).resolve().parents[1] / "resources" / "sample" / \
    "fibula.seg.nrrd"
#: The bundled sample's tracked sweep (frame folder, its tracking in the CT frame).
SAMPLE_SWEEP = SAMPLE_SEGMENTATION.parent / "sweep"
#: Rotation (xyz Euler angles, degrees) and translation (mm) of the ground truth ``T_ct_us``.
KNOWN_EULER_DEG = (20.0, -35.0, 50.0)
KNOWN_TRANSLATION_MM = (30.0, -20.0, 15.0)
#: Registration must land within these of the ground truth.
MAX_TRANSLATION_ERROR_MM = 2.0
MAX_ROTATION_ERROR_DEG = 2.0


@dataclass
class SyntheticCase:
    """A CT segmentation and US points with a known transform (LPS, mm).

    Attributes:
        segmentationPath: the CT segmentation file.
        usPointsPath: the US points (``.ply`` tagged LPS) in the US frame.
        T_ct_us: ``(4, 4)`` ground truth, LPS: ``T_ct_us @ p_us = p_ct``.
        ctMesh: the CT bone surface (:class:`comreg_core.io.SurfaceMesh`, LPS).
        usPointsCT: ``(N, 3)`` the simulated points in the CT frame (LPS).
        usPoints: ``(N, 3)`` the same points in the US frame (what the file holds).
    """

    segmentationPath: Path
    usPointsPath: Path
    T_ct_us: np.ndarray
    ctMesh: object
    usPointsCT: np.ndarray
    usPoints: np.ndarray


def knownTransform(center=None) -> np.ndarray:
    """The ground-truth ``T_ct_us`` (rotation about ``center``, then the translation)."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", KNOWN_EULER_DEG, degrees=True).as_matrix()
    c = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64)
    T[:3, 3] = c - T[:3, :3] @ c + np.asarray(KNOWN_TRANSLATION_MM)
    return T


def buildSyntheticCase(workDir, segmentation=SAMPLE_SEGMENTATION, seed: int = 0,
                       nPoints: int = 20000) -> SyntheticCase:
    """Write the US points of one simulated sweep, moved by the known transform, to ``workDir``.

    Raises ComRegError (from comreg_core) when the segmentation is missing or unusable.
    """
    from comreg_core.io import read_segmentation
    from comreg_core.io.pointclouds import PointCloud, write_points
    from comreg_core.simulation import BoneModel, SimulationConfig, simulate_sweep
    from comreg_core.surfaces.ct import extract_bone_surface

    seg = read_segmentation(segmentation)
    mesh = extract_bone_surface(seg, segment=seg.segments[0]).in_space("LPS")
    bone = BoneModel(mesh)
    sweep = simulate_sweep(bone, SimulationConfig(n_points=nPoints), np.random.default_rng(seed))
    T_ct_us = knownTransform(bone.centre)
    usPoints = apply_transform(invert_rigid(T_ct_us), sweep.points)
    path = write_points(PointCloud(usPoints, "LPS"), Path(workDir) / "us_points.ply")
    return SyntheticCase(Path(segmentation), path, T_ct_us, mesh, sweep.points, usPoints)


def poseErrors(T_estimated: np.ndarray, T_true: np.ndarray, points=None) -> dict:
    """Errors of an estimate against the truth (both ``T_ct_us``, same space).

    Returns ``translation_mm`` (``|t_est - t_true|``), ``rotation_deg`` (angle of
    ``R_est R_true^T``, by scipy) and, with ``points`` (US frame), ``mean_point_mm`` /
    ``max_point_mm`` (distances between the points mapped by the two transforms)."""
    from scipy.spatial.transform import Rotation

    T_estimated = np.asarray(T_estimated, dtype=np.float64)
    T_true = np.asarray(T_true, dtype=np.float64)
    errors = {
        "translation_mm": float(np.linalg.norm(T_estimated[:3, 3] - T_true[:3, 3])),
        "rotation_deg": float(np.degrees(Rotation.from_matrix(
            T_estimated[:3, :3] @ T_true[:3, :3].T).magnitude())),
    }
    if points is not None:
        d = np.linalg.norm(apply_transform(T_estimated, points) - apply_transform(T_true, points),
                           axis=1)
        errors["mean_point_mm"] = float(d.mean())
        errors["max_point_mm"] = float(d.max())
    return errors


def transformNodeErrors(transformNode, case: SyntheticCase) -> dict:
    """:func:`poseErrors` of a US->CT transform node (to parent, RAS) against ``case``: the node
    matrix is taken to LPS by ``T_RAS_LPS`` on both sides."""
    from comreg_plugin.scene_io import transformToParentRAS

    T_lps = T_RAS_LPS @ transformToParentRAS(transformNode) @ T_RAS_LPS
    return poseErrors(T_lps, case.T_ct_us, case.usPoints)


def checkRegistrationAccuracy(transformNode, case: SyntheticCase) -> dict:
    """Assert the transform node is within 2 mm and 2 degrees of the truth; returns the errors."""
    errors = transformNodeErrors(transformNode, case)
    if not (errors["translation_mm"] < MAX_TRANSLATION_ERROR_MM
            and errors["rotation_deg"] < MAX_ROTATION_ERROR_DEG
            and errors["max_point_mm"] < MAX_TRANSLATION_ERROR_MM):
        raise AssertionError(f"Registration error beyond {MAX_TRANSLATION_ERROR_MM} mm / "
                             f"{MAX_ROTATION_ERROR_DEG} deg: {errors}")
    return errors


def sceneSummary(scene, ignoreClasses=()) -> dict:
    """``{node name: class name}`` of the nodes a user sees (not hidden, not of
    ``ignoreClasses``), for comparisons."""
    summary = {}
    for i in range(scene.GetNumberOfNodes()):
        node = scene.GetNthNode(i)
        if node.GetHideFromEditors() or node.IsA("vtkMRMLSubjectHierarchyNode") or any(
                node.IsA(c) for c in ignoreClasses):
            continue
        summary[node.GetName()] = node.GetClassName()
    return summary


def checkScenesMatch(original, reloaded, atol: float = 1e-6, ignoreClasses=()) -> None:
    """Assert two scenes hold the same visible nodes (names and classes; ``ignoreClasses``
    left out), the same linear transforms (to-parent matrices within ``atol``), the same point
    counts per model and the same transform parents."""
    from comreg_plugin.scene_io import transformToParentRAS

    a, b = sceneSummary(original, ignoreClasses), sceneSummary(reloaded, ignoreClasses)
    if a != b:
        raise AssertionError(f"The reloaded scene differs: {a} != {b}")
    for name, cls in a.items():
        n1, n2 = (scene.GetNodesByClassByName(cls, name).GetItemAsObject(0)
                  for scene in (original, reloaded))
        if cls == "vtkMRMLLinearTransformNode":
            diff = np.abs(transformToParentRAS(n1) - transformToParentRAS(n2)).max()
            if diff > atol:
                raise AssertionError(f"Transform '{name}' changed by {diff:.3g} on reload")
        if n1.IsA("vtkMRMLModelNode"):
            c1, c2 = (n.GetPolyData().GetNumberOfPoints() for n in (n1, n2))
            if c1 != c2:
                raise AssertionError(f"Model '{name}' has {c2} points after reload, not {c1}")
        if n1.IsA("vtkMRMLTransformableNode"):
            p1, p2 = n1.GetParentTransformNode(), n2.GetParentTransformNode()
            if (p1 and p1.GetName()) != (p2 and p2.GetName()):
                raise AssertionError(f"'{name}' is under a different transform after reload")


def readTransformWithSlicer(path) -> np.ndarray:
    """Read a transform file with Slicer's own storage node into a new node; its ``(4, 4)``
    to-parent matrix (RAS)."""
    from comreg_plugin.scene_io import transformToParentRAS
    from comreg_plugin.slicer_compat import slicer

    scene = slicer.vtkMRMLScene()
    node = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
    storage = scene.AddNewNodeByClass("vtkMRMLTransformStorageNode")
    storage.SetFileName(str(path))
    if not storage.ReadData(node):
        raise AssertionError(f"Slicer could not read the transform file '{path}'")
    return transformToParentRAS(node)


def checkSweepInputs(test, logic):
    """The bundled sweep as a Sequence browser and as files give the same bone points (RAS, to
    1e-6 mm; more than 500); returns the browser node. ``test``: a unittest.TestCase."""
    browser = logic.addSweepSequence(SAMPLE_SWEEP)
    test.assertTrue(browser.IsA("vtkMRMLSequenceBrowserNode"))
    fromSequence, _ = logic.usPointsFromSequence(browser, name="US points (Sequence)")
    fromFiles, _ = logic.loadTrackedSweep(SAMPLE_SWEEP, name="US points (files)")
    from comreg_plugin.scene_io import arrayFromModelPoints

    a, b = arrayFromModelPoints(fromSequence), arrayFromModelPoints(fromFiles)
    test.assertEqual(a.shape, b.shape)
    test.assertGreater(len(a), 500)
    test.assertLess(np.abs(a - b).max(), 1e-6)
    return browser


def checkTransformFiles(test, logic, transformNode, workDir) -> None:
    """The node saved as ``.tfm`` and ``.h5`` reads back (by Slicer, RAS, and by ComReg, LPS)
    as its to-parent matrix, to 1e-6."""
    from comreg_core.io import load_transform
    from comreg_plugin.scene_io import transformToParentRAS

    T_ras = transformToParentRAS(transformNode)
    for ext in (".tfm", ".h5"):
        path = logic.saveTransform(transformNode, Path(workDir) / f"T{ext}")
        test.assertLess(np.abs(readTransformWithSlicer(path) - T_ras).max(), 1e-6)
        test.assertLess(np.abs(load_transform(path) - T_RAS_LPS @ T_ras @ T_RAS_LPS).max(),
                        1e-6)


def checkSceneReload(test, logic, browser, case, errors: dict, workDir, logicClass) -> None:
    """The scene saved and reloaded into a new ``logicClass`` holds the same nodes, the same
    sweep (frame count) and an output transform with the same error (``errors``: the
    original's :func:`checkRegistrationAccuracy`)."""
    from comreg_plugin.scene_inputs import trackedSweepFromBrowser
    from comreg_plugin.slicer_compat import slicer

    scenePath = logic.saveScene(Path(workDir) / "scene" / "ComRegTest.mrml")
    reloaded = logicClass(slicer.vtkMRMLScene())
    reloaded.loadScene(scenePath)
    # (Slicer's .seq.mha reader renames the pose sequence it reloads: compared through the
    # sweep it gives back)
    checkScenesMatch(logic.scene, reloaded.scene, ignoreClasses=("vtkMRMLSequenceNode",))
    sweepBack = trackedSweepFromBrowser(reloaded.getParameterNode().sweep)
    test.assertEqual(sweepBack.n_frames, browser.GetMasterSequenceNode().GetNumberOfDataNodes())
    errorsBack = checkRegistrationAccuracy(reloaded.getParameterNode().outputTransform, case)
    test.assertAlmostEqual(errorsBack["translation_mm"], errors["translation_mm"], places=5)


def endToEnd(test, logic, workDir, logicClass) -> dict:
    """The module's end-to-end self test (``test``: a unittest.TestCase with ``delayDisplay``):
    segmentation -> bone model, the bundled sweep as a Sequence browser, US points -> model,
    registration by the pose search within 2 mm / 2 deg of the truth, transform files, scene
    save and reload. Returns the registration errors."""
    from comreg_plugin.scene_io import arrayFromModelPoints

    test.delayDisplay("Building the test data (sample CT, simulated sweep, known transform)")
    case = buildSyntheticCase(workDir)

    test.delayDisplay("CT segmentation -> bone model")
    segNode, models = logic.loadSegmentation(case.segmentationPath)
    test.assertEqual(len(models), 1)
    vertices = arrayFromModelPoints(models[0])
    expected = case.ctMesh.in_space("RAS").vertices
    test.assertEqual(vertices.shape, expected.shape)
    test.assertLess(np.abs(vertices - expected).max(), 1e-6)

    test.delayDisplay("Tracked sweep as a Sequence browser -> bone points")
    browser = checkSweepInputs(test, logic)

    test.delayDisplay("US points -> model")
    usNode = logic.loadUSPoints(case.usPointsPath)
    test.assertEqual(usNode.GetPolyData().GetNumberOfPoints(), len(case.usPoints))

    test.delayDisplay("Registration (ComReg pose search, no network)")
    output = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ReferenceToCT")
    summary = logic.register(usNode, "search", ctModelNode=models[0],
                             outputTransformNode=output)
    test.assertIs(summary.transformNode, output)
    test.assertIs(usNode.GetParentTransformNode(), output)
    test.assertEqual(summary.method, "search")
    errors = checkRegistrationAccuracy(summary.transformNode, case)
    test.delayDisplay(f"Registration error: {errors['translation_mm']:.3f} mm, "
                      f"{errors['rotation_deg']:.3f} deg (mean point "
                      f"{errors['mean_point_mm']:.3f} mm)")

    test.delayDisplay("Transform files (.tfm, .h5)")
    checkTransformFiles(test, logic, summary.transformNode, workDir)

    test.delayDisplay("Scene save and reload")
    checkSceneReload(test, logic, browser, case, errors, workDir, logicClass)
    test.delayDisplay("Test passed")
    return errors


def checkBadInputs(test, logic, workDir) -> None:
    """Bad inputs give clear errors: a missing or wrong segmentation, nothing to cancel, no
    US points."""
    from comreg_core.errors import ComRegError

    missing = Path(workDir) / "missing.seg.nrrd"
    with test.assertRaisesRegex(ComRegError, "does not exist"):
        logic.loadSegmentation(missing)
    wrong = Path(workDir) / "notes.txt"
    wrong.write_text("not a segmentation")
    with test.assertRaisesRegex(ComRegError, "Use one of"):
        logic.loadSegmentation(wrong)
    with test.assertRaisesRegex(ComRegError, "nothing to cancel"):
        logic.cancelPretraining()
    with test.assertRaisesRegex(ComRegError, "no US points"):
        logic.register(method="search")
    test.delayDisplay("Bad inputs give clear errors")
