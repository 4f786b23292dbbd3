"""The two bone surfaces the ComReg module registers, as model nodes in the scene (RAS).

- CT bone models: one closed surface per segment of a CT segmentation (a label map or
  ``.seg.nrrd`` file: :func:`loadSegmentationModels`; a segmentation node:
  :func:`segmentationNodeModels`), or a bone mesh file (:func:`loadMeshModel`);
- US bone points: a model node of vertices, the bone points ``extract-us``'s detector finds in a
  tracked sweep (a file: :func:`loadSweepPointsModel`; a Sequence browser's:
  :func:`sweepPointsModel`) or a reconstructed US volume node (:func:`volumePointsModel`), or
  the points of a point cloud file (:func:`loadPointsModel`).

Each node carries ``ComReg.*`` attributes (:data:`ATTRIBUTE_PREFIX`, the prefix of every value
ComReg stores on a node) saying what it is (``role``: ``ct_bone``, ``us_points``) and where it
came from (``source``, ``segment``, ``extraction``). :class:`comreg_plugin.logic.ComRegLogic`
makes them in its scene and puts them in its parameter node. Function names are camelCase, as in
3D Slicer modules.
"""

import logging
from pathlib import Path

import numpy as np
from vtk.util import numpy_support

from comreg_core.errors import UnsupportedFormatError
from comreg_core.io._files import file_extension, require_input_file
from comreg_core.progress import silent
from comreg_core.transforms import apply_transform, space_change
from comreg_plugin.scene_io import (addModelNode, readSlicerSegmentation,
                                    segmentationNodeFromArrays)
from comreg_plugin.scene_inputs import segmentationFromNode, volumeFromNode

log = logging.getLogger(__name__)

#: Node attribute prefix for values ComReg stores on nodes.
ATTRIBUTE_PREFIX = "ComReg."
US_POINTS_NODE_NAME = "US bone points"
BONE_COLOR = (0.95, 0.9, 0.75)
US_POINTS_COLOR = (0.1, 0.55, 1.0)
#: Point-data array of a US points model holding each point's beam origin (RAS, mm): where its
#: ultrasound beam started, as ``extract-us``'s PLY files keep it.
BEAM_ORIGINS_ARRAY = "ComReg beam origin"


def addPointsModel(scene, points: np.ndarray, space: str, name: str, color, node=None,
                   origins=None):
    """A model node of vertices from ``(N, 3)`` points given in ``space``; ``node`` is updated in
    place if given; ``origins`` ``(N, 3)`` (same space): the points' beam origins, kept as the
    :data:`BEAM_ORIGINS_ARRAY` point data."""
    change = space_change(space, "RAS")
    ras = apply_transform(change, np.asarray(points, dtype=np.float64))
    node = addModelNode(scene, ras, None, name, color, node=node)
    if origins is not None:
        array = numpy_support.numpy_to_vtk(np.ascontiguousarray(apply_transform(
            change, np.asarray(origins, dtype=np.float64))), deep=True)
        array.SetName(BEAM_ORIGINS_ARRAY)
        node.GetPolyData().GetPointData().AddArray(array)
    return node


def beamOriginsOfNode(node, space: str = "LPS"):
    """``(N, 3)`` beam origins (in ``space``) a US points model keeps, or None."""
    polydata = node.GetPolyData() if node.IsA("vtkMRMLModelNode") else None
    array = None if polydata is None else \
        polydata.GetPointData().GetArray(BEAM_ORIGINS_ARRAY)
    if array is None:
        return None
    return apply_transform(space_change("RAS", space),
                           numpy_support.vtk_to_numpy(array).astype(np.float64))


def addBoneModel(scene, mesh, name: str, color=BONE_COLOR):
    """A closed-surface model node (role ``ct_bone``) of a
    :class:`~comreg_core.io.SurfaceMesh` (any space)."""
    ras = mesh.in_space("RAS")
    node = addModelNode(scene, ras.vertices, ras.faces, name, color)
    node.SetAttribute(ATTRIBUTE_PREFIX + "role", "ct_bone")
    return node


def loadSegmentationModels(scene, path, segmentNames, options, progress) -> tuple:
    """``(segmentationNode, [modelNode, ...])`` of a CT segmentation file, one bone model per
    segment (or per name in ``segmentNames``); see :meth:`ComRegLogic.loadSegmentation
    <comreg_plugin.logic.ComRegLogic.loadSegmentation>`."""
    from comreg_core.io import SEGMENTATION_READ_EXTENSIONS, read_segmentation

    path = require_input_file(path, "CT segmentation")
    ext = file_extension(path)
    if ext not in SEGMENTATION_READ_EXTENSIONS:
        raise UnsupportedFormatError(path, "CT segmentation", SEGMENTATION_READ_EXTENSIONS)
    report = progress or silent
    seg = read_segmentation(path)
    segments = _segments(seg, segmentNames)
    base = Path(path).name[: -len(ext)] or "CT"
    if ext == ".seg.nrrd":
        segNode = readSlicerSegmentation(scene, path, base)
    else:
        segNode = segmentationNodeFromArrays(scene, seg, base, BONE_COLOR)
    segNode.CreateDefaultDisplayNodes()
    models = _boneModels(scene, seg, segments, options, Path(path).name, report)
    log.info("Loaded '%s': %d segment(s), %d bone model(s)", path, len(seg.segments),
             len(models))
    return segNode, models


