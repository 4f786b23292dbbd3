"""What the ComReg panel draws of a registration in the 3D view.

- the US points coloured by their distance to the CT surface (mm; the report's viridis map and
  0-5 mm range, :mod:`comreg_core.report.style`) with a colour legend
  (:func:`colourByDistance`), as SlicerIGT colours a model by its distance;
- the competing pose, the US points where the best clinically different pose puts them, as a
  faint model that can be hidden (:func:`showCompetitor`);
- the region to scan next, the CT triangles around the record's ``scan_next`` point, as a
  coloured patch on the CT model (:func:`showScanNext`).

Each is a node with a ``ComReg.role`` attribute (saved with the scene) and is updated in place by
the next registration. Function names are camelCase, as in 3D Slicer modules.
"""

import numpy as np
from vtk.util import numpy_support

from comreg_core.report.style import DEFAULT_STYLE, colormap_rgb
from comreg_core.transforms import apply_transform, space_change
from comreg_plugin.bone_models import ATTRIBUTE_PREFIX
from comreg_plugin.scene_io import addModelNode, arraysFromModelMesh

#: Point-data array of the US points: distance to the CT surface (mm).
DISTANCE_ARRAY = "ComReg distance to CT (mm)"
DISTANCE_COLORS_NAME = "ComReg distance to CT (mm)"
COMPETITOR_NODE_NAME = "ComReg competing pose"
COMPETITOR_COLOR = (0.85, 0.3, 0.3)
COMPETITOR_OPACITY = 0.35
SCAN_NEXT_NODE_NAME = "ComReg scan next"
SCAN_NEXT_COLOR = (1.0, 0.55, 0.0)
#: Radius (mm) of the patch to scan next when the record gives none.
SCAN_NEXT_RADIUS_MM = 15.0


def roleNode(scene, role: str):
    """The node of ``role`` (``ComReg.role`` attribute) in ``scene``, or None."""
    nodes = scene.GetNodesByClass("vtkMRMLNode")
    nodes.InitTraversal()
    for _ in range(nodes.GetNumberOfItems()):
        node = nodes.GetNextItemAsObject()
        if node.GetAttribute(ATTRIBUTE_PREFIX + "role") == role:
            return node
    return None


def distanceColorNode(scene):
    """The viridis colour table of distances (256 entries; the report's map), made once."""
    node = roleNode(scene, "distance_colors")
    if node is not None:
        return node
    node = scene.AddNewNodeByClass("vtkMRMLColorTableNode", DISTANCE_COLORS_NAME)
    node.SetTypeToUser()
    node.SetNumberOfColors(256)
    rgb = colormap_rgb(np.linspace(0.0, 1.0, 256)) / 255.0
    for k, (r, g, b) in enumerate(rgb):
        node.SetColor(k, f"{k}", float(r), float(g), float(b), 1.0)
    node.SetAttribute(ATTRIBUTE_PREFIX + "role", "distance_colors")
    return node


def colourByDistance(scene, pointsNode, distances_mm: np.ndarray,
                     rangeMm=DEFAULT_STYLE.distance_range_mm):
    """Colour ``pointsNode`` by ``distances_mm`` ``(N,)`` (one per point, mm) on the viridis
    table over ``rangeMm`` (beyond: the end colours) and show a colour legend; returns the
    legend display node (None where the legend class is not available)."""
    distances = np.ascontiguousarray(distances_mm, dtype=np.float64)
    polydata = pointsNode.GetPolyData()
    if len(distances) != polydata.GetNumberOfPoints():
        raise ValueError("one distance per point is needed")
    array = numpy_support.numpy_to_vtk(distances, deep=True)
    array.SetName(DISTANCE_ARRAY)
    polydata.GetPointData().AddArray(array)
    polydata.GetPointData().SetActiveScalars(DISTANCE_ARRAY)
    polydata.Modified()
    display = pointsNode.GetDisplayNode()
    display.SetActiveScalarName(DISTANCE_ARRAY)
    display.SetAndObserveColorNodeID(distanceColorNode(scene).GetID())
    display.SetScalarRangeFlag(display.UseManualScalarRange)
    display.SetScalarRange(float(rangeMm[0]), float(rangeMm[1]))
    display.SetScalarVisibility(True)
    return _legend(scene, pointsNode, "Distance to CT (mm)")


