"""Segmentations: multi-segment label maps, read from 3D Slicer ``.seg.nrrd`` files or plain
integer label maps (``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd``) and written as ``.seg.nrrd`` with
Slicer's ``Segment{i}_*`` header fields. Geometry conventions: see :mod:`comreg_core.io.volumes`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from comreg_core.errors import ComRegError, EmptyMaskError, LabelNotFoundError
from comreg_core.io._files import require_extension, require_input_file
from comreg_core.io.image_files import (format_numbers, parse_errors_as_corrupt,
                                        single_volume_array)
from comreg_core.io.nrrd_files import (SLICER_SEGMENT_FIELD, has_slicer_segment_fields,
                                       read_nrrd_grid, write_nrrd_grid)
from comreg_core.io.volumes import VOLUME_READ_EXTENSIONS, Volume, read_volume
from comreg_core.transforms import check_space


@dataclass
class Segment:
    """One segment of a segmentation: where it lives (layer, label value) and how it is called."""

    name: str
    label_value: int
    layer: int = 0
    id: str = ""
    color: tuple[float, float, float] = (0.9, 0.85, 0.7)

    def __post_init__(self) -> None:
        self.id = self.id or self.name


@dataclass
class Segmentation:
    """A multi-segment label map (3D Slicer ``.seg.nrrd`` or a plain label map).

    Attributes:
        layers: ``(L, I, J, K)`` integer label values; segments may share a layer (different
            label values) or overlap (different layers).
        ijk_to_space: ``(4, 4)`` voxel index -> ``space`` mm, shared by all layers.
        space: "LPS" or "RAS".
        segments: the named segments, in file order.
        path: the file it was read from, if any.
    """

    layers: np.ndarray
    ijk_to_space: np.ndarray
    space: str = "LPS"
    segments: list[Segment] = field(default_factory=list)
    path: Path | None = None

    def __post_init__(self) -> None:
        self.space = check_space(self.space)
        self.ijk_to_space = np.asarray(self.ijk_to_space, dtype=np.float64)
        if self.layers.ndim == 3:
            self.layers = self.layers[np.newaxis]

    @classmethod
    def from_labelmap(cls, volume: Volume) -> "Segmentation":
        """One segment per non-zero label value of an integer label map, named "Label <v>"."""
        labels = np.asarray(volume.array)
        values = [int(v) for v in np.unique(labels) if v != 0]
        segments = [Segment(name=f"Label {v}", label_value=v, id=f"Label_{v}") for v in values]
        return cls(labels[np.newaxis], volume.ijk_to_space, volume.space, segments, volume.path)

    def find_segment(self, *, name: str | None = None, label: int | None = None) -> Segment:
        """The segment with this name (or id), or with this label value in a single-layer map.

        With neither given, the only segment; raises :class:`LabelNotFoundError` when there is no
        match or the choice is ambiguous.
        """
        where = f" in '{self.path}'" if self.path else ""
        listing = ", ".join(f"'{s.name}' (label {s.label_value}, layer {s.layer})"
                            for s in self.segments) or "none"
        if name is not None:
            for seg in self.segments:
                if name in (seg.name, seg.id):
                    return seg
            raise LabelNotFoundError(f"There is no segment named '{name}'{where}.",
                                     f"Segments present: {listing}.")
        if label is not None:
            matches = [s for s in self.segments if s.label_value == int(label)]
            if len(matches) == 1:
                return matches[0]
            if not matches:
                raise LabelNotFoundError(f"No segment has label value {label}{where}.",
                                         f"Segments present: {listing}.")
            raise LabelNotFoundError(
                f"Label value {label} is used by {len(matches)} segments in different layers{where}.",
                "Choose the segment by name instead (--segment NAME).")
        if len(self.segments) == 1:
            return self.segments[0]
        if not self.segments:
            raise EmptyMaskError(f"The segmentation{where} contains no labelled voxels.",
                                 "Check that the right file was exported.")
        raise LabelNotFoundError(
            f"The segmentation{where} has {len(self.segments)} segments; which one is the bone?",
            f"Choose one with --segment NAME or --label N. Segments present: {listing}.")

    def mask(self, segment: Segment) -> np.ndarray:
        """``(I, J, K)`` boolean mask of ``segment``; raises :class:`EmptyMaskError` if empty."""
        mask = self.layers[segment.layer] == segment.label_value
        if not mask.any():
            raise EmptyMaskError(
                f"Segment '{segment.name}' (label {segment.label_value}) has no voxels.",
                "Pick a segment that is painted, or fix the segmentation.")
        return mask

    def geometry(self, array: np.ndarray) -> Volume:
        """A :class:`Volume` holding ``array`` ``(I, J, K)`` on this segmentation's grid."""
        return Volume(array, self.ijk_to_space.copy(), self.space, self.path)


