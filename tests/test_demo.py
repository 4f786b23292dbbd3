"""``comreg demo``: the bundled sample case end to end with the bundled model."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from comreg_core.demo import SAMPLE_MODEL, TRUTH, run_demo, summary_lines
from comreg_core.registration.geometry.surface import CTSurface
from comreg_core.io import load_transform, read_mesh, read_points


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    import torch

    out = tmp_path_factory.mktemp("demo") / "demo"
    steps: list[str] = []
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        result = run_demo(out, device="cpu", trials=2, seed=0, train_minutes=0.1,
                          step=steps.append)
    finally:
        torch.set_num_threads(threads)
    return result, out, steps


def test_demo_uses_the_bundled_model_and_writes_every_file(demo):
    result, out, steps = demo
    assert not result.trained and result.model == SAMPLE_MODEL  # the bundled model fits
    assert not any("pretraining" in line for line in steps)
    for name in ("ct_bone.stl", "us_points.ply", "us_points_moved.ply", "T_ct_us_truth.tfm",
                 "demo.json", "registration/result.json", "registration/transform.tfm",
                 "registration/metrics.json", "registration/report.html"):
        assert (out / name).is_file(), name
    html = (out / "registration" / "report.html").read_text(encoding="utf-8")
    images = list((out / "registration").rglob("*.png"))
    assert len(images) >= 3 and all(p.name in html for p in images)
    # the sample sweep's B-mode frames with the CT contour, and the CT cross-sections
    assert len([p for p in images if p.name.startswith("frame_")]) == 4
    assert len([p for p in images if p.name.startswith("section_")]) == 3
    recorded = json.loads((out / "registration" / "result.json").read_text())["sweep"]
    assert recorded["path"].endswith("sweep") and np.array(recorded["T_us_ref"]).shape == (4, 4)
    assert result.n_us_points > 2000  # 37 real frames -> 3,166 points here


def test_demo_errors_match_an_independent_computation(demo):
    result, out, _ = demo
    registration = json.loads((out / "registration" / "result.json").read_text())
    T_est = np.array(registration["T_ct_us"])
    T_true = load_transform(out / "T_ct_us_truth.tfm")
    moved = read_points(out / "us_points_moved.ply").points
    c = moved.mean(axis=0)
    rte = np.linalg.norm(T_est[:3, :3] @ c + T_est[:3, 3] - T_true[:3, :3] @ c - T_true[:3, 3])
    rre = np.degrees(Rotation.from_matrix(T_est[:3, :3].T @ T_true[:3, :3]).magnitude())
    assert result.RTE_mm == pytest.approx(rte, abs=1e-6)
    assert result.RRE_deg == pytest.approx(rre, abs=1e-4)
    summary = json.loads((out / "demo.json").read_text())
    assert summary["RTE_mm"] == pytest.approx(rte, abs=1e-6)
    metrics = json.loads((out / "registration" / "metrics.json").read_text())
    assert [(t["trial"], t["method"]) for t in metrics["trials"]] == [
        (0, "search"), (0, "comreg"), (1, "search"), (1, "comreg")]  # 2 starts, both methods


def test_the_truth_is_icp_from_the_recorded_tracking(demo):
    """The demo's truth is the paper's pseudo ground truth: ICP from the recorded tracking
    (identity: CT and tracking share one frame). It puts the recorded points closer to the CT
    bone than the recording does, and the moved points' truth is it after undoing the move."""
    result, out, steps = demo
    metrics = json.loads((out / "registration" / "metrics.json").read_text())["registration"]
    assert metrics["truth"] == TRUTH and any("truth" in line for line in steps)
    T_recorded = np.array(metrics["T_ct_recorded"])
    recorded = read_points(out / "us_points.ply").points
    moved = read_points(out / "us_points_moved.ply").points
    T_true = load_transform(out / "T_ct_us_truth.tfm")
    assert np.abs((moved @ T_true[:3, :3].T + T_true[:3, 3])
                  - (recorded @ T_recorded[:3, :3].T + T_recorded[:3, 3])).max() < 1e-3
    surface = CTSurface(read_mesh(out / "ct_bone.stl"))
    on_bone = surface.distance(recorded @ T_recorded[:3, :3].T + T_recorded[:3, 3])
    assert np.median(on_bone) < np.median(surface.distance(recorded))
    # how far the recorded tracking lies from it, as numbers (at the points' centroid)
    c = recorded.mean(axis=0)
    offset = np.linalg.norm(T_recorded[:3, :3] @ c + T_recorded[:3, 3] - c)
    angle = np.degrees(Rotation.from_matrix(T_recorded[:3, :3]).magnitude())
    assert result.tracking_RTE_mm == pytest.approx(offset, abs=1e-6) and offset > 0.1
    assert result.tracking_RRE_deg == pytest.approx(angle, abs=1e-4)
    summary = json.loads((out / "demo.json").read_text())
    assert summary["truth"] == TRUTH
    assert summary["tracking_vs_truth"]["RTE_mm"] == pytest.approx(offset, abs=1e-6)
    assert summary["tracking_vs_truth"]["RRE_deg"] == pytest.approx(angle, abs=1e-4)


