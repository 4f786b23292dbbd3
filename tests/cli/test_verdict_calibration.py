"""`comreg register --verdict-calibration FILE`: result.json gets p_correct (the calibration's
figure for the result's own margin and extent), the competitor and the calibration's record;
a file that is not a calibration is refused before any work."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from comreg_core.cli import app
from comreg_core.io import PointCloud, write_points
from comreg_core.registration.judgement.calibration import Calibration, fit_calibration
from comreg_core.transforms import apply_transform
from tests.helpers import FIBULA_STL

runner = CliRunner()


@pytest.fixture(scope="module")
def short_sweep(tmp_path_factory, shared_data):
    """A 40-50 mm simulated one-face sweep of the fibula, moved by a known pose."""
    from comreg_core.config import from_dict
    from comreg_core.simulation.config import SimulationConfig
    from tests.benchmarks.bench_partial import PARTIAL_SWEEPS, simulated_runs

    config = from_dict(SimulationConfig, PARTIAL_SWEEPS, "simulation")
    points, origins = simulated_runs(FIBULA_STL, 1, 11, config)[0]
    T = np.eye(4)
    T[:3, 3] = [20.0, -10.0, 5.0]
    folder = tmp_path_factory.mktemp("calibrated")
    path = write_points(PointCloud(apply_transform(T, points), "LPS",
                                   beam_origins=apply_transform(T, origins)), folder / "us.ply")
    return folder, path


def test_register_reports_p_correct_from_the_calibration_given(short_sweep):
    folder, us = short_sweep
    rng = np.random.default_rng(0)
    p_raw = rng.uniform(0, 1, 60)
    calibration = fit_calibration(p_raw, rng.uniform(0, 1, 60) < p_raw ** 2, ct_length_mm=404.0)
    path = calibration.save(folder / "calibration.json")
    out = folder / "reg"
    result = runner.invoke(app, ["register", str(us), "--ct", str(FIBULA_STL), "--out", str(out),
                                 "--verdict-calibration", str(path)])
    assert result.exit_code == 0, result.output
    saved = json.loads((out / "result.json").read_text())
    competitor = saved["competitor"]
    assert 0.0 <= competitor["margin"] <= 1.0 and 0.0 < saved["extent_share"] < 0.5
    p_raw = saved["uncertainty"]["p_raw"]
    assert p_raw == pytest.approx(saved["uncertainty"]["p_local"] * saved["uncertainty"]["p_basin"])
    expected = Calibration.load(path).p_correct(p_raw)
    assert saved["p_correct"] == pytest.approx(expected, abs=1e-12)
    assert saved["verdict_figures"]["p_correct"] == pytest.approx(expected, abs=1e-12)
    assert saved["verdict_calibration"]["sweeps"] == 60
    assert (saved["verdict"] == "ok") == (expected >= 0.95 and not saved["verdict_reasons"])
    if competitor["name"] is not None:  # a clinically different pose: beyond 4 mm or 5 deg
        assert competitor["distance_mm"] > 4.0 or competitor["rotation_deg"] > 5.0


def test_a_file_that_is_not_a_calibration_is_refused_before_any_work(short_sweep):
    folder, us = short_sweep
    bad = folder / "not_a_calibration.json"
    bad.write_text(json.dumps({"weights": [0, 1]}))
    out = folder / "refused"
    result = runner.invoke(app, ["register", str(us), "--ct", str(FIBULA_STL), "--out", str(out),
                                 "--verdict-calibration", str(bad)])
    assert result.exit_code == 2
    assert "not a ComReg calibration" in result.output and not out.exists()


def test_pretrain_calibrates_for_the_kind_of_prior_given(short_sweep, tmp_path):
    """`pretrain --calibration-sweeps 4 --calibration-prior landmark` writes the run's own
    calibration for registrations within landmarks: a registration with this run and no prior is
    then refused, before any work (it would be over-rated)."""
    import yaml

    from tests.training.tiny import TINY

    _, us = short_sweep
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY))
    run = tmp_path / "run"
    result = runner.invoke(app, ["pretrain", str(FIBULA_STL), "--out", str(run), "--epochs", "1",
                                 "--config", str(config), "--device", "cpu",
                                 "--calibration-sweeps", "4", "--calibration-prior", "landmark"])
    assert result.exit_code == 0, result.output
    assert "'landmark'" in result.stdout
    calibration = Calibration.load(run / "calibration.json")
    assert calibration.prior_kind == "landmark" and calibration.sweeps == 4
    out = tmp_path / "reg"
    result = runner.invoke(app, ["register", str(us), "--model", str(run), "--out", str(out)])
    assert result.exit_code == 2 and "landmark" in result.stderr, result.output
    assert len(result.stderr.strip().splitlines()) == 1 and not out.exists()
