"""Checks and repairs of bone triangle meshes (numpy, scipy, trimesh): closedness, winding,
connected components, small holes, and the millimetre check.

:func:`prepare_bone_mesh` checks a mesh given directly (e.g. a Slicer model) and repairs what is
trivially broken: unmerged vertices, degenerate or duplicate faces, inconsistent winding, small
holes. The helpers take ``(N, 3)`` points and ``(M, 3)`` int triangles.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from comreg_core.errors import InvalidGeometryError
from comreg_core.io.meshes import SurfaceMesh

log = logging.getLogger(__name__)

#: Holes whose boundary has at most this many edges are filled by :func:`prepare_bone_mesh`.
MAX_HOLE_EDGES = 8
#: Smallest bounding-box extent (mm) a bone may have; smaller ones look like metres.
MIN_EXTENT_MM = 1.0


def check_millimetres(vertices: np.ndarray, where: str = "") -> float:
    """The largest bounding-box extent (mm) of a bone's ``(N, 3)`` vertices; raises
    :class:`InvalidGeometryError` below :data:`MIN_EXTENT_MM` (a bone in metres)."""
    extent = float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0
    if extent < MIN_EXTENT_MM:
        raise InvalidGeometryError(
            f"The bone mesh{where} is only {extent:.3g} units across, which looks like "
            "metres rather than millimetres.",
            "Scale it by 1000 (ComReg works in millimetres), e.g. in 3D Slicer's Transforms "
            "module, and export it again.")
    return extent


def prepare_bone_mesh(mesh: SurfaceMesh, *, largest_component: bool = False) -> SurfaceMesh:
    """``mesh`` checked and trivially repaired: vertices merged, degenerate and duplicate faces
    and unreferenced vertices dropped, winding made consistent and outward, small holes filled.

    Logs each repair; logs a warning (and still returns the mesh) if it stays open. Raises
    :class:`InvalidGeometryError` for a mesh in metres (:func:`check_millimetres`) or one that
    encloses no volume (fewer than 4 triangles, or closed but flat, e.g. a single triangle).
    """
    tm = mesh.to_trimesh()
    n_vertices, n_faces = len(tm.vertices), len(tm.faces)
    tm.merge_vertices()
    merged = n_vertices - len(tm.vertices)
    tm.update_faces(tm.nondegenerate_faces())
    degenerate = n_faces - len(tm.faces)
    tm.update_faces(tm.unique_faces())
    duplicate = n_faces - degenerate - len(tm.faces)
    where = f" '{mesh.path}'" if mesh.path else ""
    if len(tm.faces) == 0:
        raise InvalidGeometryError(f"All {n_faces} triangles of the mesh{where} have zero area.",
                                   "Export the bone model again; it holds no surface.")
    vertices, faces = compact_mesh(np.asarray(tm.vertices), np.asarray(tm.faces))
    extent = check_millimetres(vertices, where)

    dropped = 0
    if largest_component:
        n_before = len(faces)
        vertices, faces = keep_largest_component(vertices, faces)
        dropped = n_before - len(faces)
    faces, flipped = orient_outward(vertices, faces)
    faces, filled = fill_small_holes(faces)

    repairs = {"duplicate vertices merged": merged, "degenerate faces dropped": degenerate,
               "duplicate faces dropped": duplicate, "faces of smaller components dropped": dropped,
               "faces flipped": flipped, "holes filled": filled}
    done = ", ".join(f"{n} {what}" for what, n in repairs.items() if n)
    if done:
        log.info("Repaired mesh%s: %s.", where, done)
    if len(faces) < 4 or (is_closed(faces) and
                          abs(signed_volume(vertices, faces)) < 1e-9 * extent ** 3):
        raise InvalidGeometryError(
            f"The mesh{where} encloses no volume ({len(faces)} triangles): it is not a bone "
            "surface.", "Export the closed bone surface, e.g. from its segmentation.")
    if not is_closed(faces):
        log.warning("Mesh%s is not closed (watertight) after repair; distances and inside/outside "
                    "tests near its holes may be wrong.", where)
    return replace(mesh, vertices=vertices, faces=faces)


# --- mesh helpers (numpy) ----------------------------------------------------------------------


def compact_mesh(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(points, faces)`` without the points no face uses, faces renumbered to match."""
    used, inverse = np.unique(faces, return_inverse=True)
    return points[used], inverse.reshape(faces.shape)


