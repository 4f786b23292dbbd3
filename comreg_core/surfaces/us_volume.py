"""Bone points from a reconstructed (compounded) 3D ultrasound volume.

3D Slicer's volume reconstruction (SlicerIGT), PLUS's ``VolumeReconstructor``, ``comreg
extract-us --compound`` and 3D probes give one scalar volume instead of tracked frames: the beam
direction of each voxel is lost. This module gives the volume back the shape the frame detector
(:mod:`comreg_core.surfaces.us_detector`) knows, then runs the frame path:

1. **Coverage**: voxels above 0 were imaged; the rest were not (a sparse freehand sweep leaves
   most of its box empty between the frames).
2. **Slice normal**: a freehand sweep's frames are nearly parallel; the coverage then consists of
   thin slabs, and the dominant direction of its gradient (the structure tensor of the coverage
   at 1 mm) is their normal (measured on the shared fibula sweep compounded at 0.5 mm: 4 deg from
   the frames' mean normal). A densely (hole-filled) reconstructed volume is smooth across its
   frames: the direction of least intensity change is taken instead (PLUS's spine phantom:
   15 deg).
3. **Beam direction** (``auto``): echo layers lie across the beam, so in the frame plane the
   intensity changes most along it (the structure tensor of the coverage-normalised intensity),
   and echoes fade with depth, which gives its sign (fibula: 2 deg from the frames' mean beam;
   PLUS spine phantom: 15 deg). Or a volume axis given by the user (``x``, ``-y``, ...: the voxel
   index axes ``i j k`` in the volume's space).
4. **Slices**: the volume resampled (trilinear) on a grid aligned with the slice normal, the beam
   and the third direction, every :data:`SLICE_MM` along the normal; holes between frames filled
   by linear interpolation along the normal (gaps up to :data:`MAX_GAP_MM`); pixels never imaged
   set to their slice's median imaged intensity, so the edge of the imaged region is neither a
   bright ridge nor a shadow. Each slice is a frame, rows along the beam, with its pose.
5. The frame path: the shadow-aware detector and the denoising of
   :func:`~comreg_core.surfaces.us.extract_us_surface`. A label volume (a few integer values,
   bone segmented in the US volume) gives the first labelled voxel along the beam instead.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from comreg_core.errors import ComRegError
from comreg_core.io.sweeps import TrackedSweep
from comreg_core.io.volumes import Volume
from comreg_core.surfaces.us_kernels import fill_slices, may_exceed_zero, reach_of

#: ``--beam-direction`` choices: ``auto`` or a voxel index axis of the volume, either way.
BEAM_DIRECTIONS = ("auto", "x", "-x", "y", "-y", "z", "-z")
#: Distance between the slices cut from the volume, along the slice normal (mm).
SLICE_MM = 1.0
#: Holes between imaged slabs up to this long (mm, along the slice normal) are interpolated.
MAX_GAP_MM = 20.0
#: Coverage whose structure tensor has this share of its energy in one direction is a stack of
#: frame slabs (fibula sweep: 0.93; a dense reconstruction: about 1/3 each).
SLAB_ANISOTROPY = 0.6
#: Detections from a volume's slices below this bone probability are dropped: the weakest
#: echoes of interpolated slices are the least accurate (fibula: keeping score >= 0.15, about
#: three quarters of them, takes p90 from 3.2 to 2.9 mm).
VOLUME_MIN_SCORE = 0.15
#: A volume with at most this many distinct integer values is a label volume.
MAX_LABELS = 16


class NotAUsVolumeError(ComRegError):
    """The volume cannot be a reconstructed ultrasound volume (2D, empty, no geometry)."""


def check_us_volume(volume: Volume) -> None:
    """Refuse what cannot be a reconstructed ultrasound volume: not 3D, fewer than 3 voxels
    along an axis, no usable geometry, or all one value (e.g. all zero)."""
    shape = volume.array.shape
    where = f" '{volume.path}'" if volume.path else ""
    if volume.array.ndim != 3 or min(shape) < 3:
        raise NotAUsVolumeError(f"The volume{where} is {'x'.join(map(str, shape))} voxels: a 3D "
                                "ultrasound volume needs at least 3 voxels along every axis.",
                                "Pass a reconstructed 3D volume (a 2D image is a frame: use a "
                                "tracked sweep).")
    M = volume.ijk_to_space
    spacing = np.linalg.norm(M[:3, :3], axis=0)
    if not np.isfinite(M).all() or (spacing <= 0).any() or abs(np.linalg.det(M[:3, :3])) < 1e-12:
        raise NotAUsVolumeError(f"The volume{where} has no usable spatial geometry (spacing "
                                f"{spacing.tolist()}).", "Export it with its spacing, origin and "
                                "directions (NRRD or MetaImage).")
    if volume.array.dtype.kind == "f" and not np.isfinite(volume.array).all():
        raise NotAUsVolumeError(f"The volume{where} holds NaN or infinite voxels.",
                                "Export the reconstructed B-mode volume again.")
    if float(np.ptp(volume.array)) == 0.0:
        raise NotAUsVolumeError(f"Every voxel of the volume{where} has the same value "
                                f"({volume.array.flat[0]}).",
                                "Pass the reconstructed B-mode volume (or a bone label volume).")


def is_label_volume(volume: Volume) -> bool:
    """Integer voxels with at most :data:`MAX_LABELS` distinct values (0 = background)."""
    array = volume.array
    if array.dtype.kind not in "biu":
        return False
    sample = array.ravel()[:: max(1, array.size // 2_000_000)]  # cheap refusal of B-mode first
    return len(np.unique(sample)) <= MAX_LABELS and len(np.unique(array)) <= MAX_LABELS


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _coarse(volume: Volume, step_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``(voxels (I', J', K') float32, ijk' -> space (4, 4))`` subsampled to about ``step_mm``."""
    spacing = np.linalg.norm(volume.ijk_to_space[:3, :3], axis=0)
    steps = np.maximum(1, np.rint(step_mm / spacing).astype(int))
    array = volume.array[::steps[0], ::steps[1], ::steps[2]].astype(np.float32)
    return array, volume.ijk_to_space @ np.diag([*steps, 1.0])


