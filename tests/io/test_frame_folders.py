"""Frame folders (UltraBones100k layout) against the documented calibration chain, with missing,
extra and bad frames."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from comreg_core.errors import CorruptFileError, InputFileNotFoundError
from comreg_core.io.frame_folders import read_frame_folder, read_frame_folder_tracking
from comreg_core.io.sweeps import CalibrationMismatchError, NoValidFramesError
from tests.helpers import SHARED_DATA, assert_close

FIBULA_DIR = SHARED_DATA / "ultrabones100k-fibula"


def naive_euler(deg):
    x, y, z = np.radians(deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    Ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    Rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


@pytest.fixture(scope="module")
def fibula(shared_data):
    return read_frame_folder(FIBULA_DIR)


def test_frame_folder_follows_the_documented_chain(fibula):
    from PIL import Image

    cal = json.loads((FIBULA_DIR / "calibration.json").read_text())
    table = np.genfromtxt(FIBULA_DIR / "tracking.csv", delimiter=",", names=True)
    assert fibula.frames.shape == (111, 811, 950) and fibula.valid.all()
    assert fibula.reference == "CT"
    sx, sy = cal["pixel_spacing_mm"]
    T_probe_image = np.eye(4)
    T_probe_image[:3, :3] = naive_euler(cal["image_to_probe"]["euler_xyz_deg"])
    T_probe_image[:3, 3] = cal["image_to_probe"]["translation_mm"]
    for f in (0, 55, 110):
        row = table[f]
        T_ct_probe = np.eye(4)
        T_ct_probe[:3, :3] = naive_euler([row["euler_x"], row["euler_y"], row["euler_z"]])
        T_ct_probe[:3, 3] = [row["x"], row["y"], row["z"]]
        for col, r in [(0, 0), (949, 810), (400, 300)]:
            chain = T_ct_probe @ T_probe_image @ np.diag([sx, sy, 1, 1]) @ [col + .5, r + .5, 0, 1]
            ours = fibula.pixel_to_reference([f], [r], [col])[0]
            assert_close(ours, chain[:3], atol=1e-9, what=f"frame {f} pixel {col},{r}")
        name = fibula.frame_names[f]
        assert name == str(int(row["timestamp"]))
        pil = np.asarray(Image.open(FIBULA_DIR / "frames" / f"{name}.png"))
        assert np.array_equal(fibula.frames[f], pil if pil.ndim == 2 else pil[..., 0])
        assert_close(fibula.timestamps[f], row["timestamp"] / 1000.0, atol=1e-12)


def copy_folder(tmp_path: Path, n: int) -> Path:
    """A frame folder with the first ``n`` frames of the fibula sweep."""
    folder = tmp_path / "sweep"
    (folder / "frames").mkdir(parents=True)
    lines = (FIBULA_DIR / "tracking.csv").read_text().splitlines()
    (folder / "tracking.csv").write_text("\n".join(lines[:n + 1]) + "\n")
    shutil.copy(FIBULA_DIR / "calibration.json", folder)
    for line in lines[1:n + 1]:
        name = line.split(",")[0]
        shutil.copy(FIBULA_DIR / "frames" / f"{name}.png", folder / "frames")
    return folder


def test_frame_folder_missing_and_extra_frames(tmp_path, shared_data, caplog):
    folder = copy_folder(tmp_path, 4)
    names = [line.split(",")[0] for line in
             (folder / "tracking.csv").read_text().splitlines()[1:]]
    (folder / "frames" / f"{names[1]}.png").unlink()  # a tracked frame without its image
    shutil.copy(folder / "frames" / f"{names[0]}.png", folder / "frames" / "999.png")  # untracked
    with caplog.at_level(logging.WARNING):
        sweep = read_frame_folder(folder)
    assert sweep.frame_names == [names[0], names[2], names[3]]
    assert "have no image" in caplog.text and "no tracking row" in caplog.text
    for name in names:
        (folder / "frames" / f"{name}.png").unlink(missing_ok=True)
    with pytest.raises(NoValidFramesError, match="matches"):
        read_frame_folder(folder)


def test_frame_folder_bad_rows_and_calibration(tmp_path, shared_data, caplog):
    folder = copy_folder(tmp_path, 3)
    lines = (folder / "tracking.csv").read_text().splitlines()
    cells = lines[2].split(",")
    cells[3] = "nan"
    lines[2] = ",".join(cells)
    (folder / "tracking.csv").write_text("\n".join(lines) + "\n")
    with caplog.at_level(logging.WARNING):
        sweep = read_frame_folder(folder)
    assert list(sweep.valid) == [True, False, True]
    assert "non-numeric" in caplog.text
    with pytest.raises(CorruptFileError):
        read_frame_folder_tracking(folder / "calibration.json", folder / "calibration.json")
    cal = json.loads((folder / "calibration.json").read_text())
    cal["image_size_px"] = [640, 480]
    (folder / "calibration.json").write_text(json.dumps(cal))
    with pytest.raises(CalibrationMismatchError, match="640 x 480"):
        read_frame_folder(folder)
    del cal["image_to_probe"]
    (folder / "calibration.json").write_text(json.dumps(cal))
    with pytest.raises(CorruptFileError, match="calibration"):
        read_frame_folder(folder)
    with pytest.raises(InputFileNotFoundError):
        read_frame_folder(tmp_path / "nowhere")


def test_realism_loader_uses_the_frame_folder_reader(fibula):
    from comreg_core.simulation.realism import load_tracked_sweep_poses

    poses = load_tracked_sweep_poses(FIBULA_DIR)
    shift = np.eye(4)
    shift[:2, 3] = 0.5 * fibula.spacing
    assert_close(poses.T_ct_image @ shift, fibula.T_ref_image, atol=1e-9)
