"""The Slicer module's registration methods and summary (comreg_plugin.registration): method
choice and defaults, RAS <-> the method's space, the completed bone, the transform node's
attributes and the user's result line. The Logic's end-to-end registrations are in
test_logic.py."""

from __future__ import annotations

import json
import types

import numpy as np
import pytest

from tests.plugin.conftest import SLICER_CORE_MISSING

pytest.importorskip("slicer_core", reason=SLICER_CORE_MISSING)

import slicer  # noqa: E402

from comreg_core.errors import ComRegError  # noqa: E402
from comreg_core.evaluation.outputs import RegistrationOutput  # noqa: E402
from comreg_core.transforms import T_RAS_LPS, apply_transform  # noqa: E402
from comreg_plugin.registration import (COMPLETED_BONE_NODE_NAME,  # noqa: E402
                                        RegistrationMethods, RegistrationSummary,
                                        resultAttributes, runRegistration)
from tests.helpers import assert_close, random_rigid  # noqa: E402

NO_DEFAULTS = types.SimpleNamespace(runDirectory="", ctModel=None)


def _summary(info=None, completed=None) -> RegistrationSummary:
    return RegistrationSummary(None, completed, np.eye(4), np.eye(4), "LPS", "ransac", 1.234,
                               info or {})


def test_a_callable_is_a_method_named_after_itself():
    def oracle(points):
        return np.eye(4)

    methods = RegistrationMethods()
    space, run, name, runDirectory = methods.prepare(oracle, NO_DEFAULTS, runDirectory=None,
                                                     ctModelNode=None, seed=0, device="cpu")
    assert (space, run, name, runDirectory) == ("LPS", oracle, "oracle", None)

    class Named:
        name = "mine"

        def __call__(self, points):
            return np.eye(4)

    assert methods.prepare(Named(), NO_DEFAULTS, runDirectory=None, ctModelNode=None, seed=0,
                           device="cpu")[2] == "mine"


def test_unknown_or_incomplete_methods_are_refused():
    methods = RegistrationMethods()
    kwargs = dict(runDirectory=None, ctModelNode=None, seed=0, device="cpu")
    with pytest.raises(ComRegError, match="Unknown registration method 'magic'.*comreg, search, "
                                          "ransac"):
        methods.prepare("magic", NO_DEFAULTS, **kwargs)
    with pytest.raises(ComRegError, match="No pretrained run folder"):
        methods.prepare("comreg", NO_DEFAULTS, **kwargs)
    for method in ("ransac", "search"):
        with pytest.raises(ComRegError, match=f"'{method}' method needs the CT bone model"):
            methods.prepare(method, NO_DEFAULTS, **kwargs)


def test_missing_inputs_default_to_the_parameter_node():
    scene = slicer.vtkMRMLScene()
    transform = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "T")
    defaults = types.SimpleNamespace(runDirectory="", ctModel=transform)
    with pytest.raises(ComRegError, match="CT bone model must be a model node.*'T'"):
        RegistrationMethods().prepare("ransac", defaults, runDirectory=None, ctModelNode=None,
                                      seed=0, device="cpu")


def test_a_run_sees_lps_points_and_returns_the_transform_in_both_spaces():
    rng = np.random.default_rng(1)
    T = random_rigid(rng)
    points_ras = rng.normal(size=(50, 3)) * 30
    completion = rng.normal(size=(20, 3)) * 30  # in the received (US) frame
    seen = []

    def method(points):
        seen.append(points)
        return {"T_ct_us": T, "completion": completion, "info": {"fitness": 0.5}}

    output, T_lps, T_ras, completion_ct = runRegistration(method, points_ras, "LPS")
    assert_close(seen[0], apply_transform(T_RAS_LPS, points_ras), atol=1e-12, what="LPS in")
    assert_close(T_lps, T, atol=1e-12) and output.info == {"fitness": 0.5}
    assert_close(T_ras, T_RAS_LPS @ T @ T_RAS_LPS, atol=1e-12, what="T in RAS")
    assert_close(completion_ct, apply_transform(T, completion), atol=1e-9, what="completion")
    assert output.runtime_s >= 0.0

    # a result that carries its own CT-frame completion is taken as it is
    own = types.SimpleNamespace(T_ct_us=T, completion_ct=completion, runtime_s=2.0)
    output, _, _, completion_ct = runRegistration(lambda points: own, points_ras, "LPS")
    assert completion_ct is completion and output.runtime_s == 2.0
    assert runRegistration(lambda points: np.eye(4), points_ras, "RAS")[3] is None


def test_the_transform_node_attributes():
    output = RegistrationOutput(np.eye(4), 0.123456789, info={
        "residuals_mm": np.array([1.0, 2.0]), "ambiguous": np.bool_(True), "n": np.int64(3),
        "other": object})
    attributes = resultAttributes(output, "comreg", "/runs/a")
    # no "space" (the node is RAS like every Slicer transform) and no absolute path
    assert set(attributes) == {"method", "runtime_s", "info", "run"}
    assert attributes["runtime_s"] == "0.123457" and attributes["run"] == "a"
    info = json.loads(attributes["info"])
    assert info["residuals_mm"] == [1.0, 2.0] and info["ambiguous"] is True and info["n"] == 3
    assert info["other"] == str(object)
    assert "run" not in resultAttributes(output, "ransac", "/runs/a")


def test_the_result_line():
    assert _summary().describe(False, -1.0) == "ransac: 1.23 s"
    summary = _summary({"residuals_mm": {"median": 0.456}, "ambiguous": True},
                       completed=object())
    assert summary.describe(True, 0.8) == (
        "ransac: 1.23 s, median distance to CT 0.46 mm, AMBIGUOUS (check the pose), "
        f"confidence 0.80; '{COMPLETED_BONE_NODE_NAME}' added")
    assert summary.describe(False, -1.0) == (
        f"ransac: 1.23 s, median distance to CT 0.46 mm; '{COMPLETED_BONE_NODE_NAME}' added")
    # the verdict's uncertainty weighed the search's close, clinically different pose: ruled
    # out at 1/19 (0.0526) or less, the OK line's odds
    for weight, words in ((1e-9, "a close pose ruled out by the fit"),
                          (0.05, "a close pose ruled out by the fit"),
                          (0.06, "AMBIGUOUS (check the pose)")):
        summary.record = {"uncertainty": {"competitor": {"delta_cost": 1.0, "weight": weight}}}
        assert f", {words}, confidence 0.80" in summary.describe(True, 0.8)
