"""The module self test's checks of the panel's result parts on the bundled sample (issue 50):
the verdict and its figures on the transform node, two sweeps registered as one body, "Save
result folder", "Write report", "Calibrate verdict" in the background and the live mode's
second process. Shared by ``ComRegTest`` (inside 3D Slicer: Reload and Test) and pytest
(headless, ``tests/plugin/test_module.py``)."""

import json
import time
from pathlib import Path

import numpy as np

from comreg_plugin.testing import SAMPLE_SEGMENTATION, SAMPLE_SWEEP

#: Sweeps of the self test's verdict calibration (a few: it checks the plumbing, not p_correct).
CALIBRATION_SWEEPS = 4
#: Frames of the bundled sweep streamed through the live mode.
LIVE_FRAMES = 12


def checkPanel(test, logic, workDir) -> None:
    """Run every check below on the bundled sample (``test``: a unittest.TestCase with
    ``delayDisplay``)."""
    workDir = Path(workDir)
    logic.getParameterNode().resultDirectory = str(workDir / "registrations")
    test.delayDisplay("Bundled sample: CT model and the sweep's bone points")
    _, models = logic.loadSegmentation(SAMPLE_SEGMENTATION)
    points, _ = logic.loadTrackedSweep(SAMPLE_SWEEP)
    summary = checkVerdict(test, logic, points, models[0])
    checkTwoSweeps(test, logic, points, models[0], summary)
    checkResultFolder(test, logic, summary, workDir)
    checkCalibration(test, logic, points, models[0], workDir)
    checkLive(test, logic, models[0])
    test.delayDisplay("Panel checks passed")


def checkVerdict(test, logic, points, ctModel):
    """A registration by the pose search carries ``comreg register``'s verdict: the figures on
    the transform node are ``result.json``'s. Returns the summary."""
    from comreg_plugin.verdict_record import figuresFromNode, recordAdvice

    test.delayDisplay("Registration with its verdict")
    summary = logic.register(points, "search", ctModelNode=ctModel)
    saved = json.loads((summary.resultFolder / "result.json").read_text(encoding="utf-8"))
    test.assertEqual(saved["T_ct_us"], np.asarray(summary.T_ct_us).tolist())
    figures = figuresFromNode(summary.transformNode)
    test.assertEqual(figures["verdict"], saved["verdict"])
    test.assertEqual(figures["verdict_reasons"], saved["verdict_reasons"])
    test.assertEqual(figures["p_correct"], saved["p_correct"])
    test.assertEqual(figures["warnings"], saved["warnings"])
    test.assertEqual(figures["advice"] or "", recordAdvice(saved))
    test.assertIn(f"Verdict: {saved['verdict'].upper()}",
                  summary.describe(False, -1.0))
    display = points.GetDisplayNode()
    test.assertEqual(display.GetActiveScalarName(), "ComReg distance to CT (mm)")
    test.delayDisplay(f"Verdict {saved['verdict'].upper()}, confidence "
                      f"{saved['confidence']:.2f}")
    return summary


def checkTwoSweeps(test, logic, points, ctModel, whole) -> None:
    """The sweep's points split in two nodes (its first and second half, each with its beam
    origins) and registered as two sweeps give the bit-identical pose of the whole."""
    from comreg_plugin.bone_models import addPointsModel, beamOriginsOfNode
    from comreg_plugin.scene_inputs import arrayFromPointsNode

    test.delayDisplay("Two sweeps registered as one body")
    ras = arrayFromPointsNode(points)
    origins = beamOriginsOfNode(points, "RAS")
    half = len(ras) // 2
    nodes = [addPointsModel(logic.scene, ras[part], "RAS", f"Sweep half {k}", (0.2, 0.6, 1.0),
                            origins=None if origins is None else origins[part])
             for k, part in enumerate((slice(0, half), slice(half, None)), start=1)]
    summary = logic.register(nodes, "search", ctModelNode=ctModel)
    test.assertTrue(np.array_equal(summary.T_ct_us, whole.T_ct_us))
    test.assertEqual([r["n_points"] for r in summary.record["us_inputs"]],
                     [half, len(ras) - half])
    for node in nodes:
        test.assertIs(node.GetParentTransformNode(), summary.transformNode)


