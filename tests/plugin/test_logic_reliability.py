"""The Slicer module's Logic with the wrong node types and unusable output places (issue 15):
the module's error (ComRegError) with a clear message, never an AttributeError, and nothing
left behind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

from comreg_core.errors import ComRegError  # noqa: E402
from comreg_plugin.scene_io import arrayFromModelPoints, transformToParentRAS  # noqa: E402

WRONG_KINDS = ["vtkMRMLSegmentationNode", "vtkMRMLLinearTransformNode",
               "vtkMRMLScalarVolumeNode"]


def _node(logic, className: str):
    return logic.scene.AddNewNodeByClass(className, className)


def _points_model(logic, n: int = 300):
    points = np.random.default_rng(0).normal(size=(n, 3)) * 20
    return logic.addPointsModel(points, "LPS", "US points")


@pytest.mark.parametrize("className", WRONG_KINDS)
def test_register_with_the_wrong_node_types(logic, className):
    wrong = _node(logic, className)
    with pytest.raises(ComRegError, match=f"US points must be a model node.*{className}"):
        logic.register(wrong, "ransac")
    points = _points_model(logic)
    with pytest.raises(ComRegError, match=f"CT bone model must be a model node.*{className}"):
        logic.register(points, "ransac", ctModelNode=wrong)
    with pytest.raises(ComRegError, match="CT bone model must be a model node"):
        logic.ransacBaseline(wrong)
    with pytest.raises(ComRegError, match="must be a model node"):
        arrayFromModelPoints(wrong)


@pytest.mark.parametrize("className", WRONG_KINDS)
def test_start_pretraining_with_the_wrong_node_type_leaves_no_folder(logic, tmp_path,
                                                                     className):
    run = tmp_path / "run"
    with pytest.raises(ComRegError, match="CT bone model must be a model node"):
        logic.startPretraining(_node(logic, className), run)
    assert not run.exists() and logic.pretrainingJob is None


def test_start_pretraining_with_a_points_model_leaves_no_folder(logic, tmp_path):
    with pytest.raises(ComRegError, match="no surface"):
        logic.startPretraining(_points_model(logic), tmp_path / "run")
    assert list(tmp_path.iterdir()) == []


def test_start_pretraining_refuses_an_unwritable_run_folder(logic, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(ComRegError, match="is a file, not a folder"):
        logic.startPretraining(_points_model(logic), blocker / "run")


def test_save_transform_and_scene_with_bad_nodes_or_places(logic, tmp_path):
    transform = _node(logic, "vtkMRMLLinearTransformNode")
    with pytest.raises(ComRegError, match="transform to save must be a linear transform"):
        logic.saveTransform(_points_model(logic), tmp_path / "t.tfm")
    with pytest.raises(ComRegError, match="must be a linear transform node"):
        transformToParentRAS(_node(logic, "vtkMRMLSegmentationNode"))
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    # under a regular file: unwritable for root too (chmod would not stop root)
    with pytest.raises(ComRegError, match="is a file, not a folder"):
        logic.saveTransform(transform, blocker / "t.tfm")
    (tmp_path / "t.tfm").mkdir()
    with pytest.raises(ComRegError, match="is an existing folder"):
        logic.saveTransform(transform, tmp_path / "t.tfm")
    with pytest.raises(ComRegError, match="is a file, not a folder"):
        logic.saveScene(blocker / "scene" / "scene.mrml")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "t.tfm"]
    assert list((tmp_path / "t.tfm").iterdir()) == []


def test_save_into_an_immutable_folder(logic, tmp_path):
    from tests.helpers import immutable

    locked = tmp_path / "locked"
    locked.mkdir()
    with immutable(locked):
        transform = _node(logic, "vtkMRMLLinearTransformNode")
        with pytest.raises(ComRegError, match="not writable"):
            logic.saveTransform(transform, locked / "t.tfm")
        with pytest.raises(ComRegError, match="not writable"):
            logic.saveScene(locked / "scene.mrml")
    assert list(locked.iterdir()) == []


def test_a_seg_nrrd_without_segment_fields_gives_a_model(logic, tmp_path):
    from comreg_core.io import Volume, write_volume

    labels = np.zeros((24, 24, 24), np.uint8)
    labels[6:18, 6:18, 4:20] = 1
    path = write_volume(Volume.from_geometry(labels, spacing=(1.0, 1.0, 1.0)),
                        tmp_path / "bone.seg.nrrd")
    _, models = logic.loadSegmentation(Path(path))
    assert len(models) == 1 and models[0].GetPolyData().GetNumberOfPoints() > 0
