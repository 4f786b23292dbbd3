"""Bone surfaces: closed triangle meshes from CT label maps, checked mesh inputs, and bone surface
points from tracked ultrasound sweeps (:mod:`comreg_core.surfaces.us`)."""

from comreg_core.surfaces.ct import SurfaceExtractionOptions, extract_bone_surface, voxelize_mesh
from comreg_core.surfaces.mesh_repair import prepare_bone_mesh
from comreg_core.surfaces.us import USExtractionConfig, extract_us_surface, extract_us_to_file

__all__ = ["SurfaceExtractionOptions", "extract_bone_surface", "prepare_bone_mesh", "voxelize_mesh",
           "USExtractionConfig", "extract_us_surface", "extract_us_to_file"]
