"""Benchmark of CT surface extraction on 400^3 label maps: time per stage, triangles, peak memory.

Run: ``.venv/bin/python -m tests.benchmarks.bench_extract_ct``. Two label maps: the CT fibula
voxelized at 1 mm into 400^3 voxels (a long thin bone, as in a leg CT), and an ellipsoid at 0.5 mm
filling most of 400^3 (the worst case: a large surface). Each is meshed by both methods, raw
(no smoothing or decimation) and with the default options. Stage times come from the progress
callback; peak memory is the process's high-water mark so far (ru_maxrss), so it only grows.
"""

from __future__ import annotations

import logging
import resource
import time

import numpy as np

from comreg_core.io import read_mesh
from comreg_core.io.segmentations import Segmentation
from comreg_core.io.volumes import Volume
from comreg_core.surfaces import SurfaceExtractionOptions, extract_bone_surface, voxelize_mesh
from tests.helpers import FIBULA_STL

SIZE = 400
STAGES = ["cropping", "meshing", "smoothing", "decimating", "transforming"]


def fibula_labelmap() -> Segmentation:
    return voxelize_mesh(read_mesh(FIBULA_STL), 1.0, dims=(SIZE,) * 3)


def ellipsoid_labelmap(spacing: float = 0.5) -> Segmentation:
    """Semi-axes 0.48, 0.38, 0.28 of the grid's edge, centred (built slice by slice to keep
    the memory baseline at the 64 MB label map)."""
    axes = np.array([0.48, 0.38, 0.28]) * SIZE
    c = (SIZE - 1) / 2
    i, j = np.ogrid[:SIZE, :SIZE]
    in_plane = ((i - c) / axes[0]) ** 2 + ((j - c) / axes[1]) ** 2
    labels = np.empty((SIZE,) * 3, np.uint8)
    for k in range(SIZE):
        labels[:, :, k] = in_plane + ((k - c) / axes[2]) ** 2 <= 1
    return Segmentation.from_labelmap(Volume.from_geometry(labels, (spacing,) * 3))


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def run(segmentation: Segmentation, options: SurfaceExtractionOptions) -> tuple[dict, int]:
    """Seconds per stage (and "total") and the number of triangles."""
    marks = []
    start = time.perf_counter()
    mesh = extract_bone_surface(segmentation, options=options,
                                progress=lambda f, m: marks.append((m, time.perf_counter())))
    times = {m: t_next - t for (m, t), (_, t_next) in zip(marks, marks[1:])}
    times["total"] = time.perf_counter() - start
    return times, len(mesh.faces)


def main() -> None:
    logging.basicConfig(level=logging.WARNING, format="    %(levelname)s: %(message)s")
    configs = {
        f"{method} {label}": SurfaceExtractionOptions(method=method, **kwargs)
        for method in ("flying_edges", "surface_nets")
        for label, kwargs in [("raw", dict(smoothing=0.0, decimation=0.0)), ("default", {})]
    }
    header = f"{'label map':10s} {'configuration':22s}" + "".join(
        f" {s[:9]:>9s}" for s in [*STAGES, "total"]) + f" {'triangles':>10s} {'peak MiB':>9s}"
    for name, build in [("fibula", fibula_labelmap), ("ellipsoid", ellipsoid_labelmap)]:
        t = time.perf_counter()
        segmentation = build()
        voxels = int((segmentation.layers != 0).sum())
        print(f"\n{name}: {SIZE}^3 voxels of {segmentation.ijk_to_space[0, 0]} mm, {voxels} "
              f"inside, built in {time.perf_counter() - t:.1f} s; peak so far {peak_mib():.0f} MiB")
        print(header)
        for config, options in configs.items():
            times, triangles = run(segmentation, options)
            print(f"{name:10s} {config:22s}" + "".join(
                f" {times.get(s, 0.0):9.2f}" for s in [*STAGES, "total"])
                + f" {triangles:10d} {peak_mib():9.0f}", flush=True)


if __name__ == "__main__":
    main()