def checkResultFolder(test, logic, summary, workDir) -> None:
    """"Save result folder" writes ``comreg register``'s files of the transform node's last
    registration; "Write report" its report."""
    test.delayDisplay("Save result folder, write report")
    saved = logic.saveResultFolder(workDir / "saved", summary.transformNode)
    for name in ("result.json", "transform.tfm", "registered_us.ply", "config.yaml"):
        test.assertTrue((saved / name).is_file(), name)
    record = json.loads((saved / "result.json").read_text(encoding="utf-8"))
    test.assertEqual(record["verdict"], summary.record["verdict"])
    given = record["us_points"]
    for path in given if isinstance(given, list) else [given]:  # the saved copies
        test.assertTrue(path.startswith(str(saved.resolve())), path)
    page = logic.writeReport(workDir / "report", summary.transformNode)
    test.assertTrue(page.is_file())
    test.assertGreater(len(list((page.parent / "report_images").glob("*.png"))), 3)


def checkCalibration(test, logic, points, ctModel, workDir) -> None:
    """"Calibrate verdict" runs in the background, then gives the registrations ``p_correct``."""
    test.delayDisplay(f"Calibrate verdict ({CALIBRATION_SWEEPS} sweeps, in the background)")
    logic.startCalibration(ctModel, workDir / "calibration", sweeps=CALIBRATION_SWEEPS)
    deadline = time.monotonic() + 600.0
    status = logic.pollCalibration()
    while status.state == "running" and time.monotonic() < deadline:
        time.sleep(0.5)
        status = logic.pollCalibration()
    test.assertEqual(status.state, "finished", status.message)
    summary = logic.register(points, "search", ctModelNode=ctModel)
    test.assertIsNotNone(summary.record["p_correct"])
    test.assertEqual(logic.getParameterNode().pCorrect, summary.record["p_correct"])


def checkLive(test, logic, ctModel) -> None:
    """The live mode registers frames of the bundled sweep, streamed into image and pose
    nodes, in its second process; the output node carries the verdict."""
    from comreg_core.io import read_tracked_sweep
    from comreg_plugin.live import LiveRegistration
    from comreg_plugin.scene_io import vtkMatrixFromArray

    test.delayDisplay("Live mode (the session in a second process)")
    sweep = read_tracked_sweep(SAMPLE_SWEEP)
    image = logic.scene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "Image")
    pose = logic.scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "ImageToReference")
    live = LiveRegistration(logic, image, pose, ctModelNode=ctModel, background=False)
    try:
        for i in range(min(LIVE_FRAMES, sweep.n_frames)):
            streamFrame(image, pose, sweep, i, vtkMatrixFromArray)
        live.tick(wait=True)
        test.assertTrue(live.updates, live.status)
        test.assertNotEqual(live.processId, None)
        test.assertEqual(live.outputTransformNode.GetAttribute("ComReg.verdict"),
                         live.updates[-1].verdict)
    finally:
        live.stop()
    test.delayDisplay(live.status)


def streamFrame(imageNode, poseNode, sweep, i, vtkMatrixFromArray) -> None:
    """Frame ``i`` of a :class:`~comreg_core.io.TrackedSweep` into the nodes as 3D Slicer's
    OpenIGTLink connector shows a PLUS stream: the pose first, then the image."""
    import vtk
    from vtk.util import numpy_support

    from comreg_core.transforms import T_RAS_LPS

    poseNode.SetMatrixTransformToParent(vtkMatrixFromArray(
        T_RAS_LPS @ sweep.T_ref_image[i] @ T_RAS_LPS))
    imageNode.SetIJKToRASMatrix(vtkMatrixFromArray(T_RAS_LPS @ np.diag([*sweep.spacing, 1, 1])))
    H, W = sweep.image_shape
    image = vtk.vtkImageData()
    image.SetDimensions(W, H, 1)
    image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(
        np.ascontiguousarray(sweep.frames[i]).ravel(), deep=True,
        array_type=vtk.VTK_UNSIGNED_CHAR))
    imageNode.SetAndObserveImageData(image)
