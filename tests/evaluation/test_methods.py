"""Methods by name for ``comreg evaluate``: ComReg with and without its pose search side by
side (one network), the baselines, ``all``."""

from __future__ import annotations

import functools

import pytest

from comreg_core.errors import ComRegError
from comreg_core.evaluation import evaluate
from comreg_core.choices import METHODS
from comreg_core.evaluation.methods import method_names, registration_methods
from comreg_core.register import Registrar
from tests.helpers import FIBULA_STL
from tests.training.tiny import tiny_run


def test_method_names():
    assert METHODS == ("search", "comreg", "comreg-plain", "ransac", "icp-gt")
    assert method_names("all") == list(METHODS)
    assert method_names(["comreg-plain", "comreg", "comreg-plain"]) == ["comreg-plain", "comreg"]
    assert method_names(["icp-gt", "all"]) == ["icp-gt", "search", "comreg", "comreg-plain",
                                               "ransac"]
    with pytest.raises(ComRegError, match="Unknown registration method 'comreg-x'"):
        method_names(["comreg-x"])
    with pytest.raises(ComRegError, match="No registration method"):
        method_names([])


def test_comreg_and_plain_side_by_side(tmp_path_factory):
    run = tiny_run(tmp_path_factory)[1]
    methods = registration_methods(["comreg", "comreg-plain", "icp-gt"], run, FIBULA_STL,
                                   device="cpu")
    assert list(methods) == ["comreg", "comreg-plain", "icp-gt"]
    comreg, plain = methods["comreg"], methods["comreg-plain"]
    assert isinstance(comreg, Registrar) and comreg.search_config.enabled
    assert isinstance(plain, functools.partial) and plain.func.__self__ is comreg  # one network
    result = evaluate(methods, "simulated", FIBULA_STL, trials=1, seed=0)
    rows = {r["method"]: r for r in result["trials"]}
    assert isinstance(rows["comreg"]["ambiguous"], bool)
    assert rows["comreg"]["info"]["search"]["chosen"] in \
        rows["comreg"]["info"]["search"]["scores_mm"]
    assert rows["comreg-plain"]["ambiguous"] is None
    assert rows["comreg-plain"]["info"]["search"] is None
    s = result["summary"]
    assert s["comreg"]["ambiguous_rate"] in (0.0, 1.0)
    assert s["comreg-plain"]["ambiguous_rate"] is None
    with pytest.raises(ComRegError, match="comreg-plain"):
        registration_methods(["comreg"], run, FIBULA_STL, device="cpu", search=False)