def sweep_normal(volume: Volume) -> np.ndarray:
    """The unit normal (space) of the frames the volume was compounded from: the normal of the
    imaged slabs of a sparse freehand reconstruction (the dominant direction of the coverage's
    gradient), else the direction along which the intensity changes least (a hole-filled
    reconstruction is smooth across its frames and sharp within them; PLUS's spine phantom:
    15 deg from the frames' mean normal)."""
    array, M = _coarse(volume)
    R = M[:3, :3] / np.linalg.norm(M[:3, :3], axis=0)  # index axes -> space directions
    covered = ndimage.gaussian_filter((array > 0).astype(np.float32), 1.0)
    w, V = np.linalg.eigh(R @ _structure_tensor(covered, covered > 0.02) @ R.T)
    if w.sum() > 0 and w[-1] / w.sum() >= SLAB_ANISOTROPY:
        return _unit(V[:, -1])
    inside = ndimage.binary_erosion(array > 0, iterations=2)
    if not inside.any():
        inside = array > 0
    w, V = np.linalg.eigh(R @ _structure_tensor(ndimage.gaussian_filter(array, 1.0), inside)
                          @ R.T)
    return _unit(V[:, 0])


def _structure_tensor(image: np.ndarray, where: np.ndarray) -> np.ndarray:
    """``(3, 3)`` sum of the outer products of the gradient of ``image`` over ``where``."""
    grad = np.gradient(image)
    return np.array([[float(np.sum(grad[a][where] * grad[b][where])) for b in range(3)]
                     for a in range(3)])


