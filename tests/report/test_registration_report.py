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
    assert "success rate" not in page.lower()  # the stale metrics.json is left out
    assert "Median distance to the CT surface" in page

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


def test_metrics_are_labelled_in_words_with_units_apart(tmp_path, fibula, monkeypatch):
    """Every row of the metrics table: a label in words (no ``_mm``/``_deg`` key, no
    underscore), the value, and the unit in its own cell."""
    import re

    out, _ = _folder(tmp_path, fibula)
    result = json.loads((out / "result.json").read_text(encoding="utf-8"))
    result["timings_s"] = {"preprocess": 0.01, "completion_and_coarse_pose": 0.2,
                           "some_new_stage": 0.05, "total": 0.5}
    result["search"] = {"ambiguous": False, "confidence": 0.8, "chosen": "network+rot45",
                        "runner_up": "flip", "score_mm": 0.31, "score_gap_mm": 0.6,
                        "polish": {"moved_mm": 0.1, "iterations": 3,
                                   "inlier_fraction": 0.95, "rmse_mm": 0.4}}
    (out / "result.json").write_text(json.dumps(result), encoding="utf-8")
    truth = "ICP from the recorded tracking (pseudo ground truth, as in the paper)"
    metrics = {"registration": {
        "T_ct_us": np.eye(4).tolist(), "truth": truth,
        "errors_vs_truth": {"RTE_mm": 1.25, "RRE_deg": 0.5, "success": True},
        "tracking_vs_truth": {"RTE_mm": 1.5, "RRE_deg": 0.08}},
        "summary": {"comreg": {"trials": 2, "success_rate": 0.5, "flip_rate": 0.5,
                               "RTE_mm": {"median": 1.75}, "RRE_deg": {"median": 45.0}},
                    "search": {"trials": 2, "success_rate": 1.0, "flip_rate": 0.0,
                               "RTE_mm": {"median": 1.5}, "RRE_deg": {"median": 1.0}}}}
    (out / "metrics.json").write_text(json.dumps(metrics), encoding="utf-8")
    _render_small(monkeypatch)
    assert CliRunner().invoke(app, ["report", str(out)]).exit_code == 0
    page = (out / "report.html").read_text(encoding="utf-8")
    metrics_table = page[page.index("<h2>Metrics</h2>"):].split("</table>")[0]
    rows = re.findall(r"<tr><td>(.*?)</td><td[^>]*>(.*?)</td><td>(.*?)</td></tr>",
                      metrics_table)
    assert len(rows) >= 20
    for label, _, _ in rows:
        assert "_" not in label and "_mm" not in label and "_deg" not in label, label
    table = {label: (value, unit) for label, value, unit in rows}
    fit = "Fit of the US points to the CT bone / "
    assert table[fit + "Median distance to the CT surface"][1] == "mm"
    assert table[fit + "90 % of the points within"][1] == "mm"
    assert table[fit + "Points within 2 mm of the surface"][1] == "%"
    assert table[fit + "Best-fitting scale of the US points"][1] == ""
    error = "Error against the truth / "
    assert table[error + "Truth"] == (truth, "")
    assert table[error + "Translation error at the US centroid (RTE)"] == ("1.250", "mm")
    assert table[error + "Rotation error (RRE)"] == ("0.500", "deg")
    assert table[error + "Success (RTE &lt; 2 mm and RRE &lt; 2 deg)"] == ("yes", "")
    assert table[error + "Offset of the recorded tracking from the truth (translation)"] == (
        "1.500", "mm")
    assert table[error + "Offset of the recorded tracking from the truth (rotation)"] == (
        "0.080", "deg")
    starts = "Further random starts, with the network (against the same truth) / "
    assert table[starts + "Success rate"] == ("50.000", "%")
    assert table[starts + "Median rotation error (RRE)"] == ("45.000", "deg")
    alone = "Further random starts, the pose search alone (against the same truth) / "
    assert table[alone + "Success rate"] == ("100.000", "%")
    assert table[alone + "Median rotation error (RRE)"] == ("1.000", "deg")
    assert table["Pose search / Trimmed mean distance of the kept pose"] == ("0.310", "mm")
    assert table["Pose search / Confidence (0-1; below 0.3 is ambiguous)"] == ("0.800", "")
    assert table["Time / Registration in all"] == ("0.500", "s")
    assert table["Time / Completion and coarse pose (network)"] == ("0.200", "s")
    assert table["Time / Some new stage"] == ("0.050", "s")
