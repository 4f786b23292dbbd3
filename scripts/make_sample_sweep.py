"""Rebuild resources/sample/sweep/ from the UltraBones100k fibula sweep (CC BY 4.0).

The bundled sweep is a small part of the real tracked sweep in ../shared/data: every ``--step``-th
of its 111 frames, each image reduced ``--shrink`` times by averaging pixel blocks (the pixel
spacing grows by the same factor; pixel centres stay where the calibration puts them), with the
matching rows of tracking.csv and an updated calibration.json. Run from the repository root:

    .venv/bin/python scripts/make_sample_sweep.py [--step 3] [--shrink 2]
"""

import argparse
import csv
import json
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT.parent / "shared" / "data" / "ultrabones100k-fibula"
TARGET = ROOT / "resources" / "sample" / "sweep"

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--step", type=int, default=3, help="keep every step-th frame")
parser.add_argument("--shrink", type=int, default=2, help="image reduction factor")
args = parser.parse_args()

calibration = json.loads((SOURCE / "calibration.json").read_text(encoding="utf-8"))
cols, rows = calibration["image_size_px"]
k = args.shrink
calibration["pixel_spacing_mm"] = [s * k for s in calibration["pixel_spacing_mm"]]
calibration["image_size_px"] = [cols // k, rows // k]
with open(SOURCE / "tracking.csv", newline="", encoding="utf-8") as f:
    table = list(csv.DictReader(f))
kept = table[::args.step]

(TARGET / "frames").mkdir(parents=True, exist_ok=True)
for old in (TARGET / "frames").glob("*.png"):
    old.unlink()
for row in kept:
    image = np.asarray(Image.open(SOURCE / "frames" / f"{row['timestamp']}.png").convert("L"),
                       dtype=np.float64)[:rows // k * k, :cols // k * k]
    small = image.reshape(rows // k, k, cols // k, k).mean(axis=(1, 3))
    Image.fromarray(np.round(small).astype(np.uint8)).save(
        TARGET / "frames" / f"{row['timestamp']}.png", optimize=True)
    row["space_factor"] = f"{float(row['space_factor']) * k:.5f}"
with open(TARGET / "tracking.csv", "w", newline="", encoding="utf-8") as f:
    writer = csv.DictWriter(f, list(kept[0]))
    writer.writeheader()
    writer.writerows(kept)
(TARGET / "calibration.json").write_text(json.dumps(calibration, indent=2) + "\n",
                                         encoding="utf-8")
size = sum(p.stat().st_size for p in TARGET.rglob("*") if p.is_file())
print(f"wrote {TARGET}: {len(kept)} frames of {cols // k} x {rows // k} px, {size / 1e6:.1f} MB")
