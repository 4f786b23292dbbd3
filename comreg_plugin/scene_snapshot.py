"""A picture of the module's 3D scene rendered off-screen, headless: the model nodes a 3D view
shows (their display node's colour, opacity, point size, scalars through its colour table, each
under its parent transform), with the colour legend of the scalars. For the documentation's
screenshot and the self test; inside 3D Slicer its own 3D view shows the same nodes.

Function names are camelCase, as in 3D Slicer modules.
"""

from pathlib import Path

import numpy as np
import vtk

#: The default picture size (pixels) and background (RGB 0..1).
SIZE = (960, 320)
BACKGROUND = (1.0, 1.0, 1.0)


def _lookupTable(scene, display):
    """A ``vtkLookupTable`` of the display node's colour table over its scalar range."""
    colors = scene.GetNodeByID(display.GetColorNodeID())
    table = vtk.vtkLookupTable()
    n = colors.GetNumberOfColors()
    table.SetNumberOfTableValues(n)
    rgba = [0.0] * 4
    for k in range(n):
        colors.GetColor(k, rgba)
        table.SetTableValue(k, *rgba)
    table.SetRange(*display.GetScalarRange())
    table.Build()
    return table


def _worldPolyData(node):
    """The node's polydata under its parent transforms (world RAS)."""
    polydata = node.GetPolyData()
    parent = node.GetParentTransformNode()
    if parent is None:
        return polydata
    matrix = vtk.vtkMatrix4x4()
    parent.GetMatrixTransformToWorld(matrix)
    transform = vtk.vtkTransform()
    transform.SetMatrix(matrix)
    moved = vtk.vtkTransformPolyDataFilter()
    moved.SetTransform(transform)
    moved.SetInputData(polydata)
    moved.Update()
    return moved.GetOutput()


def _actor(scene, node):
    """``(actor, lookup table or None)`` of a shown model node, or ``(None, None)``."""
    display = node.GetDisplayNode()
    if display is None or not display.GetVisibility() or node.GetPolyData() is None:
        return None, None
    mapper = vtk.vtkPolyDataMapper()
    mapper.SetInputData(_worldPolyData(node))
    table = None
    if display.GetScalarVisibility() and display.GetActiveScalarName():
        table = _lookupTable(scene, display)
        mapper.SetLookupTable(table)
        mapper.SetScalarModeToUsePointFieldData()
        mapper.SelectColorArray(display.GetActiveScalarName())
        mapper.SetScalarRange(*display.GetScalarRange())
        mapper.ScalarVisibilityOn()
    else:
        mapper.ScalarVisibilityOff()
    actor = vtk.vtkActor()
    actor.SetMapper(mapper)
    prop = actor.GetProperty()
    prop.SetColor(*display.GetColor())
    prop.SetOpacity(display.GetOpacity())
    prop.SetPointSize(display.GetPointSize())
    if display.GetRepresentation() == display.PointsRepresentation:
        prop.SetRepresentationToPoints()
        prop.RenderPointsAsSpheresOn()
    return actor, table


def renderScene(scene, path, *, size=SIZE, view=(0.0, -1.0, 0.0), up=(1.0, 0.0, 0.0),
                fitNode=None, legendTitle: str = "Distance to CT (mm)") -> Path:
    """Render the scene's shown model nodes off-screen into the PNG ``path``: seen from
    ``view`` (a direction in RAS, default from the front) with ``up`` (default: the patient's
    left, so a long bone lies across the picture), fitted to ``fitNode`` (default: every
    actor); with a legend of the first coloured node's scalars. Returns ``path``."""
    from comreg_core.report.backend import ensure_offscreen_rendering

    ensure_offscreen_rendering()
    renderer = vtk.vtkRenderer()
    renderer.SetBackground(*BACKGROUND)
    legend, fit = None, None
    nodes = scene.GetNodesByClass("vtkMRMLModelNode")
    for k in range(nodes.GetNumberOfItems()):
        node = nodes.GetItemAsObject(k)
        actor, table = _actor(scene, node)
        if actor is None:
            continue
        renderer.AddActor(actor)
        if node is fitNode:
            fit = actor.GetBounds()
        if table is not None and legend is None:
            legend = vtk.vtkScalarBarActor()
            legend.SetLookupTable(table)
            legend.SetTitle(legendTitle)
            legend.SetNumberOfLabels(6)
            legend.SetLabelFormat("%.0f")
            legend.SetUnconstrainedFontSize(True)
            legend.SetPosition(0.9, 0.1)
            legend.SetWidth(0.06)
            legend.SetHeight(0.7)
            for text, points in ((legend.GetTitleTextProperty(), 14),
                                 (legend.GetLabelTextProperty(), 13)):
                text.SetColor(0.1, 0.1, 0.1)
                text.SetFontSize(points)
                text.ItalicOff()
                text.ShadowOff()
            renderer.AddViewProp(legend)
    camera = renderer.GetActiveCamera()
    camera.SetPosition(*(-np.asarray(view, float)))
    camera.SetFocalPoint(0.0, 0.0, 0.0)
    camera.SetViewUp(*up)
    renderer.ResetCamera(*fit) if fit is not None else renderer.ResetCamera()
    camera.Zoom(2.3)
    window = vtk.vtkRenderWindow()
    window.SetOffScreenRendering(True)
    window.SetSize(*size)
    window.AddRenderer(renderer)
    window.Render()
    grab = vtk.vtkWindowToImageFilter()
    grab.SetInput(window)
    grab.Update()
    writer = vtk.vtkPNGWriter()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer.SetFileName(str(path))
    writer.SetInputConnection(grab.GetOutputPort())
    writer.Write()
    window.Finalize()
    return path