def segmentationNodeModels(scene, segmentationNode, segmentNames, options, progress) -> list:
    """Bone models of a segmentation node already in the scene, by the same extraction as
    :func:`loadSegmentationModels`."""
    seg = segmentationFromNode(segmentationNode)
    return _boneModels(scene, seg, _segments(seg, segmentNames), options,
                       segmentationNode.GetName(), progress or silent)


def loadMeshModel(scene, path, name):
    """The CT bone model of a bone mesh file, named ``name`` or after the file."""
    from comreg_core.io import read_mesh

    model = addBoneModel(scene, read_mesh(path), name or Path(path).stem)
    model.SetAttribute(ATTRIBUTE_PREFIX + "source", Path(path).name)
    return model


def _segments(seg, segmentNames) -> list:
    if segmentNames is None:
        return seg.segments
    return [seg.find_segment(name=name) for name in segmentNames]


def _boneModels(scene, seg, segments, options, source: str, report) -> list:
    from comreg_core.surfaces.ct import extract_bone_surface

    models = []
    report(0, len(segments) + 1, "reading")
    for i, segment in enumerate(segments):
        report(i + 1, len(segments) + 1, f"surface of '{segment.name}'")
        mesh = extract_bone_surface(seg, segment=segment, options=options)
        model = addBoneModel(scene, mesh, f"{segment.name} bone", segment.color or BONE_COLOR)
        model.SetAttribute(ATTRIBUTE_PREFIX + "segment", segment.name)
        model.SetAttribute(ATTRIBUTE_PREFIX + "source", source)
        models.append(model)
    report(len(segments) + 1, len(segments) + 1, "done")
    return models


def extractionConfig(config):
    """``config`` as a :class:`~comreg_core.surfaces.us_config.USExtractionConfig` (itself, or
    read from its YAML file; None: the defaults)."""
    from comreg_core.surfaces.us_config import USExtractionConfig, load_us_extraction_config

    return config if isinstance(config, USExtractionConfig) else \
        load_us_extraction_config(config)


def loadSweepPointsModel(scene, path, calibration, config, name, progress) -> tuple:
    """``(pointsNode, USExtractionResult)``: the bone points of a tracked sweep file or frame
    folder (with its PLUS calibration, if not beside the data)."""
    from comreg_core.io import read_tracked_sweep

    config = extractionConfig(config)
    sweep = read_tracked_sweep(path, calibration=calibration, reference=config.reference)
    return sweepPointsModel(scene, sweep, config, name, Path(path).name, progress)


def sweepPointsModel(scene, sweep, config, name, source: str, progress) -> tuple:
    """``(pointsNode, USExtractionResult)``: the bone points of a
    :class:`~comreg_core.io.TrackedSweep` (LPS), ``config`` a ``USExtractionConfig``."""
    from comreg_core.surfaces.us import extract_us_surface

    from comreg_core.surfaces.us_points import beam_origins

    result = extract_us_surface(sweep, config, progress=progress)
    found, origins = result.points, None
    if (found.frame_index >= 0).all():  # as extract-us writes them
        origins = beam_origins(found.points, sweep.T_ref_image[found.frame_index])
    return _addUSPointsModel(scene, result, "LPS", name, source, origins), result


def volumePointsModel(scene, volumeNode, beamDirection: str, config, name, progress) -> tuple:
    """``(pointsNode, USExtractionResult)``: the bone points of a reconstructed 3D US volume
    node (RAS), the beam ``"auto"`` or a voxel axis (``"-y"``, ...)."""
    from comreg_core.surfaces.us_volume import extract_volume_surface

    result, _ = extract_volume_surface(volumeFromNode(volumeNode), beamDirection,
                                       extractionConfig(config), progress=progress)
    return _addUSPointsModel(scene, result, "RAS", name, volumeNode.GetName()), result


def _addUSPointsModel(scene, result, space: str, name, source: str, origins=None):
    """The US bone points node of a :class:`~comreg_core.surfaces.us.USExtractionResult` (its
    points, and their beam ``origins`` if known, in ``space``), with its extraction summary."""
    node = addPointsModel(scene, result.points.points, space, name, US_POINTS_COLOR,
                          origins=origins)
    node.SetAttribute(ATTRIBUTE_PREFIX + "role", "us_points")
    node.SetAttribute(ATTRIBUTE_PREFIX + "source", source)
    node.SetAttribute(ATTRIBUTE_PREFIX + "extraction", result.summary())
    log.info("US sweep '%s': %s", source, result.summary())
    return node


def loadPointsModel(scene, path, name):
    """The US bone points node of a point cloud file (LPS unless tagged)."""
    from comreg_core.io import read_points

    cloud = read_points(path)
    node = addPointsModel(scene, cloud.points, cloud.space, name, US_POINTS_COLOR,
                          origins=cloud.beam_origins)
    node.SetAttribute(ATTRIBUTE_PREFIX + "role", "us_points")
    node.SetAttribute(ATTRIBUTE_PREFIX + "source", Path(path).name)
    return node
