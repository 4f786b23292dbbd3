"""Bone points from reconstructed 3D US volumes: the shared fibula sweep compounded at 0.5 mm
(the project's own compounding) against its CT, PLUS's own reconstructed spine-phantom volume
against the points from its frames, a label volume, and bad inputs through the CLI."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from comreg_core.cli import app
from comreg_core.io.volumes import Volume, read_volume, write_volume
from comreg_core.registration.geometry.surface import CTSurface
from comreg_core.surfaces.us_volume import (NotAUsVolumeError, check_us_volume,
                                            extract_volume_surface, is_volume_file)
from tests.helpers import FIBULA_STL, SHARED_DATA

PLUS = SHARED_DATA / "plus"
SPINE_VOLUME = PLUS / "TestImages" / "SpinePhantomFreehandReconstructed.mha"


def _angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) /
                                              np.linalg.norm(b), -1.0, 1.0))))


def _mean_direction(vectors: np.ndarray) -> np.ndarray:
    mean = (vectors / np.linalg.norm(vectors, axis=1, keepdims=True)).mean(axis=0)
    return mean / np.linalg.norm(mean)


@pytest.fixture(scope="module")
def fibula(tmp_path_factory, shared_data):
    """The shared fibula sweep, compounded at 0.5 mm, written and read back as NRRD; the bone
    points extracted from the volume alone (beam direction ``auto``)."""
    from comreg_core.io.tracked_us import read_tracked_sweep
    from comreg_core.surfaces.us_compounding import compound_sweep

    sweep = read_tracked_sweep(shared_data / "ultrabones100k-fibula")
    path = write_volume(compound_sweep(sweep, 0.5), tmp_path_factory.mktemp("vol") / "fib.nrrd")
    volume = read_volume(path)
    result, slices = extract_volume_surface(volume)
    return sweep, path, result, slices


def test_compounded_fibula_volume_gives_points_on_the_ct(fibula):
    sweep, _, result, slices = fibula
    # the beam found from the volume alone: the frames' mean beam within a few degrees
    frames_beam = _mean_direction(sweep.T_ref_image[sweep.valid][:, :3, 1])
    assert _angle_deg(slices.T_ref_image[0][:3, 1], frames_beam) < 5.0  # measured 2 deg
    distance = CTSurface(FIBULA_STL).distance(result.points.points)
    # measured: 6,566 points, median 0.57 mm, p90 2.82 mm (frames: 0.42 / 1.21 mm)
    assert len(distance) > 3000
    assert np.median(distance) <= 1.0 and np.percentile(distance, 90) <= 3.0


def test_registration_from_volume_points_lands_where_frame_points_do(fibula):
    from comreg_core.register import Registrar
    from comreg_core.registration.geometry.metrics import registration_metrics
    from comreg_core.simulation import sample_initial_pose
    from comreg_core.surfaces.us import extract_us_surface
    from comreg_core.transforms import apply_transform

    sweep, _, result, _ = fibula
    search = Registrar.from_ct(FIBULA_STL)
    clouds = {"volume": result.points.points, "frames": extract_us_surface(sweep).points.points}
    poses = {}
    for name, points in clouds.items():
        T_moved = sample_initial_pose(np.random.default_rng(0), "paper",
                                      center=points.mean(axis=0))
        poses[name] = search.register(apply_transform(T_moved, points)).T_ct_us @ T_moved
        errors = registration_metrics(poses[name], np.eye(4), points, FIBULA_STL)
        assert errors["RTE_mm"] < 4.0 and errors["RRE_deg"] < 5.0, (name, errors)
    between = registration_metrics(poses["volume"], poses["frames"], clouds["frames"], FIBULA_STL)
    # measured: volume 2.12 mm / 2.41 deg, frames 3.24 mm / 2.90 deg from the recorded tracking
    # (its own offset is about 3 mm); between them 1.29 mm / 0.53 deg
    assert between["RTE_mm"] < 2.0 and between["RRE_deg"] < 1.0, between


def test_plus_reconstructed_spine_volume_points_lie_where_its_frames_see_bone(shared_data):
    """PLUS's own hole-filled reconstruction of SpinePhantomFreehand: the points from the
    volume lie on the bright surfaces the frame detector finds in its 21 frames."""
    from comreg_core.io.plus_sequences import read_plus_sequence
    from comreg_core.surfaces.us import extract_us_surface

    assert is_volume_file(SPINE_VOLUME)
    result, slices = extract_volume_surface(read_volume(SPINE_VOLUME))
    sweep = read_plus_sequence(
        PLUS / "TestImages" / "SpinePhantomFreehand.igs.mha",
        calibration=PLUS / "ConfigFiles" / "Testing" /
        "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml")
    assert not is_volume_file(PLUS / "TestImages" / "SpinePhantomFreehand.igs.mha")
    frames = extract_us_surface(sweep).points.points
    frames_beam = _mean_direction(sweep.T_ref_image[sweep.valid][:, :3, 1])
    assert _angle_deg(slices.T_ref_image[0][:3, 1], frames_beam) < 20.0  # measured 15 deg
    distance, _ = cKDTree(frames).query(result.points.points)
    assert len(distance) >= 30 and np.median(distance) <= 1.0  # measured 54, 0.70 mm


def test_a_label_volume_gives_its_top_surface_along_the_beam(tmp_path):
    """A ball labelled 1 in a 0.5 mm volume (RAS, axes tilted): with the beam along -z (voxel
    axis k backwards), the points are the ball's surface facing +k, within a voxel."""
    n, spacing, radius = 60, 0.5, 10.0
    centre_ijk = np.array([30.0, 30.0, 30.0])
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1)
    labels = (np.linalg.norm(ijk - centre_ijk, axis=-1) * spacing <= radius).astype(np.uint8)
    c, s = np.cos(0.3), np.sin(0.3)
    M = np.eye(4)
    M[:3, :3] = spacing * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    M[:3, 3] = [5.0, -3.0, 2.0]
    path = write_volume(Volume(labels, M, "RAS"), tmp_path / "ball.nrrd")
    result, _ = extract_volume_surface(read_volume(path), "-z")
    points = result.points.points
    centre = M[:3, :3] @ centre_ijk + M[:3, 3]
    along_k = (points - centre) @ (M[:3, 2] / spacing)
    assert len(points) > 300
    assert np.all(along_k > 0)  # the side the beam comes from (+k, as it runs along -k)
    assert np.abs(np.linalg.norm(points - centre, axis=1) - radius).max() < 2 * spacing
    with pytest.raises(NotAUsVolumeError, match="label volume"):
        extract_volume_surface(read_volume(path))  # auto: no echoes to tell the beam by


