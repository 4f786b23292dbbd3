"""Bone surfaces: closed triangle meshes from CT label maps, and checked mesh inputs."""

from comreg_core.surfaces.ct import (
    SurfaceExtractionOptions,
    extract_bone_surface,
    prepare_bone_mesh,
    voxelize_mesh,
)

__all__ = ["SurfaceExtractionOptions", "extract_bone_surface", "prepare_bone_mesh", "voxelize_mesh"]
