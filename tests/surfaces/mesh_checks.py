"""Checks shared by the CT surface and mesh repair tests."""

from __future__ import annotations

import trimesh

from comreg_core.io.meshes import SurfaceMesh


def check_closed_outward(mesh: SurfaceMesh) -> trimesh.Trimesh:
    tm = mesh.to_trimesh()
    assert tm.is_watertight, "mesh has open or non-manifold edges"
    assert tm.is_winding_consistent, "mesh winding is inconsistent"
    assert tm.volume > 0, f"mesh faces inward (signed volume {tm.volume:.1f} mm^3)"
    return tm