def test_bad_volumes_are_clear_errors(tmp_path):
    import nrrd

    runner = CliRunner()
    flat = np.zeros((40, 40, 40), np.uint8)
    cases = {
        "zeros.nrrd": (flat, {"space": "left-posterior-superior",
                              "space directions": np.eye(3) * 0.5,
                              "space origin": np.zeros(3)}, "same value"),
        "image2d.nrrd": (np.full((40, 40), 9, np.uint8), {}, "3D"),
        "nospace.nrrd": (np.arange(64000, dtype=np.uint8).reshape(40, 40, 40), {},
                         "space"),
    }
    for name, (array, header, message) in cases.items():
        nrrd.write(str(tmp_path / name), array, header, index_order="F")
        result = runner.invoke(app, ["extract-us", str(tmp_path / name), "--out",
                                     str(tmp_path / f"{name}.ply")])
        assert result.exit_code == 2 and message in result.output, (name, result.output)
        assert len(result.output.strip().splitlines()) <= 2 and "Traceback" not in result.output
        assert not (tmp_path / f"{name}.ply").exists()
    good = tmp_path / "spine.mha"
    good.write_bytes(SPINE_VOLUME.read_bytes())
    for extra, message in ((["--beam-direction", "up"], "Unknown beam direction"),
                           (["--masks", str(tmp_path)], "--masks is for tracked frames")):
        result = runner.invoke(app, ["extract-us", str(good), "--out", str(tmp_path / "o.ply"),
                                     *extra])
        assert result.exit_code == 2 and message in result.output, result.output
        assert not (tmp_path / "o.ply").exists()
    with pytest.raises(NotAUsVolumeError, match="at least 3 voxels"):
        check_us_volume(Volume(np.ones((2, 40, 40)), np.eye(4)))


def test_a_beam_direction_for_a_sweep_of_frames_is_refused(tmp_path, shared_data):
    """A sweep of frames has its beam in each frame's pose: --beam-direction, a volume's
    option, is refused for it (a direction or a name that is none) before any work."""
    sweep = SHARED_DATA / "ultrabones100k-fibula"
    for direction, message in (("-z", "--beam-direction is for a reconstructed volume"),
                               ("nonsense", "Unknown beam direction 'nonsense'")):
        result = CliRunner().invoke(app, ["extract-us", str(sweep), "--out",
                                          str(tmp_path / "out" / "us.ply"),
                                          "--beam-direction", direction])
        assert result.exit_code == 2 and message in result.output, result.output
        assert len(result.output.strip().splitlines()) == 1, result.output
        assert not (tmp_path / "out").exists()


def test_extract_us_writes_a_volume_s_points_with_beam_origins(tmp_path, shared_data):
    from comreg_core.io import read_points

    result = CliRunner().invoke(app, ["extract-us", str(SPINE_VOLUME), "--out",
                                      str(tmp_path / "spine.ply")])
    assert result.exit_code == 0, result.output
    cloud = read_points(tmp_path / "spine.ply")
    assert len(cloud.points) >= 30 and cloud.beam_origins is not None
    # every echo lies below its beam origin along the beam
    volume_result, slices = extract_volume_surface(read_volume(SPINE_VOLUME))
    beam = slices.T_ref_image[0][:3, 1]
    assert np.all((cloud.points - cloud.beam_origins) @ beam > 0)
    np.testing.assert_allclose(cloud.points, volume_result.points.points, atol=1e-6)
