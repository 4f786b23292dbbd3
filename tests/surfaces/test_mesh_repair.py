"""prepare_bone_mesh against the real CT fibula model and analytic spheres: a triangle soup with
flipped faces, a small hole, duplicate and degenerate faces, a cavity, a separate island, a big
hole, and a mesh of degenerate triangles only."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh

from comreg_core.errors import InvalidGeometryError
from comreg_core.io.meshes import SurfaceMesh
from comreg_core.surfaces import prepare_bone_mesh
from tests.helpers import assert_close
from tests.surfaces.mesh_checks import check_closed_outward


def test_prepare_repairs_unmerged_vertices_and_flipped_faces(fibula, caplog):
    rng = np.random.default_rng(7)
    faces = fibula.faces.copy()
    flipped = rng.random(len(faces)) < 0.5
    faces[flipped] = faces[flipped, ::-1]
    soup = SurfaceMesh(fibula.vertices[faces].reshape(-1, 3),  # 3 own vertices per face
                       np.arange(3 * len(faces)).reshape(-1, 3))
    assert not soup.to_trimesh().is_watertight

    with caplog.at_level(logging.INFO, logger="comreg_core.surfaces.mesh_repair"):
        repaired = prepare_bone_mesh(soup)

    tm = check_closed_outward(repaired)
    assert len(repaired.vertices) == len(fibula.vertices)
    assert_close(tm.volume, fibula.to_trimesh().volume, rtol=1e-9, what="volume (mm^3)")
    assert "duplicate vertices merged" in caplog.text and "faces flipped" in caplog.text


def test_prepare_fills_a_small_hole_and_drops_duplicate_and_degenerate_faces(fibula):
    faces = np.vstack([fibula.faces[1:], fibula.faces[:5], [[0, 0, 1]]])  # hole, dups, degenerate
    repaired = prepare_bone_mesh(SurfaceMesh(fibula.vertices, faces))
    tm = check_closed_outward(repaired)
    assert len(repaired.faces) == len(fibula.faces)
    assert_close(tm.volume, fibula.to_trimesh().volume, rtol=1e-4, what="volume (mm^3)")


def test_prepare_keeps_a_cavity_facing_inward_and_can_keep_the_largest_part():
    outer = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    inner = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    island = trimesh.creation.icosphere(subdivisions=1, radius=2.0)
    island.apply_translation([50.0, 0.0, 0.0])
    vertices = np.vstack([outer.vertices, inner.vertices, island.vertices])
    n_outer, n_inner = len(outer.vertices), len(inner.vertices)
    faces = np.vstack([outer.faces[:, ::-1], inner.faces + n_outer,  # both wound wrongly
                       island.faces + n_outer + n_inner])
    hollow = outer.volume - inner.volume

    repaired = prepare_bone_mesh(SurfaceMesh(vertices, faces)).to_trimesh()
    assert_close(repaired.volume, hollow + island.volume, rtol=1e-9, what="volume (mm^3)")
    largest = prepare_bone_mesh(SurfaceMesh(vertices, faces), largest_component=True)
    assert_close(largest.to_trimesh().volume, outer.volume, rtol=1e-9, what="outer only")


def test_prepare_leaves_a_clean_mesh_alone_and_warns_about_a_big_hole(fibula, caplog):
    with caplog.at_level(logging.INFO, logger="comreg_core.surfaces.mesh_repair"):
        clean = prepare_bone_mesh(fibula)
    assert caplog.text == ""
    np.testing.assert_array_equal(clean.faces, fibula.faces)
    assert_close(clean.vertices, fibula.vertices, what="vertices")

    opened = SurfaceMesh(fibula.vertices, fibula.faces[200:])  # a hole far beyond "small"
    with caplog.at_level(logging.WARNING, logger="comreg_core.surfaces.mesh_repair"):
        prepare_bone_mesh(opened)
    assert "not closed" in caplog.text


def test_prepare_rejects_a_mesh_of_only_degenerate_triangles():
    flat = SurfaceMesh(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), np.array([[0, 1, 2]]))
    with pytest.raises(InvalidGeometryError, match="zero area"):
        prepare_bone_mesh(flat)
