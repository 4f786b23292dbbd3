"""B-mode bone detector benchmark: frames per second on real sweeps, and its accuracy on the
UltraBones100k fibula sweep.

Run from the repository root::

    .venv/bin/python -m tests.benchmarks.bench_us_detector [--repeats 3] [--no-accuracy]
        [--keep-freed-memory]

Frames per second of :func:`detect_bone_surface` (evidence maps + dynamic programme + subpixel
refinement) on the fibula frames (950 x 811 px at 0.054 mm, worked at 0.108 mm) and on PLUS's
SpinePhantomFreehand frames (820 x 616 px at 0.085 mm, worked at full resolution), in this
process with BLAS/OpenMP threads set to 1, and seconds per reconstructed volume (bone points
from a compounded fibula volume and PLUS's spine-phantom reconstruction). Timings on a shared
2-core machine are pessimistic. ``--keep-freed-memory``: as ``comreg live``'s detection workers
run (:func:`~comreg_core.live.background.keep_freed_memory`).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from comreg_core.io.frame_folders import read_frame_folder  # noqa: E402
from comreg_core.io.plus_sequences import read_plus_sequence  # noqa: E402
from comreg_core.surfaces.us import extract_us_surface  # noqa: E402
from comreg_core.surfaces.us_detector import bone_evidence, detect_bone_surface  # noqa: E402
from tests.helpers import FIBULA_STL, SHARED_DATA  # noqa: E402


def _rate(function, frames, spacing, repeats: int) -> float:
    """Best-of-``repeats`` frames per second of ``function(frame, spacing)`` over ``frames``."""
    function(frames[0], spacing)  # warm-up
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for frame in frames:
            function(frame, spacing)
        best = min(best, time.perf_counter() - start)
    return len(frames) / best


def _accuracy(sweep) -> str:
    import trimesh
    import vtk

    result = extract_us_surface(sweep)
    reader = vtk.vtkSTLReader()
    reader.SetFileName(str(FIBULA_STL))
    reader.Update()
    distance = vtk.vtkImplicitPolyDataDistance()
    distance.SetInput(reader.GetOutput())
    mesh = trimesh.load(FIBULA_STL)
    H, W = sweep.image_shape
    size = np.array([W, H]) * sweep.spacing
    sees = []
    for f in range(sweep.n_frames):
        T = sweep.T_ref_image[f]
        section = mesh.section(plane_origin=T[:3, 3], plane_normal=T[:3, 2])
        if section is None:
            continue
        local = (np.concatenate([np.linspace(d[:-1], d[1:], 10).reshape(-1, 3)
                                 for d in section.discrete]) - T[:3, 3]) @ T[:3, :3]
        inside = np.all((local[:, :2] >= 0) & (local[:, :2] <= size), axis=1)
        step = np.median(np.linalg.norm(np.diff(local, axis=0), axis=1))
        if inside.sum() * step >= 1.0:
            sees.append(f)
    lines = []
    for name, cloud in (("raw detections", result.raw), ("after denoising", result.points)):
        d = np.abs([distance.EvaluateFunction(*p) for p in cloud.points])
        fraction = np.isin(sees, cloud.frame_index).mean()
        lines.append(f"  {name:16s}: {len(d):6d} points, distance to CT surface median "
                     f"{np.median(d):.2f} mm, p90 {np.percentile(d, 90):.2f} mm, p95 "
                     f"{np.percentile(d, 95):.2f} mm; from {100 * fraction:.0f}% of the "
                     f"{len(sees)} frames that see the bone")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-accuracy", action="store_true")
    parser.add_argument("--keep-freed-memory", action="store_true")
    args = parser.parse_args(argv)
    if args.keep_freed_memory:
        from comreg_core.live.background import keep_freed_memory

        print(f"keep_freed_memory: {keep_freed_memory()}")
    logging.basicConfig(level=logging.ERROR)

    fibula = read_frame_folder(SHARED_DATA / "ultrabones100k-fibula")
    plus = SHARED_DATA / "plus"
    spine = read_plus_sequence(plus / "TestImages" / "SpinePhantomFreehand.igs.mha",
                               calibration=plus / "ConfigFiles" / "Testing" /
                               "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml")
    print(f"cores: {os.cpu_count()} (shared; timings are pessimistic), "
          f"threads: OMP={os.environ.get('OMP_NUM_THREADS')}")
    for name, sweep in (("fibula (UltraBones100k)", fibula), ("spine phantom (PLUS)", spine)):
        H, W = sweep.image_shape
        full = _rate(detect_bone_surface, sweep.frames, sweep.spacing, args.repeats)
        maps = _rate(bone_evidence, sweep.frames, sweep.spacing, args.repeats)
        print(f"{name}: {sweep.n_frames} frames {W} x {H} px at {sweep.spacing[0]:.3f} mm: "
              f"detector {full:.1f} frames/s (evidence maps alone {maps:.1f} frames/s)")
    _volumes(fibula, plus / "TestImages" / "SpinePhantomFreehandReconstructed.mha")
    if not args.no_accuracy:
        print("fibula accuracy (default config):")
        print(_accuracy(fibula))


def _volumes(fibula, spine_volume) -> None:
    """Seconds to get bone points from a reconstructed volume (beam direction auto): the fibula
    sweep compounded at 0.5 mm and PLUS's reconstructed spine-phantom volume."""
    from comreg_core.io.volumes import read_volume
    from comreg_core.surfaces.us_compounding import compound_sweep
    from comreg_core.surfaces.us_volume import extract_volume_surface

    for name, volume in (("fibula compounded at 0.5 mm", compound_sweep(fibula, 0.5)),
                         ("PLUS spine phantom reconstruction", read_volume(spine_volume))):
        start = time.perf_counter()
        result, slices = extract_volume_surface(volume)
        print(f"volume, {name} ({' x '.join(map(str, volume.array.shape))} voxels): "
              f"{time.perf_counter() - start:.1f} s, {slices.n_frames} slices, "
              f"{len(result.points.points)} points")


if __name__ == "__main__":
    main()
