"""Medical file I/O. Each reader returns a small typed object with its spatial metadata; each
writer is atomic (temporary file, then rename).

- meshes: :func:`read_mesh` / :func:`write_mesh` -> :class:`SurfaceMesh`
- point clouds: :func:`read_points` / :func:`write_points` -> :class:`PointCloud`
- volumes and label maps: :func:`read_volume` / :func:`write_volume` -> :class:`Volume`;
  :func:`read_segmentation` / :func:`write_segmentation` -> :class:`Segmentation`
- tracked ultrasound sweeps: :func:`read_tracked_sweep` -> :class:`TrackedSweep` (PLUS sequences,
  frame folders, 3D Slicer volume sequences)
- rigid transforms: :func:`load_transform` / :func:`save_transform` (point-mapping ``T_to_from``),
  :func:`read_itk_transform` / :func:`write_itk_transform` (the raw ITK file content)
- 3D Slicer markups (landmarks, ``.mrk.json``, ``.fcsv``): :func:`read_markups` -> :class:`Markups`
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from comreg_core.errors import UnsupportedFormatError
from comreg_core.io._files import file_extension, require_input_file
from comreg_core.io.markups import MARKUPS_EXTENSIONS, Markups, read_markups
from comreg_core.io.meshes import MESH_EXTENSIONS, SurfaceMesh, read_mesh, write_mesh
from comreg_core.io.pointclouds import (POINT_CLOUD_EXTENSIONS, PointCloud, read_points,
                                        write_points)
from comreg_core.io.segmentations import (SEGMENTATION_READ_EXTENSIONS, Segment, Segmentation,
                                          read_segmentation, write_segmentation)
from comreg_core.io.sweeps import TrackedSweep
from comreg_core.io.tracked_us import read_tracked_sweep
from comreg_core.io.transform_files import (TRANSFORM_EXTENSIONS, ItkTransformFile,
                                            load_transform, read_itk_transform, save_transform,
                                            write_itk_transform)
from comreg_core.io.volumes import VOLUME_READ_EXTENSIONS, Volume, read_volume, write_volume

__all__ = [
    "MARKUPS_EXTENSIONS", "MESH_EXTENSIONS", "Markups", "POINT_CLOUD_EXTENSIONS",
    "SEGMENTATION_READ_EXTENSIONS", "TRANSFORM_EXTENSIONS", "VOLUME_READ_EXTENSIONS",
    "ItkTransformFile", "PointCloud", "Segment", "Segmentation", "SurfaceMesh", "TrackedSweep",
    "Volume", "describe_file", "load_transform", "read_itk_transform", "read_markups",
    "read_mesh", "read_points", "read_segmentation", "read_tracked_sweep", "read_volume",
    "save_transform", "write_itk_transform", "write_mesh", "write_points", "write_segmentation",
    "write_volume",
]


def describe_file(path: str | Path) -> str:
    """A few human-readable lines on what ComReg reads from ``path`` (kind, size, geometry)."""
    path = require_input_file(path)
    ext = file_extension(path)
    fmt = lambda values: " ".join(f"{v:.6g}" for v in np.ravel(values))  # noqa: E731
    if ext in SEGMENTATION_READ_EXTENSIONS or Path(path).suffix.lower() in VOLUME_READ_EXTENSIONS:
        seg = read_segmentation(path) if ext == ".seg.nrrd" else None
        if seg is None:
            volume = read_volume(path)
            lines = [f"volume {path}", f"  size (i j k): {fmt(volume.array.shape)}  "
                     f"type: {volume.array.dtype}  values: {fmt([volume.array.min(), volume.array.max()])}"]
            geometry = volume
        else:
            lines = [f"segmentation {path}", f"  size (i j k): {fmt(seg.layers.shape[1:])}  "
                     f"layers: {seg.layers.shape[0]}"]
            lines += [f"  segment '{s.name}' (id {s.id}): label {s.label_value}, layer {s.layer}"
                      for s in seg.segments]
            geometry = seg.geometry(seg.layers[0])
        lines += [f"  space: {geometry.space}", f"  spacing (mm): {fmt(geometry.spacing)}",
                  f"  origin (mm): {fmt(geometry.origin)}",
                  f"  directions (columns i j k): {fmt(geometry.directions)}"]
        return "\n".join(lines)
    if ext in MESH_EXTENSIONS:
        mesh = read_mesh(path)
        lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
        return (f"mesh {path}\n  vertices: {len(mesh.vertices)}  triangles: {len(mesh.faces)}\n"
                f"  space: {mesh.space}\n  bounds (mm): min {fmt(lo)}  max {fmt(hi)}")
    if ext in POINT_CLOUD_EXTENSIONS:
        cloud = read_points(path)
        lo, hi = cloud.points.min(0), cloud.points.max(0)
        return (f"point cloud {path}\n  points: {len(cloud.points)}\n  space: {cloud.space}\n"
                f"  bounds (mm): min {fmt(lo)}  max {fmt(hi)}")
    if ext in TRANSFORM_EXTENSIONS:
        content = read_itk_transform(path)
        return (f"transform {path}\n  ITK type: {content.transform_type}\n"
                f"  file matrix (LPS, resampling direction):\n"
                + "\n".join(f"    {fmt(row)}" for row in content.matrix)
                + "\n  as a point mapping (e.g. T_ct_us), LPS:\n"
                + "\n".join(f"    {fmt(row)}" for row in load_transform(path)))
    if ext in (".mrk.json", ".fcsv"):
        markups = read_markups(path)
        return (f"markups (landmarks) {path}\n  points: {len(markups.labels)}  space: "
                f"{markups.space}\n" + "\n".join(
                    f"  '{label}': {fmt(point)}" + ("" if tol is None else f" (tol {tol:g} mm)")
                    for label, point, tol in zip(markups.labels, markups.points,
                                                 markups.tolerances_mm)))
    supported = sorted({*MESH_EXTENSIONS, *POINT_CLOUD_EXTENSIONS, *SEGMENTATION_READ_EXTENSIONS,
                        *TRANSFORM_EXTENSIONS, ".mrk.json", ".fcsv"})
    raise UnsupportedFormatError(path, "file", supported)