LEGEND_CLASS = "vtkMRMLColorLegendDisplayNode"


def registerLegendClass(scene) -> bool:
    """Make ``scene`` know colour legend nodes (3D Slicer's Colors module does it inside the
    application; headless, a scene must know the class to create or load one). Whether the
    class is available."""
    import slicer

    if not hasattr(slicer, LEGEND_CLASS):
        return False
    if not scene.IsNodeClassRegistered(LEGEND_CLASS):
        scene.RegisterNodeClass(getattr(slicer, LEGEND_CLASS)())
    return True


def _legend(scene, node, title: str):
    """A colour legend display node of ``node``'s scalars (Slicer's Colors module's)."""
    name = LEGEND_CLASS
    if not registerLegendClass(scene):
        return None
    for k in range(node.GetNumberOfDisplayNodes()):
        legend = node.GetNthDisplayNode(k)
        if legend is not None and legend.IsA(name):
            break
    else:
        legend = scene.AddNewNodeByClass(name, f"{node.GetName()} legend")
        legend.SetAndObservePrimaryDisplayNode(node.GetDisplayNode())
        node.AddAndObserveDisplayNodeID(legend.GetID())
    legend.SetTitleText(title)
    legend.SetVisibility(True)
    return legend


def showCompetitor(scene, points_us: np.ndarray, T_competitor: np.ndarray, space: str,
                   visible: bool = True):
    """The US points ``(N, 3)`` (US frame, ``space``) placed by the competing pose
    ``T_competitor`` ``(4, 4)`` (``space``) as a faint model in the CT frame; None removes it.
    Returns the node (or None)."""
    node = roleNode(scene, "competitor")
    if T_competitor is None:
        if node is not None:
            scene.RemoveNode(node)
        return None
    ras = apply_transform(space_change(space, "RAS") @ np.asarray(T_competitor, np.float64),
                          points_us)
    node = addModelNode(scene, ras, None, COMPETITOR_NODE_NAME, COMPETITOR_COLOR, 2.0, node)
    node.SetAttribute(ATTRIBUTE_PREFIX + "role", "competitor")
    node.GetDisplayNode().SetOpacity(COMPETITOR_OPACITY)
    node.GetDisplayNode().SetVisibility(bool(visible))
    return node


def scanNextPatch(ctModelNode, scanNext: dict, space: str = "LPS") -> tuple:
    """``(vertices RAS, faces)`` of the CT model's triangles whose three corners are within the
    record's ``radius_mm`` (else :data:`SCAN_NEXT_RADIUS_MM`) of ``scanNext["point_ct"]`` (in
    ``space``); empty arrays when none is."""
    vertices, faces = arraysFromModelMesh(ctModelNode)
    point = apply_transform(space_change(space, "RAS"),
                            np.asarray(scanNext["point_ct"], np.float64)[None])[0]
    radius = float(scanNext.get("radius_mm") or SCAN_NEXT_RADIUS_MM)
    near = np.linalg.norm(vertices - point, axis=1) <= radius
    keep = faces[near[faces].all(axis=1)]
    used = np.unique(keep)
    index = np.full(len(vertices), -1)
    index[used] = np.arange(len(used))
    return vertices[used], index[keep]


def showScanNext(scene, ctModelNode, scanNext, space: str = "LPS"):
    """The region to scan next as a coloured patch on the CT model (a model node, role
    ``scan_next``); removed when ``scanNext`` is None, has no point or no CT triangle near it.
    Returns the node or None."""
    node = roleNode(scene, "scan_next")
    patch = None
    if scanNext and scanNext.get("point_ct") is not None and ctModelNode is not None:
        patch = scanNextPatch(ctModelNode, scanNext, space)
    if patch is None or not len(patch[1]):
        if node is not None:
            scene.RemoveNode(node)
        return None
    node = addModelNode(scene, patch[0], patch[1], SCAN_NEXT_NODE_NAME, SCAN_NEXT_COLOR,
                        node=node)
    node.SetAttribute(ATTRIBUTE_PREFIX + "role", "scan_next")
    return node