#: Extensions :func:`read_segmentation` accepts (Slicer segmentations or plain label maps).
SEGMENTATION_READ_EXTENSIONS = [".seg.nrrd", *VOLUME_READ_EXTENSIONS]
SEGMENTATION_WRITE_EXTENSIONS = [".seg.nrrd", ".nrrd"]


def read_segmentation(path: str | Path) -> Segmentation:
    """Read a 3D Slicer ``.seg.nrrd`` (3D, or 4D with a leading list of layers) or a plain
    integer label map (``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd``; one segment per label value).

    Slicer files without ``Segment{i}_Layer``/``_LabelValue`` fields are the legacy layout
    (segment i in layer i, label value 1) when there is one layer per segment, else segment i is
    label value i+1 in layer 0. A ``.seg.nrrd`` without any ``Segment{i}_*`` field is read as a
    label map: one segment per non-zero value (and layer).
    """
    ext = require_extension(path, "segmentation", SEGMENTATION_READ_EXTENSIONS)
    path = require_input_file(path, "segmentation file")
    if ext in (".seg.nrrd", ".nrrd", ".nhdr"):
        array, header, ijk_to_space, space, list_kind = read_nrrd_grid(path)
        if has_slicer_segment_fields(header):
            _require_labels(path, array)
            layers = array if array.ndim == 4 else array[np.newaxis]
            with parse_errors_as_corrupt(path):
                segments = _slicer_segments(header, len(layers))
            return Segmentation(layers, ijk_to_space, space, segments, path)
        if ext == ".seg.nrrd" and array.ndim == 4:  # layers without segment fields
            _require_labels(path, array)
            segments = [Segment(f"Layer {layer} label {int(v)}", int(v), layer,
                                f"Layer_{layer}_Label_{int(v)}")
                        for layer in range(len(array)) for v in np.unique(array[layer]) if v]
            return Segmentation(array, ijk_to_space, space, segments, path)
        # a .seg.nrrd without Slicer's segment fields is a plain label map: a segment per value
        volume = Volume(single_volume_array(path, array, list_kind, False), ijk_to_space, space,
                        path)
    else:
        volume = read_volume(path)
    _require_labels(path, volume.array)
    return Segmentation.from_labelmap(volume)


