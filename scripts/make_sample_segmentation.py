"""Rebuild resources/sample/fibula.seg.nrrd from the UltraBones100k CT fibula mesh (CC BY 4.0).

The bundled sample is a 3D Slicer segmentation made by voxelizing the CT bone model, so that the
README's main command has a real label map to work on. Run from the repository root:

    .venv/bin/python scripts/make_sample_segmentation.py [--spacing 0.8]
"""

import argparse
from pathlib import Path

from comreg_core.io import read_mesh, write_segmentation
from comreg_core.io.segmentations import Segment
from comreg_core.surfaces import voxelize_mesh

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT.parent / "shared" / "data" / "ultrabones100k-fibula" / "fibula.stl"
TARGET = ROOT / "resources" / "sample" / "fibula.seg.nrrd"

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--spacing", type=float, default=0.8, help="voxel size in mm")
args = parser.parse_args()

segmentation = voxelize_mesh(read_mesh(SOURCE), args.spacing, margin=3.0)
segmentation.segments = [Segment("fibula", 1, color=(0.95, 0.9, 0.75))]
write_segmentation(segmentation, TARGET)
print(f"wrote {TARGET} ({TARGET.stat().st_size / 1024:.0f} KiB), grid "
      f"{segmentation.layers.shape[1:]} at {args.spacing} mm")
