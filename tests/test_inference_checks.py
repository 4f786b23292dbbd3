"""The Registrar's checks around the network (issue 15): a network whose output is not finite
gives a clear CheckpointError (it crashed in the ICP with an IndexError), identical points are
called what they are, and a cloud above MAX_US_POINTS is registered as a seeded subset."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from comreg_core.errors import InvalidGeometryError
from comreg_core.training.checkpoint import CheckpointError
from tests.cli.test_reliability import SAMPLE_MODEL


@pytest.fixture(scope="module")
def registrar():
    """The bundled sample model, plain pipeline (no pose search: the checks are before it)."""
    from comreg_core.register import Registrar

    return Registrar.from_run(SAMPLE_MODEL, "cpu", search=False)


@pytest.fixture(scope="module")
def patch_points(registrar):
    """600 points of the CT surface's distal third (in the CT frame: truth = identity)."""
    import trimesh

    points = trimesh.Trimesh(registrar._ct_vertices, registrar._ct_faces).sample(2000, seed=3)
    return points[points[:, 2] > np.percentile(points[:, 2], 70)]


def test_a_network_with_non_finite_output_is_a_clear_error(registrar, patch_points,
                                                             monkeypatch):
    original = registrar.model.coarse_pose

    def nan_pose(source, encoding):
        completion, pose = original(source, encoding)
        return completion, pose._replace(transform=torch.full_like(pose.transform, np.nan))

    monkeypatch.setattr(registrar.model, "coarse_pose", nan_pose)
    with pytest.raises(CheckpointError, match="NaN or infinite output"):
        registrar.register(patch_points)


def test_identical_points_are_called_identical(registrar):
    with pytest.raises(InvalidGeometryError, match="only 1 distinct point") as caught:
        registrar.register(np.tile([[1.0, 2.0, 3.0]], (1000, 1)))
    assert "metres" not in str(caught.value)
    tiny = np.random.default_rng(0).uniform(0, 0.5, (1000, 3))  # 0.5 mm across: metres
    with pytest.raises(InvalidGeometryError, match="look like metres"):
        registrar.register(tiny)


def test_a_cloud_above_the_limit_is_registered_as_a_subset(registrar, patch_points,
                                                          monkeypatch):
    monkeypatch.setattr("comreg_core.registration.geometry.inputs.MAX_US_POINTS", 300)
    result = registrar.register(patch_points, seed=2)
    assert result.n_points == 300 and len(result.registered_points) == 300
    assert any("subset of 300" in w for w in result.info["warnings"])
    again = registrar.register(patch_points, seed=2)
    assert np.array_equal(again.T_ct_us, result.T_ct_us)  # a seeded subset: reproducible