def write_segmentation(seg: Segmentation, path: str | Path, *, compress: bool = True) -> Path:
    """Write ``seg`` as a 3D Slicer ``.seg.nrrd``: 3D for one layer, else 4D with a leading
    list axis, with Slicer's ``Segment{i}_*`` fields. Atomic; returns the path."""
    require_extension(path, "segmentation", SEGMENTATION_WRITE_EXTENSIONS)
    path = Path(path)
    layers = np.asarray(seg.layers)
    if layers.ndim != 4:
        raise ValueError(f"Segmentation layers must be (L, I, J, K), got shape {layers.shape}.")
    if layers.dtype.kind not in "biu":
        raise TypeError(f"Segmentation layers must be integers, got {layers.dtype}.")
    layers = layers.astype(_smallest_label_type(layers), copy=False)
    extra: dict[str, str] = {}
    for i, segment in enumerate(seg.segments):
        for text in (segment.name, segment.id):
            if not text.isascii() or not text.isprintable():
                raise ComRegError(f"Segment name or id {text!r} has characters a NRRD header "
                                  "cannot hold.", "Use printable ASCII names.")
        extra.update({
            f"Segment{i}_Color": format_numbers(segment.color),
            f"Segment{i}_ColorAutoGenerated": "0",
            f"Segment{i}_Extent": _extent(layers[segment.layer] == segment.label_value),
            f"Segment{i}_ID": segment.id,
            f"Segment{i}_LabelValue": str(int(segment.label_value)),
            f"Segment{i}_Layer": str(int(segment.layer)),
            f"Segment{i}_Name": segment.name,
            f"Segment{i}_NameAutoGenerated": "0",
            f"Segment{i}_Tags": "",
        })
    extra.update({
        "Segmentation_ContainedRepresentationNames": "Binary labelmap|",
        "Segmentation_MasterRepresentation": "Binary labelmap",
        "Segmentation_ReferenceImageExtentOffset": "0 0 0",
    })
    data = layers[0] if len(layers) == 1 else layers
    write_nrrd_grid(path, data, seg.ijk_to_space, seg.space, compress=compress, extra=extra)
    return path


def _require_labels(path: Path, array: np.ndarray) -> None:
    """Raise unless ``array`` looks like a label map (integers, none negative)."""
    hint = "This looks like an intensity CT, not a label map; segment the bone first."
    if array.dtype.kind not in "biu":
        raise ComRegError(f"'{path}' has {array.dtype} voxels, not integer labels.", hint)
    if array.dtype.kind == "i" and array.size and array.min() < 0:
        raise ComRegError(f"'{path}' has negative voxel values (down to {array.min()}), which "
                          "a label map never has.", hint)


def _slicer_segments(header: dict, n_layers: int) -> list[Segment]:
    """The segments described by Slicer's ``Segment{i}_*`` header fields, in index order."""
    per_index: dict[int, dict[str, str]] = {}
    for key, value in header.items():
        match = SLICER_SEGMENT_FIELD.match(key)
        if match:
            per_index.setdefault(int(match[1]), {})[match[2]] = str(value).strip()
    legacy = len(per_index) > 1 and n_layers == len(per_index)
    segments = []
    for n, (i, meta) in enumerate(sorted(per_index.items())):
        layer = int(meta.get("Layer", n if legacy else 0))
        label = int(meta.get("LabelValue", 1 if legacy else n + 1))
        color = tuple(float(c) for c in meta.get("Color", "").split()) or None
        segments.append(Segment(
            name=meta.get("Name") or meta.get("ID") or f"Segment_{i}", label_value=label,
            layer=layer, id=meta.get("ID", ""),
            **({"color": color} if color and len(color) == 3 else {})))
    return segments


def _extent(mask: np.ndarray) -> str:
    """Slicer's "i0 i1 j0 j1 k0 k1" bounding box of a ``(I, J, K)`` mask ("0 -1 ..." if empty)."""
    if not mask.any():
        return "0 -1 0 -1 0 -1"
    bounds = []
    for axis in range(3):
        hits = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
        bounds += [int(hits[0]), int(hits[-1])]
    return " ".join(str(b) for b in bounds)


def _smallest_label_type(layers: np.ndarray) -> np.dtype:
    """The smallest unsigned type holding all labels (Slicer does the same), else int32/64."""
    if layers.size == 0:
        return np.dtype(np.uint8)
    low, high = int(layers.min()), int(layers.max())
    for dtype in (np.uint8, np.uint16, np.uint32) if low >= 0 else (np.int8, np.int16, np.int32):
        info = np.iinfo(dtype)
        if info.min <= low and high <= info.max:
            return np.dtype(dtype)
    return np.dtype(np.int64)
