"""Registration with no pretrained model: the pose search alone (Registrar.from_ct, `comreg
register US --ct CT`, `comreg evaluate --method search`), on the real fibula sweep and known
simulated poses."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from comreg_core.cli import app
from comreg_core.errors import ComRegError
from comreg_core.register import Registrar
from comreg_core.register import register_to_directory
from comreg_core.io import PointCloud, read_mesh, write_points
from comreg_core.registration.geometry.metrics import registration_metrics
from comreg_core.simulation import sample_initial_pose
from comreg_core.transforms import apply_transform, invert_rigid
from tests.helpers import FIBULA_STL

runner = CliRunner()


@pytest.fixture(scope="module")
def real_sweep_beams(shared_data):
    """The shared real fibula sweep's bone points and each one's beam origin (CT frame: the
    recorded tracking); a third of the points: the same pose, a faster test."""
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import extract_us_surface
    from comreg_core.surfaces.us_points import beam_origins

    sweep = read_tracked_sweep(shared_data / "ultrabones100k-fibula")
    points = extract_us_surface(sweep).points
    origins = beam_origins(points.points, sweep.T_ref_image[points.frame_index])
    return points.points[::3], origins[::3]


@pytest.fixture(scope="module")
def real_sweep(real_sweep_beams):
    return real_sweep_beams[0]


@pytest.fixture(scope="module")
def search(shared_data):
    return Registrar.from_ct(FIBULA_STL)


@pytest.mark.parametrize("seed", [0, 1])
def test_real_sweep_from_full_rotation_starts(search, real_sweep, seed):
    """From any rotation up to 180 deg and 500 mm away, the search alone lands where ICP from
    the recorded tracking lands (the recording is ~3 mm off: success on real data is RTE < 4 mm,
    RRE < 5 deg)."""
    T_moved = sample_initial_pose(np.random.default_rng(seed), "full",
                                  center=real_sweep.mean(axis=0))
    moved = apply_transform(T_moved, real_sweep)
    result = search.register(moved)
    errors = registration_metrics(result.T_ct_us, invert_rigid(T_moved), moved, FIBULA_STL)
    assert errors["RTE_mm"] < 4.0 and errors["RRE_deg"] < 5.0, errors
    assert result.search.chosen.startswith("pca") and not result.ambiguous
    assert result.completion_ct.shape == (0, 3) and result.residuals["median"] < 1.0


def test_search_cannot_be_turned_off_and_needs_points(search):
    result = search.register(read_mesh(FIBULA_STL).vertices[::50], search=False)
    assert result.search is not None  # the search is the whole registration
    with pytest.raises(ComRegError, match="at least 6"):
        search.register(np.zeros((4, 3)))


def test_register_and_report_without_a_run(tmp_path, real_sweep):
    us = write_points(PointCloud(real_sweep), tmp_path / "us.ply")
    out = tmp_path / "reg"
    result = runner.invoke(app, ["register", str(us), "--ct", str(FIBULA_STL), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "by the pose search (no network)" in result.output
    assert "short sweep" not in result.output  # a whole cloud keeps the usual search
    saved = json.loads((out / "result.json").read_text())
    assert saved["search"]["patch"] is False
    assert saved["run_dir"] is None and saved["verdict"] == "ok", saved["verdict_reasons"]
    assert not (out / "completion_ct.ply").exists() and "completion_ct" not in saved["files"]
    errors = registration_metrics(np.asarray(saved["T_ct_us"]), np.eye(4), real_sweep,
                                  FIBULA_STL)
    assert errors["RTE_mm"] < 4.0 and errors["RRE_deg"] < 5.0, errors
    result = runner.invoke(app, ["report", str(out)])
    assert result.exit_code == 0, result.output
    assert "none (the pose search alone)" in (out / "report.html").read_text()
    # no CT and no run; --no-search without a network; three positionals: one line, exit 2
    for args in (["register", str(us), "--out", str(tmp_path / "x")],
                 ["register", str(us), "--ct", str(FIBULA_STL), "--no-search", "--out",
                  str(tmp_path / "y")],
                 ["register", str(us), str(us), str(us), "--out", str(tmp_path / "z")],
                 ["register", str(us), "--ct", str(FIBULA_STL), "--sweep",
                  str(tmp_path / "no_sweep"), "--out", str(tmp_path / "w")]):
        result = runner.invoke(app, args)
        assert result.exit_code == 2 and len(result.output.strip().splitlines()) <= 2, \
            result.output
        assert not any((tmp_path / n).exists() for n in "xyzw")
    # --no-hypotheses, the former name of --no-search, is still accepted (and not in the help)
    for flag in ("--no-search", "--no-hypotheses"):
        result = runner.invoke(app, ["register", str(us), "--ct", str(FIBULA_STL), flag,
                                     "--out", str(tmp_path / "v")])
        assert result.exit_code == 2 and "cannot be turned off" in result.output, result.output
    help_text = runner.invoke(app, ["register", "--help"]).output
    assert "--no-search" in help_text and "hypotheses" not in help_text


def test_register_a_short_stretch_of_the_real_sweep(tmp_path, real_sweep):
    """45 mm of the real sweep along the bone is a patch: the CLI says all orientations were
    tried, result.json records it, and it is flagged unless it leads by 0.5."""
    from comreg_core.registration.geometry.surface import principal_frame

    centre, axes = principal_frame(real_sweep)
    along = (real_sweep - centre) @ axes[:, 0]
    stretch = real_sweep[np.abs(along - 60.0) < 22.5]
    us = write_points(PointCloud(stretch), tmp_path / "short.ply")
    out = tmp_path / "short"
    result = runner.invoke(app, ["register", str(us), "--ct", str(FIBULA_STL), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "(a short sweep: all orientations tried)" in result.output
    saved = json.loads((out / "result.json").read_text())
    search = saved["search"]
    assert search["patch"] is True and search["starts_tried"] > 3000
    assert saved["ambiguous"] == (search["confidence"] < 0.5)


def test_evaluate_search_without_a_run(tmp_path, real_sweep):
    us = write_points(PointCloud(real_sweep), tmp_path / "us.ply")
    result = runner.invoke(app, ["evaluate", str(us), "--ct", str(FIBULA_STL), "--out",
                                 str(tmp_path / "ev"), "--trials", "2", "--method", "search",
                                 "--method", "icp-gt", "--perturbation", "full"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert list(metrics["summary"]) == ["search", "icp-gt"]
    rows = [r for r in metrics["trials"] if r["method"] == "search"]
    assert all(r["RTE_mm"] < 4.0 and r["RRE_deg"] < 5.0 for r in rows), rows
    assert metrics["summary"]["search"]["ambiguous_rate"] == 0.0
    result = runner.invoke(app, ["evaluate", str(us), "--ct", str(FIBULA_STL), "--out",
                                 str(tmp_path / "ev2"), "--method", "comreg"])
    assert result.exit_code == 2 and "--model RUN_DIR" in result.output
    with pytest.raises(ComRegError, match="no CT mesh and no pretrained run"):
        register_to_directory(None, us, tmp_path / "none")


def test_beam_origins_lie_above_the_bone_and_keep_the_pose(search, real_sweep_beams):
    """Each echo's beam starts at the transducer face, outside the bone, 5-45 mm above its
    echo (the image depth); with them the search lands at the same pose, the chosen surface
    facing its probe."""
    points, origins = real_sweep_beams
    depth = np.linalg.norm(points - origins, axis=1)
    assert depth.min() > 0.0 and depth.max() < 45.0, (depth.min(), depth.max())
    assert (search.surface.distance(origins) > 2.0).all()  # measured: at least 2.8 mm
    T_moved = sample_initial_pose(np.random.default_rng(5), "paper", center=points.mean(axis=0))
    result = search.register(apply_transform(T_moved, points),
                             beam_origins=apply_transform(T_moved, origins))
    errors = registration_metrics(result.T_ct_us, invert_rigid(T_moved),
                                  apply_transform(T_moved, points), FIBULA_STL)
    assert errors["RTE_mm"] < 4.0 and errors["RRE_deg"] < 5.0, errors
    assert result.search.polish["facing_away"] < 0.1
    with pytest.raises(ComRegError, match="beam origins for"):
        search.register(points, beam_origins=origins[:-1])


def test_extract_us_keeps_beam_origins_and_register_uses_them(tmp_path, shared_data):
    """`comreg extract-us` writes each point's beam origin into the PLY (beam_x/y/z); read
    back, moved with the points, and used by `comreg register` (recorded in result.json)."""
    from comreg_core.io import read_points
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us import extract_us_to_file
    from comreg_core.surfaces.us_points import beam_origins

    sweep = read_tracked_sweep(shared_data / "ultrabones100k-fibula")
    result = extract_us_to_file(sweep, tmp_path / "us.ply")
    cloud = read_points(tmp_path / "us.ply")
    expected = beam_origins(result.points.points, sweep.T_ref_image[result.points.frame_index])
    np.testing.assert_allclose(cloud.beam_origins, expected, atol=1e-9)
    ras = cloud.in_space("RAS")
    np.testing.assert_allclose(ras.beam_origins[:, :2], -expected[:, :2], atol=1e-9)
    out = tmp_path / "reg"
    run = runner.invoke(app, ["register", str(tmp_path / "us.ply"), "--ct", str(FIBULA_STL),
                              "--out", str(out), "--sweep",
                              str(shared_data / "ultrabones100k-fibula")])
    assert run.exit_code == 0, run.output
    saved = json.loads((out / "result.json").read_text())
    assert saved["beam_origins_used"] is True
    assert saved["sweep"]["T_us_ref"] == np.eye(4).tolist()
    # the report draws four of the sweep's frames with the registered CT contour
    assert runner.invoke(app, ["report", str(out)]).exit_code == 0
    frames = sorted(p.name for p in (out / "report_images").glob("frame_*.png"))
    assert len(frames) == 4 and all(n in (out / "report.html").read_text() for n in frames)
    assert saved["search"]["polish"]["facing_away"] < 0.1
    errors = registration_metrics(np.asarray(saved["T_ct_us"]), np.eye(4), cloud.points,
                                  FIBULA_STL)
    assert errors["RTE_mm"] < 4.0 and errors["RRE_deg"] < 5.0, errors
    with pytest.raises(ComRegError, match="beam origins for"):
        PointCloud(cloud.points, beam_origins=cloud.points[:-1])


def test_the_search_gives_the_same_pose_at_any_thread_count(tmp_path, shared_data):
    """Same inputs, same output: the pose search alone run at 1 and at 2 threads (BLAS and
    OpenMP, and numba's threads for the compiled kernels) returns bit-identical transforms."""
    import os
    import subprocess
    import sys

    code = ("import numpy as np, sys\n"
            "from comreg_core.register import Registrar\n"
            "from comreg_core.io import read_mesh\n"
            "from comreg_core.simulation import sample_initial_pose\n"
            "from comreg_core.transforms import apply_transform\n"
            f"ct = read_mesh({str(FIBULA_STL)!r})\n"
            "pts = ct.vertices[::40]\n"
            "T = sample_initial_pose(np.random.default_rng(2), 'full', center=pts.mean(0))\n"
            "r = Registrar.from_ct(ct).register(apply_transform(T, pts))\n"
            "np.save(sys.argv[1], r.T_ct_us)\n")
    results = []
    for threads in ("1", "2"):
        env = {**os.environ, "OMP_NUM_THREADS": threads, "OPENBLAS_NUM_THREADS": threads,
               "MKL_NUM_THREADS": threads, "NUMBA_NUM_THREADS": threads}
        path = tmp_path / f"T{threads}.npy"
        subprocess.run([sys.executable, "-c", code, str(path)], env=env, check=True,
                       capture_output=True)
        results.append(np.load(path))
    assert np.array_equal(results[0], results[1])