def estimate_beam(volume: Volume, normal: np.ndarray | None) -> np.ndarray:
    """The unit beam direction (space), in the plane normal to ``normal`` when given: the axis
    along which the intensity changes most (echo layers lie across the beam: the largest
    eigenvector of the structure tensor of the coverage-normalised intensity, 1 mm smoothed,
    inside the imaged region), pointing down the mean intensity gradient (echoes fade with
    depth). Fibula sweep compounded at 0.5 mm: 2 deg from the frames' mean beam."""
    array, M = _coarse(volume)
    spacing = np.linalg.norm(M[:3, :3], axis=0)
    R = M[:3, :3] / spacing  # index axes -> space directions
    covered = (array > 0).astype(np.float32)
    weight = ndimage.gaussian_filter(covered, 1.0 / spacing)
    level = np.where(weight > 0.05, ndimage.gaussian_filter(array, 1.0 / spacing)
                     / np.maximum(weight, 1e-6), 0.0)
    inside = (covered > 0) & (ndimage.minimum_filter(weight, size=3) > 0.2)
    if inside.sum() < 100:
        inside = covered > 0
    grad = R @ np.stack([d[inside] for d in np.gradient(level, *spacing)])  # 3 x voxels
    plane = np.eye(3) if normal is None else np.eye(3) - np.outer(normal, normal)
    w, V = np.linalg.eigh(plane @ (grad @ grad.T) @ plane)
    falloff = -(plane @ grad.mean(axis=1))
    if not w[-1] > 0:
        raise NotAUsVolumeError("The volume shows no depth direction (no intensity structure).",
                                "Give --beam-direction (x, -x, y, -y, z or -z).")
    beam = _unit(V[:, -1])
    return beam if beam @ falloff >= 0 else -beam


def check_beam_direction(name: str) -> None:
    """Raise a one-line error unless ``name`` is one of :data:`BEAM_DIRECTIONS`."""
    if name not in BEAM_DIRECTIONS:
        raise ComRegError(f"Unknown beam direction '{name}'.",
                          f"Use one of: {', '.join(BEAM_DIRECTIONS)}.")


def beam_from_name(volume: Volume, name: str) -> np.ndarray:
    """The unit space direction of a voxel index axis (``"x"`` = ``i``, ``"-z"`` = ``-k``)."""
    check_beam_direction(name)
    if name == "auto":
        raise ComRegError("'auto' is not a volume axis.", "Use x, -x, y, -y, z or -z.")
    axis = "xyz".index(name[-1])
    return (-1.0 if name.startswith("-") else 1.0) * _unit(volume.ijk_to_space[:3, axis])


