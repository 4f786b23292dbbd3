"""Issue 15, bad inputs: a corrupt or truncated image in any US input (frame folders, masks,
PLUS sequences, volumes) ends ``comreg extract-us`` with one line naming the file, exit status 2,
and nothing written (split from ``test_reliability.py``)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from comreg_core.demo import SAMPLE_SWEEP
from tests.helpers import SHARED_DATA, paths_under

PLUS_IMAGES = SHARED_DATA / "plus" / "TestImages"
NWIRE_XML = SHARED_DATA / "plus" / "ConfigFiles" / "Testing" / \
    "PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml"


def _cut_in_half(path: Path) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _sample_frames(folder: Path, ext: str, n: int = 3) -> list[Path]:
    """The first ``n`` frames of the sample sweep as a frame folder of ``ext`` images."""
    from PIL import Image

    (folder / "frames").mkdir(parents=True)
    lines = (SAMPLE_SWEEP / "tracking.csv").read_text().splitlines()
    (folder / "tracking.csv").write_text("\n".join(lines[:n + 1]) + "\n")
    shutil.copy(SAMPLE_SWEEP / "calibration.json", folder)
    names = [line.split(",")[0] for line in lines[1:n + 1]]
    for name in names:
        Image.open(SAMPLE_SWEEP / "frames" / f"{name}.png").save(folder / "frames" / f"{name}{ext}")
    return [folder / "frames" / f"{name}{ext}" for name in names]


def _truncated_us_input(case: str, root: Path) -> tuple[list, Path]:
    """``(extract-us arguments, the file cut in half)``: real images with one cut short."""
    from comreg_core.io import read_volume, write_volume

    root.mkdir()
    if case in ("frames.png", "frames.jpg"):
        frames = _sample_frames(root / "sweep", case[-4:])
        return [root / "sweep"], _cut_in_half(frames[1])
    if case == "masks.png":
        frames = _sample_frames(root / "sweep", ".png")
        (root / "masks").mkdir()
        for frame in frames:
            shutil.copy(frame, root / "masks")
        return [root / "sweep", "--masks", root / "masks"], _cut_in_half(root / "masks" /
                                                                         frames[2].name)
    if case.startswith("sequence"):
        path = root / f"{case}"
        path.write_bytes((PLUS_IMAGES / f"NwirePhantomFreehand{case[8:]}").read_bytes())
        return [path, "--calibration", NWIRE_XML], _cut_in_half(path)
    source = PLUS_IMAGES / "NwirePhantomFreehandReconstructed.mha"
    path = write_volume(read_volume(source), root / case)  # volume.mha or volume.nrrd
    return [path], _cut_in_half(path)


@pytest.mark.parametrize("case", ["frames.png", "frames.jpg", "masks.png", "sequence.igs.mha",
                                  "sequence.igs.nrrd", "volume.mha", "volume.nrrd"])
def test_a_truncated_us_image_exits_2_naming_the_file(tmp_path, shared_data, case):
    """In a subprocess: a truncated PNG frame used to kill 'extract-us' with a segmentation
    fault (libpng: Read Error) and a truncated JPEG was read as garbage. Every US input now
    ends with one line naming the file, exit status 2, and nothing written."""
    args, bad = _truncated_us_input(case, tmp_path / "in")
    out = tmp_path / "out"
    compound = [] if case.startswith("volume") else ["--compound", out / "compound.nrrd"]
    before = paths_under(tmp_path)
    done = subprocess.run([sys.executable, "-m", "comreg_core.cli", "extract-us",
                           *map(str, [*args, "--out", out / "points.ply", *compound])],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, (done.returncode, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: Cannot read "), done.stderr
    assert f"'{bad}'" in lines[0] and "truncated" in lines[0], lines[0]
    assert paths_under(tmp_path) == before