def test_success_agrees_with_the_verdict_and_the_summary_says_what_the_truth_is(demo):
    result, out, _ = demo
    assert result.verdict == "ok" and result.success  # on the bundled sample
    assert result.success == (result.verdict == "ok")
    registration = json.loads((out / "registration" / "result.json").read_text())
    assert registration["verdict"] == result.verdict
    html = (out / "registration" / "report.html").read_text(encoding="utf-8")
    assert "Verdict: OK" in html and TRUTH in html
    assert "<td>Error against the truth / Success (RTE &lt; 2 mm and RRE &lt; 2 deg)</td>" \
           "<td>yes</td>" in html
    tracking = (f"<td>Error against the truth / Offset of the recorded tracking from the truth "
                f'(translation)</td><td class="num">{result.tracking_RTE_mm:.3f}</td><td>mm</td>')
    assert tracking in html
    lines = summary_lines(result, 2)
    assert lines[0].endswith("success yes; Verdict: OK")
    assert lines[1] == (f"truth: {TRUTH}; the tracking itself lies "
                        f"{result.tracking_RTE_mm:.2f} mm / {result.tracking_RRE_deg:.2f}° "
                        "from it")
    assert lines[-1] == f"report: {result.report}"


def test_further_starts_compare_the_network_with_the_search_alone(demo):
    """The demo's further starts are registered by the search alone and with the network, side
    by side; with the network the chosen score is never worse, start for start."""
    result, out, _ = demo
    metrics = json.loads((out / "registration" / "metrics.json").read_text())
    scores: dict = {}
    for trial in metrics["trials"]:
        scores.setdefault(trial["trial"], {})[trial["method"]] = \
            trial["info"]["search"]["score_mm"]
    assert scores and all(set(pair) == {"search", "comreg"} for pair in scores.values())
    assert all(pair["comreg"] <= pair["search"] for pair in scores.values()), scores
    assert result.search_success_rate == metrics["summary"]["search"]["success_rate"]
    assert "the search alone success" in summary_lines(result, len(scores))[2]


def test_registered_us_points_lie_on_the_ct_bone(demo):
    _, out, _ = demo
    registered = read_points(out / "registration" / "registered_us.ply").points
    distances = CTSurface(read_mesh(out / "ct_bone.stl")).distance(registered)
    # the real sweep's points sit on the bone after registration (median, mm)
    assert np.median(distances) < 1.0


def test_demo_into_a_file_is_a_clear_error(tmp_path):
    from typer.testing import CliRunner

    from comreg_core.cli import app

    target = tmp_path / "not_a_folder"
    target.write_text("x")
    out = CliRunner().invoke(app, ["demo", "--out", str(target)])
    assert out.exit_code == 2 and "is not a folder" in out.output
    assert target.read_text() == "x"


def test_demo_on_cuda_without_cuda_is_refused_before_any_file_is_written(tmp_path):
    import torch
    from typer.testing import CliRunner

    from comreg_core.cli import app

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    out = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "demo"), "--device", "cuda"])
    assert out.exit_code == 2 and "no CUDA device" in out.output, out.output
    assert not (tmp_path / "demo").exists()


def test_demo_gives_the_same_figures_at_one_thread_on_a_busy_machine(demo, tmp_path):
    """The fixture ran at 2 torch threads on a quiet process; the same demo at 1 thread (torch,
    BLAS, OpenMP) while another process keeps a core busy gives the identical transform and
    figures (README quotes them)."""
    import os
    import subprocess
    import sys

    result, out, _ = demo
    code = ("import sys, torch\n"
            "torch.set_num_threads(1)\n"
            "from comreg_core.demo import run_demo\n"
            "run_demo(sys.argv[1], device='cpu', trials=2, seed=0, train_minutes=0.1)\n")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        subprocess.run([sys.executable, "-c", code, str(tmp_path / "demo")], env=env,
                       check=True, capture_output=True)
    finally:
        busy.kill()
        busy.wait()
    again = json.loads((tmp_path / "demo" / "demo.json").read_text())
    first = json.loads((out / "demo.json").read_text())
    for key in ("RTE_mm", "RRE_deg", "success_rate", "flip_rate", "search_success_rate",
                "n_us_points", "success", "verdict", "tracking_vs_truth"):
        assert again[key] == first[key], key
    T_first = json.loads((out / "registration" / "result.json").read_text())["T_ct_us"]
    T_again = json.loads((tmp_path / "demo" / "registration" / "result.json").read_text())
    assert np.array_equal(np.array(T_again["T_ct_us"]), np.array(T_first))
    trials = [json.loads((folder / "registration" / "metrics.json").read_text())["trials"]
              for folder in (out, tmp_path / "demo")]
    assert [t["RTE_mm"] for t in trials[0]] == [t["RTE_mm"] for t in trials[1]]