def slicing_normal(volume: Volume, beam: np.ndarray, normal: np.ndarray | None,
                   points: np.ndarray | None = None) -> np.ndarray:
    """The unit normal of the slices: ``normal`` made perpendicular to ``beam``, or without one
    the direction, perpendicular to the beam, of the imaged region's longest extent."""
    if normal is None:
        if points is None:
            covered = volume.array > 0
            points = np.argwhere(covered)[:: max(1, int(covered.sum()) // 200_000)] \
                @ volume.ijk_to_space[:3, :3].T + volume.ijk_to_space[:3, 3]
        flat = points - points.mean(axis=0)
        flat -= np.outer(flat @ beam, beam)
        normal = np.linalg.svd(flat, full_matrices=False)[2][0]
    return _unit(np.asarray(normal, float) - (np.asarray(normal, float) @ beam) * beam)


def volume_as_sweep(volume: Volume, beam: np.ndarray, normal: np.ndarray | None = None, *,
                    slice_mm: float = SLICE_MM, labels: bool = False) -> TrackedSweep:
    """The volume as a sweep of 2D slices (module docstring, step 4): rows along ``beam``
    (row 0 where the beam comes from), slices normal to ``normal`` (default: across the
    coverage's longest extent), pixels of the volume's finest spacing, uint8. With ``labels``
    the slices are the label volume's (nearest voxel, 255 = labelled), nothing filled."""
    array = volume.array.astype(np.float32)
    if labels:
        array = (volume.array > 0).astype(np.float32) * 255.0
    elif volume.array.dtype != np.uint8:
        lo, hi = float(array.min()), float(array.max())
        array = (array - lo) * (255.0 / max(hi - lo, 1e-12))
    covered = volume.array > 0
    M = volume.ijk_to_space
    beam = _unit(np.asarray(beam, float))
    where = _argwhere(covered)
    points = where[:: max(1, len(where) // 200_000)] @ M[:3, :3].T + M[:3, 3]
    normal = slicing_normal(volume, beam, normal, points)
    across = np.cross(beam, normal)  # columns; (across, beam, normal) is right-handed
    basis = np.stack([normal, beam, across])
    pixel = float(np.linalg.norm(M[:3, :3], axis=0).min())
    proj = points @ basis.T
    lo = proj.min(axis=0) - pixel
    span = proj.max(axis=0) + pixel - lo
    # resampled and filled every pixel (the volume's finest spacing) along the normal, so thin
    # imaged slabs are not missed; every slice_mm-th slice becomes a frame
    fine = int(span[0] // pixel) + 1
    every = max(1, int(round(slice_mm / pixel)))
    rows, cols = (int(v) for v in np.ceil(span[1:] / pixel) + 1)
    rr, cc = np.meshgrid(np.arange(rows) * pixel, np.arange(cols) * pixel, indexing="ij")
    plane = lo[1] * beam + lo[2] * across + rr[..., None] * beam + cc[..., None] * across
    starts = lo[0] + np.arange(fine) * pixel
    if labels:
        frames = _resample_labels(array, M, plane, starts, normal)[::every]
    else:
        frames = fill_slices(*_resample(array, covered, M, plane, starts, normal), pixel,
                             MAX_GAP_MM, every)
    n_slices = len(frames)
    T = np.tile(np.eye(4), (n_slices, 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = across, beam, normal
    T[:, :3, 3] = (lo[1] * beam + lo[2] * across)[None] \
        + (lo[0] + np.arange(n_slices) * every * pixel)[:, None] * normal
    return TrackedSweep(frames, np.array([pixel, pixel]), T, np.full(n_slices, np.nan),
                        np.ones(n_slices, dtype=bool), reference=volume.space,
                        frame_names=[f"slice{k:04d}" for k in range(n_slices)], path=volume.path)


def _argwhere(mask: np.ndarray) -> np.ndarray:
    """``np.argwhere(mask)`` ``(n, 3)`` (the same array, C order), without copying a Fortran
    ordered ``mask`` (volumes are read so) to C order."""
    if not mask.flags.f_contiguous:
        return np.argwhere(mask)
    where = np.unravel_index(np.flatnonzero(mask.T), mask.shape, order="F")
    return np.stack(np.unravel_index(np.sort(np.ravel_multi_index(where, mask.shape)),
                                     mask.shape)).T


def _slice_ijk(Minv: np.ndarray, plane: np.ndarray, start: float, normal: np.ndarray
               ) -> np.ndarray:
    """``(H * W, 3)`` voxel index coordinates of the slice ``plane + start * normal``
    (``plane`` ``(H, W, 3)`` mm; ``Minv``: the volume's ``space -> ijk``)."""
    return (plane + start * normal).reshape(-1, 3) @ Minv[:3, :3].T + Minv[:3, 3]


def _resample_labels(array, M, plane, starts, normal) -> np.ndarray:
    """uint8 slices ``(K, H, W)`` of ``array`` at ``plane + starts[k] * normal`` (nearest
    voxel, 0 outside)."""
    slices, Minv = np.zeros((len(starts), *plane.shape[:2]), np.uint8), np.linalg.inv(M)
    for k, start in enumerate(starts):
        ijk = _slice_ijk(Minv, plane, start, normal).T
        slices[k] = ndimage.map_coordinates(array, ijk, order=0, cval=0.0).reshape(
            plane.shape[:2]).astype(np.uint8)
    return slices


def _resample(array, covered, M, plane, starts, normal) -> tuple[np.ndarray, np.ndarray]:
    """``(values (K, H, W) float32, imaged (K, H, W) bool)``: the slices ``plane + starts[k] *
    normal`` of ``array`` (trilinear), imaged where the trilinear coverage ``covered`` is above
    0.5; values are only resampled where imaged (0 elsewhere). Only the points next to a covered
    voxel are interpolated: the others are 0."""
    shape = (len(starts), *plane.shape[:2])
    values, imaged = np.zeros(shape, np.float32), np.zeros(shape, bool)
    reach = [a.T for a in reach_of(covered.T)] if covered.flags.c_contiguous \
        else reach_of(covered)
    coverage, Minv = covered.astype(np.float32), np.linalg.inv(M)
    for k, start in enumerate(starts):
        ijk = _slice_ijk(Minv, plane, start, normal)
        near = may_exceed_zero(ijk, *reach)
        near = near[ndimage.map_coordinates(coverage, ijk[near].T, order=1, cval=0.0) > 0.5]
        imaged[k].reshape(-1)[near] = True
        values[k].reshape(-1)[near] = ndimage.map_coordinates(array, ijk[near].T, order=1,
                                                              cval=0.0)
    return values, imaged


def extract_volume_surface(volume: Volume, beam_direction: str = "auto", config=None, *,
                           progress=None):
    """Bone surface points of a reconstructed US volume (module docstring): returns
    ``(USExtractionResult, TrackedSweep of the slices)``; the points are in the volume's space
    (mm), each slice's pose has the beam as its second column. ``config``: a
    :class:`~comreg_core.surfaces.us_config.USExtractionConfig`."""
    from comreg_core.surfaces.us import extract_us_surface

    check_us_volume(volume)
    labels = is_label_volume(volume)
    if labels and beam_direction == "auto":
        raise NotAUsVolumeError("A label volume has no echoes to find the beam direction from.",
                                "Give --beam-direction (x, -x, y, -y, z or -z): the volume axis "
                                "the ultrasound beam ran along.")
    normal = None if labels else sweep_normal(volume)
    beam = estimate_beam(volume, normal) if beam_direction == "auto" \
        else beam_from_name(volume, beam_direction)
    sweep = volume_as_sweep(volume, beam, normal, labels=labels)
    result = extract_us_surface(sweep, config, masks=sweep.frames if labels else None,
                                progress=progress)
    if not labels:
        result.points = result.points.subset(result.points.score >= VOLUME_MIN_SCORE)
    return result, sweep


def is_volume_file(path) -> bool:
    """Whether ``path`` is a NRRD or MetaImage file holding one image or volume, not a tracked
    sequence (PLUS per-frame fields) or a 3D Slicer volume sequence (a list axis)."""
    from pathlib import Path

    from comreg_core.io.metaimage_files import header_field, read_metaimage_header
    from comreg_core.io.nrrd_files import read_nrrd_header
    from comreg_core.io.plus_files import has_plus_frame_fields

    path = Path(path)
    name = path.name.lower()
    if not path.is_file() or name.endswith((".igs.mha", ".seq.mha", ".igs.nrrd", ".seq.nrrd")):
        return False
    if name.endswith((".nrrd", ".nhdr")):
        header = read_nrrd_header(path)
        return not has_plus_frame_fields(header) and int(header.get("dimension", 3)) <= 3
    if name.endswith((".mha", ".mhd")):
        fields, _ = read_metaimage_header(path)
        return not has_plus_frame_fields(fields) and \
            int(header_field(fields, "NDims") or 3) <= 3
    return False


def extract_volume_to_file(volume_path, out, *, beam_direction: str = "auto", config=None,
                           progress=None, frame_options: dict | None = None):
    """``comreg extract-us VOLUME --out POINTS [--beam-direction D]``: bone points of a
    reconstructed US volume written like the frame path's (the volume's space; a ``.ply`` also
    keeps each point's beam origin on its slice's first row). ``frame_options``: options of the
    frame path by name, refused when given. Returns the
    :class:`~comreg_core.surfaces.us.USExtractionResult`."""
    given = [name for name, value in (frame_options or {}).items() if value is not None]
    if given:
        raise ComRegError(f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} for "
                          f"tracked frames; '{volume_path}' is a reconstructed volume.",
                          "Drop them.")
    from comreg_core.io.volumes import read_volume
    from comreg_core.surfaces.us import check_us_outputs, write_surface_points
    from comreg_core.surfaces.us_config import USExtractionConfig, load_us_extraction_config

    check_us_outputs(out, inputs=[volume_path, config])
    check_beam_direction(beam_direction)
    if not isinstance(config, USExtractionConfig):
        config = load_us_extraction_config(config)
    volume = read_volume(volume_path)
    result, sweep = extract_volume_surface(volume, beam_direction, config, progress=progress)
    result.output = write_surface_points(result.points, sweep, out, volume.space)
    return result
