"""`comreg register --init TRANSFORM --init-tolerance DEG,MM --landmarks CT US`: a prior that
excludes the truth comes out CHECK with the reason in result.json and on the terminal; bad prior
inputs are one-line errors (exit 2) before any work."""

from __future__ import annotations

import json
import math

from typer.testing import CliRunner

from comreg_core.cli import app
from comreg_core.io import PointCloud, save_transform, write_points
from comreg_core.registration.search.search import rotation_about
from tests.helpers import FIBULA_STL
from tests.registration.test_priors import short_run  # noqa: F401  (the fixture)

runner = CliRunner()

FCSV = """# Markups fiducial file version = 5.6
# CoordinateSystem = {space}
# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID
1,{x},{y},{z},0,0,0,1,1,1,0,{label},,,2,0
"""


def test_a_prior_that_excludes_the_truth_is_checked(tmp_path, short_run):  # noqa: F811
    us = write_points(PointCloud(short_run), tmp_path / "us.ply")
    T_init = rotation_about(short_run.mean(axis=0), [1.0, 0.3, 0.2], math.radians(60.0))
    init = save_transform(T_init, tmp_path / "init.h5")
    out = tmp_path / "reg"
    result = runner.invoke(app, ["register", str(us), "--ct", str(FIBULA_STL), "--init",
                                 str(init), "--init-tolerance", "10,10", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "prior: " in result.output and "AT THE EDGE" in result.output
    saved = json.loads((out / "result.json").read_text())
    prior = saved["prior"]
    assert prior["init_file"] == str(init.absolute()) and prior["at_edge"] is True
    assert (prior["max_deg"], prior["max_mm"]) == (10.0, 10.0)
    assert prior["rotation_from_init_deg"] <= 10.0 + 1e-6
    assert saved["verdict"] == "check"
    reason = next(r for r in saved["verdict_reasons"] if "edge of the initial pose" in r)
    assert "of 10 deg" in reason and "the prior may exclude the true pose" in reason
    settings = (out / "config.yaml").read_text()
    assert "init_tolerance" in settings and "init.h5" in settings


def test_bad_prior_inputs_are_one_line_errors(tmp_path):
    us = write_points(PointCloud([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]), tmp_path / "us.ply")
    (tmp_path / "ct.fcsv").write_text(FCSV.format(space="LPS", x=1, y=2, z=3, label="tip"))
    (tmp_path / "us.fcsv").write_text(FCSV.format(space="RAS", x=1, y=2, z=3, label="apex"))
    (tmp_path / "ct.txt").write_text("1 2 3\n")
    init = save_transform([[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                          tmp_path / "init.tfm")
    base = ["register", str(us), "--ct", str(FIBULA_STL)]
    cases = {
        "without an initial pose": ["--init-tolerance", "10,10"],
        "is not DEG,MM": ["--init", str(init), "--init-tolerance", "ten"],
        "do not pair up": ["--landmarks", str(tmp_path / "ct.fcsv"), str(tmp_path / "us.fcsv")],
        "extension": ["--landmarks", str(tmp_path / "ct.txt"), str(tmp_path / "us.fcsv")],
        "does not exist": ["--init", str(tmp_path / "none.tfm")],
        "without landmarks": ["--landmark-tolerance", "5"],
    }
    for k, (message, args) in enumerate(cases.items()):
        out = tmp_path / f"out{k}"
        result = runner.invoke(app, [*base, *args, "--out", str(out)])
        assert result.exit_code == 2, (message, result.output)
        assert message in result.output and len(result.output.strip().splitlines()) <= 2, \
            result.output
        assert not out.exists()
