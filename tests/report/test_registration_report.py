"""``comreg report OUT_DIR`` on a hand-made registration folder: the page starts with the verdict,
works from another directory (absolute paths in result.json), judges ``--transform``, and shows
no metrics.json that was not made for this registration."""

import json

import numpy as np
from typer.testing import CliRunner

from comreg_core.cli import app
from comreg_core.io import PointCloud, write_points
from comreg_core.io.transform_files import save_transform
from tests.helpers import FIBULA_STL
from tests.report.support import make_case


def _folder(tmp_path, fibula):
    case = make_case(fibula)
    out = tmp_path / "registration"
    out.mkdir()
    us = write_points(PointCloud(case.us_after, fibula.space), tmp_path / "us.ply")
    result = {"T_ct_us": np.eye(4).tolist(), "run_dir": str(tmp_path / "no_run"),
              "us_points": str(us.absolute()), "ct_mesh": str(FIBULA_STL), "seed": 0,
              "device": "cpu", "runtime_s": 0.5, "timings_s": {"total": 0.5}}
    (out / "result.json").write_text(json.dumps(result), encoding="utf-8")
    (out / "metrics.json").write_text(json.dumps({"summary": {"comreg": {"success_rate": 0.1}}}),
                                      encoding="utf-8")  # an old evaluation: not this one's
    return out, case


def _render_small(monkeypatch):
    from comreg_core.report import report as report_module

    original = report_module.write_report

    def small(*args, **kwargs):
        kwargs.update(window_size=(160, 160), views=("anterior",), scenes=["registered"])
        return original(*args, **kwargs)

    monkeypatch.setattr("comreg_core.report.registration.write_report", small)


def test_report_from_another_directory_starts_with_the_verdict(tmp_path, fibula, monkeypatch):
    out, case = _folder(tmp_path, fibula)
    _render_small(monkeypatch)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    result = CliRunner().invoke(app, ["report", str(out)])
    assert result.exit_code == 0, result.output
    page = (out / "report.html").read_text(encoding="utf-8")
    body = page[page.index("<body>"):]
    assert body.index("Verdict: OK") < body.index("<h1>")
    assert "success rate" not in page  # the stale metrics.json is left out
    assert "median distance to the CT surface" in page

    slid = np.eye(4)
    slid[:3, 3] = 25.0 * case.ct.vertices.std(0) / np.linalg.norm(case.ct.vertices.std(0))
    save_transform(slid, tmp_path / "slid.tfm", space=fibula.space)
    result = CliRunner().invoke(app, ["report", str(out), "--transform",
                                      str(tmp_path / "slid.tfm")])
    assert result.exit_code == 0, result.output
    page = (out / "report.html").read_text(encoding="utf-8")
    assert "Verdict: CHECK" in page


def test_report_with_a_missing_transform_file_is_a_one_line_error(tmp_path, fibula):
    out, _ = _folder(tmp_path, fibula)
    result = CliRunner().invoke(app, ["report", str(out), "--transform",
                                      str(tmp_path / "missing.tfm")])
    assert result.exit_code == 2
