"""Small helpers for the simulation tests (config edits, naive reference geometry)."""

from dataclasses import replace

import numpy as np

from comreg_core.simulation import SimulationConfig


def with_perturbation(config: SimulationConfig, **changes) -> SimulationConfig:
    """``config`` with some perturbation fields replaced."""
    return replace(config, perturbation=replace(config.perturbation, **changes))


def with_trajectory(config: SimulationConfig, **changes) -> SimulationConfig:
    """``config`` with some trajectory fields replaced."""
    return replace(config, trajectory=replace(config.trajectory, **changes))


def naive_ray(T_ct_image: np.ndarray, ray: int, width_mm: float, n_rays: int):
    """Origin and direction of one ray, written out from the image-frame definition:
    origin = image point ((ray + 0.5) * width / n_rays, 0, 0), direction = image +y."""
    p = np.array([(ray + 0.5) * width_mm / n_rays, 0.0, 0.0, 1.0])
    origin = (T_ct_image @ p)[:3]
    direction = T_ct_image[:3, :3] @ np.array([0.0, 1.0, 0.0])
    return origin, direction


def vtk_surface(vertices: np.ndarray, faces: np.ndarray):
    """A vtkPolyData of a triangle mesh (for VTK reference queries)."""
    import pyvista as pv

    return pv.PolyData.from_regular_faces(np.asarray(vertices, float), np.asarray(faces))


def vtk_distance(polydata, points: np.ndarray) -> np.ndarray:
    """Unsigned point-to-surface distance with vtkImplicitPolyDataDistance, point by point."""
    import vtk

    function = vtk.vtkImplicitPolyDataDistance()
    function.SetInput(polydata)
    return np.array([abs(function.EvaluateFunction(*p)) for p in np.asarray(points, float)])


def obb_tree(polydata):
    import vtk

    tree = vtk.vtkOBBTree()
    tree.SetDataSet(polydata)
    tree.SetTolerance(1e-9)
    tree.BuildLocator()
    return tree


def _hits(tree, origin, direction, length):
    import vtk

    pts = vtk.vtkPoints()
    end = np.asarray(origin) + length * np.asarray(direction)
    tree.IntersectWithLine(list(map(float, origin)), list(map(float, end)), pts, None)
    hits = np.array([pts.GetPoint(i) for i in range(pts.GetNumberOfPoints())]).reshape(-1, 3)
    d = (hits - origin) @ direction
    return hits[np.argsort(d)], np.sort(d)


def segment_hits(tree, origin, direction, length):
    """Sorted intersections (points, distances) of a ray segment with an OBB tree."""
    return _hits(tree, origin, direction, length)