def signed_volume(points: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by the triangles, positive when they wind counter-clockwise seen from
    outside (divergence theorem)."""
    a, b, c = (points[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c))) / 6.0


def _edge_keys(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(3M,)`` int64 keys of each face's directed edges ``a -> b`` and of their reverses."""
    n = int(faces.max()) + 1 if len(faces) else 0
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    return a * n + b, b * n + a


def _in_sorted(values: np.ndarray, sorted_keys: np.ndarray) -> np.ndarray:
    """``(len(values),)`` bool: which values occur in ``sorted_keys`` (faster than np.isin)."""
    at = np.minimum(np.searchsorted(sorted_keys, values), len(sorted_keys) - 1)
    return sorted_keys[at] == values


def is_closed(faces: np.ndarray) -> bool:
    """Closed 2-manifold with consistent winding: every directed edge occurs exactly once and
    its reverse occurs too (so each edge borders exactly two faces)."""
    if len(faces) == 0:
        return False
    keys, reverse = (np.sort(k) for k in _edge_keys(faces))
    return not (keys[1:] == keys[:-1]).any() and np.array_equal(keys, reverse)


def _component_labels(faces: np.ndarray, n_points: int) -> np.ndarray:
    """``(M,)`` label of each face's connected component (faces sharing a point connect)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = (faces.ravel(), faces[:, [1, 2, 0]].ravel())
    graph = coo_matrix((np.ones(len(edges[0])), edges), shape=(n_points, n_points))
    return connected_components(graph, directed=False)[1][faces[:, 0]]


def keep_largest_component(points: np.ndarray,
                            faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Only the connected component with the most faces."""
    labels = _component_labels(faces, len(points))
    largest = np.argmax(np.bincount(labels))
    return compact_mesh(points, faces[labels == largest])


def _edge_neighbours(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of faces sharing an edge that no other face uses: ``(P, 2)`` face indices and
    ``(P,)`` bool, True where both run the shared edge the same way (winding disagrees)."""
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    key = np.minimum(a, b) * (int(faces.max()) + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    _, start, count = np.unique(key[order], return_index=True, return_counts=True)
    first = order[start[count == 2]]
    second = order[start[count == 2] + 1]
    same_way = a[first] == a[second]
    return np.column_stack([first // 3, second // 3]), same_way


def orient_outward(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Faces re-wound consistently within each edge-connected body, each body facing outward
    (positive volume) unless it lies inside another body (a cavity wall, facing inward).

    Returns the faces and how many were flipped.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    pairs, same_way = _edge_neighbours(faces)
    n = len(faces)
    n_bodies, body = connected_components(
        coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)),
        directed=False)
    # One breadth-first pass from an extra root node n joined to each body's first face; edge
    # weight 2 = the neighbour must be flipped relative to its parent, 1 = kept.
    roots = np.unique(body, return_index=True)[1]
    rows = np.concatenate([pairs[:, 0], np.full(n_bodies, n)])
    cols = np.concatenate([pairs[:, 1], roots])
    weight = coo_matrix((np.concatenate([1 + same_way, np.ones(n_bodies)]), (rows, cols)),
                        shape=(n + 1, n + 1))
    graph = (weight + weight.T).tocsr()
    order, parent = breadth_first_order(graph, n, directed=False, return_predecessors=True)
    children = order[1:]
    relative = np.asarray(graph[parent[children], children]).ravel() == 2
    flip = [False] * (n + 1)
    for child, parent_of, rel in zip(children.tolist(), parent[children].tolist(),
                                     relative.tolist()):
        flip[child] = flip[parent_of] ^ rel
    flip = np.asarray(flip[:n])
    faces = np.where(flip[:, None], faces[:, ::-1], faces)

    a, b, c = (points[faces[:, i]] for i in range(3))
    volumes = np.bincount(body, np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0, n_bodies)
    outward = ~_nested_odd(points, faces, body, volumes)
    wrong = ((volumes > 0) != outward)[body]
    faces = np.where(wrong[:, None], faces[:, ::-1], faces)
    return faces, int(np.count_nonzero(flip != wrong))


def _nested_odd(points: np.ndarray, faces: np.ndarray, body: np.ndarray,
                volumes: np.ndarray) -> np.ndarray:
    """``(B,)`` bool: True where a body lies inside an odd number of other (larger) bodies."""
    import trimesh

    n_bodies = len(volumes)
    depth = np.zeros(n_bodies, dtype=int)
    if n_bodies == 1:
        return depth.astype(bool)
    corners = points[faces]  # (M, 3 corners, 3)
    lows = np.full((n_bodies, 3), np.inf)
    highs = np.full((n_bodies, 3), -np.inf)
    np.minimum.at(lows, body, corners.min(axis=1))
    np.maximum.at(highs, body, corners.max(axis=1))
    probe_faces = np.unique(body, return_index=True)[1]
    for outer in np.argsort(-np.abs(volumes)):
        inner = np.flatnonzero((np.abs(volumes) < abs(volumes[outer]))
                               & (lows >= lows[outer]).all(axis=1)
                               & (highs <= highs[outer]).all(axis=1))
        if len(inner):
            shell = trimesh.Trimesh(points, faces[body == outer], process=False)
            depth[inner] += shell.contains(corners[probe_faces[inner], 0])
    return depth % 2 == 1


def fill_small_holes(faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Fan-fill holes bounded by a simple loop of at most :data:`MAX_HOLE_EDGES` edges, wound to
    match their neighbours. Returns the faces and the number of holes filled."""
    if len(faces) == 0:
        return faces, 0
    keys, reverse = _edge_keys(faces)
    boundary = ~_in_sorted(reverse, np.sort(keys))
    starts = faces.ravel()[boundary]
    ends = faces[:, [1, 2, 0]].ravel()[boundary]
    if len(starts) == 0:
        return faces, 0
    unique_starts, counts = np.unique(starts, return_counts=True)
    simple = set(unique_starts[counts == 1].tolist())  # one outgoing boundary edge: a plain loop
    successor = {s: e for s, e in zip(starts.tolist(), ends.tolist()) if s in simple}

    new_faces = []
    holes = 0
    while successor:
        loop = [next(iter(successor))]
        while (nxt := successor.pop(loop[-1], None)) is not None and nxt != loop[0]:
            loop.append(nxt)
        if nxt == loop[0] and 3 <= len(loop) <= MAX_HOLE_EDGES:
            new_faces += [(loop[0], loop[i + 1], loop[i]) for i in range(1, len(loop) - 1)]
            holes += 1
    if not new_faces:
        return faces, 0
    return np.vstack([faces, np.array(new_faces, dtype=faces.dtype)]), holes
