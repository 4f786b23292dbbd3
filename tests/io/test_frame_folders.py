"""Frame folders (UltraBones100k layout) against the documented calibration chain, with missing,
extra and bad frames."""

from __future__ import annotations

import json
import logging
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from comreg_core.errors import CorruptFileError, InputFileNotFoundError
from comreg_core.io.frame_folders import (FRAME_IMAGE_EXTENSIONS, read_frame_folder,
                                          read_frame_folder_tracking, read_frame_image)
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


def copy_folder(tmp_path: Path, n: int, source: Path = FIBULA_DIR, ext: str = ".png") -> Path:
    """A frame folder with the first ``n`` frames of the sweep in ``source`` (default: the
    fibula sweep), its PNG frames saved as ``ext`` images."""
    from PIL import Image

    folder = tmp_path / "sweep"
    (folder / "frames").mkdir(parents=True)
    lines = (source / "tracking.csv").read_text().splitlines()
    (folder / "tracking.csv").write_text("\n".join(lines[:n + 1]) + "\n")
    shutil.copy(source / "calibration.json", folder)
    for line in lines[1:n + 1]:
        name = line.split(",")[0]
        if ext == ".png":
            shutil.copy(source / "frames" / f"{name}.png", folder / "frames")
        else:
            Image.open(source / "frames" / f"{name}.png").save(folder / "frames" / f"{name}{ext}")
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


# --- frame images: every format, decoded by a reader that reports damage -----------------------

SAMPLE_SWEEP = Path(__file__).resolve().parents[2] / "resources" / "sample" / "sweep"


def sample_folder(tmp_path: Path, n: int = 3, ext: str = ".png") -> Path:
    """A frame folder with the first ``n`` frames of the bundled sample sweep (475 x 405 px
    grey PNGs), saved as ``ext`` images."""
    return copy_folder(tmp_path, n, SAMPLE_SWEEP, ext)


def cut_in_half(path: Path) -> Path:
    """Keep the first half of ``path``'s bytes: a file whose copy or download stopped."""
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


@pytest.mark.parametrize("ext", FRAME_IMAGE_EXTENSIONS)
def test_a_truncated_frame_image_is_a_corrupt_file(tmp_path, ext):
    """VTK's PNG reader crashed the process on a truncated PNG; its JPEG, BMP, TIFF and PNM
    readers filled the missing rows with garbage. Every format now fails naming the file."""
    folder = sample_folder(tmp_path, 3, ext)
    bad = cut_in_half(sorted((folder / "frames").iterdir())[1])
    with pytest.raises(CorruptFileError, match=re.escape(bad.name) + ".*truncated"):
        read_frame_folder(folder)
    with pytest.raises(CorruptFileError, match=re.escape(bad.name)) as caught:
        read_frame_image(bad)
    assert caught.value.path == bad


def test_damaged_and_non_image_frames_are_corrupt_files(tmp_path):
    from PIL import Image

    frame = sorted((SAMPLE_SWEEP / "frames").iterdir())[0]
    data = bytearray(frame.read_bytes())
    data[len(data) // 2: len(data) // 2 + 64] = bytes(64)  # full length, a damaged IDAT chunk
    cases = {"damaged.png": bytes(data), "empty.png": b"", "text.png": b"timestamp,x,y,z\n",
             "cut_header.jpg": b"\xff\xd8\xff\xe0\x00"}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(CorruptFileError, match=re.escape(name)):
            read_frame_image(tmp_path / name)
    pages = [Image.open(frame), Image.open(frame)]
    pages[0].save(tmp_path / "pages.tif", save_all=True, append_images=pages[1:])
    with pytest.raises(CorruptFileError, match="2D frame was expected"):
        read_frame_image(tmp_path / "pages.tif")


def test_frame_images_of_every_format_read_the_same_pixels(tmp_path):
    """Row 0 at the top in every format (VTK's reader turned TIFF frames upside down), colour
    as luminance, grey + alpha and palettes as grey, 16-bit PGM as uint16."""
    from PIL import Image

    frame = sorted((SAMPLE_SWEEP / "frames").iterdir())[0]
    grey = np.asarray(Image.open(frame))
    assert np.array_equal(read_frame_image(frame), grey)
    image = Image.fromarray(grey)
    for name, saved in [("f.bmp", image), ("f.tif", image), ("f.tiff", image), ("f.pgm", image),
                        ("f.pnm", image), ("rgb.png", image.convert("RGB")),
                        ("la.png", image.convert("LA")), ("p.png", image.convert("P"))]:
        saved.save(tmp_path / name)
        assert np.array_equal(read_frame_image(tmp_path / name), grey), name
    Image.fromarray(grey.astype(np.uint16) * 257).save(tmp_path / "deep.pgm")
    deep = read_frame_image(tmp_path / "deep.pgm")
    assert deep.dtype == np.uint16 and np.array_equal(deep, grey.astype(np.uint16) * 257)
    image.save(tmp_path / "f.jpg", quality=95)
    jpeg = read_frame_image(tmp_path / "f.jpg")
    assert jpeg.shape == grey.shape and np.abs(jpeg.astype(int) - grey).mean() < 2
