"""Bone surfaces: closed triangle meshes from CT label maps (:mod:`comreg_core.surfaces.ct`),
checked mesh inputs (:mod:`comreg_core.surfaces.mesh_repair`), and bone surface points from tracked
ultrasound sweeps (:mod:`comreg_core.surfaces.us` and its ``us_*`` modules)."""

from comreg_core.surfaces.ct import SurfaceExtractionOptions, extract_bone_surface, voxelize_mesh
from comreg_core.surfaces.mesh_repair import prepare_bone_mesh
from comreg_core.surfaces.us import extract_us_surface, extract_us_to_file
from comreg_core.surfaces.us_config import USExtractionConfig

__all__ = ["SurfaceExtractionOptions", "extract_bone_surface", "prepare_bone_mesh", "voxelize_mesh",
           "USExtractionConfig", "extract_us_surface", "extract_us_to_file"]
