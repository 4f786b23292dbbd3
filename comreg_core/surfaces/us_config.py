"""Settings of ultrasound bone surface extraction (YAML section ``us_extraction``): the B-mode
detector (:mod:`comreg_core.surfaces.us_detector`), the point clean-up
(:mod:`comreg_core.surfaces.us_denoise`) and what ``comreg extract-us`` does around them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from comreg_core.config import load_config, require


@dataclass(frozen=True)
class BoneDetectorConfig:
    """The classical B-mode bone detector (:mod:`comreg_core.surfaces.us_detector`). Lengths in
    mm.

    The defaults were set on every other frame of the UltraBones100k fibula sweep and checked on
    the others: raw detections within median 0.43 / 90th percentile 1.5 mm of the CT surface on
    the held-out frames, from 89% of them (tests/benchmarks/bench_us_detector.py prints the
    figures for the whole sweep). Another scanner, probe or imaging preset (echo thickness,
    speckle, gain, depth) may need other values: check them the same way on a sweep with a
    known pose.

    Attributes:
        working_pixel_mm: frames are block-averaged to about this pixel size first (0 = keep).
        smoothing_mm: Gaussian sigma of the intensity term.
        ridge_scale_mm: Gaussian sigma of the Hessian (about half the echo thickness).
        ridge_saturation: scale-normalised ridge strength (/ 99th percentile) counted as 1.
        shadow_gap_mm, shadow_depth_mm: the shadow window starts this far below a pixel and is
            this deep.
        shadow_reference_percentile: percentile over the imaged columns of each row that the
            shadow is compared with (50 = the median: right when the bone shadow covers less
            than half the image width; raise it when the bone fills most of the width).
        tissue_depth_mm: depth of the soft-tissue window above a pixel (ending shadow_gap_mm
            above it).
        tissue_min_fill: fraction of that window that must be echogenic (brighter than a
            quarter of the median tissue intensity) for full credit; 0 = no such check (for a
            phantom scanned in a water bath, where no tissue lies above the bone).
        min_depth_mm, max_depth_mm: depth range searched (below the transducer face); None =
            to the bottom.
        intensity_power, ridge_power, shadow_power, tissue_power: exponents of the four terms.
        threshold: probability above which a pixel counts as evidence for bone (0..1).
        max_slope_deg: steepest surface (to the array direction) followed between neighbouring
            scan lines.
        depth_change_penalty: cost per mm of depth change between neighbouring scan lines.
        segment_penalty: cost of starting a bone segment (probability x mm).
        min_segment_mm: bone segments narrower than this (along the array) are dropped.
        subpixel: refine each depth with a parabola through the probability.
    """

    working_pixel_mm: float = 0.1
    smoothing_mm: float = 0.1
    ridge_scale_mm: float = 0.3
    ridge_saturation: float = 0.2
    shadow_gap_mm: float = 1.0
    shadow_depth_mm: float = 10.0
    shadow_reference_percentile: float = 50.0
    tissue_depth_mm: float = 4.0
    tissue_min_fill: float = 0.75
    min_depth_mm: float = 2.0
    max_depth_mm: float | None = None
    intensity_power: float = 1.0
    ridge_power: float = 1.0
    shadow_power: float = 1.0
    tissue_power: float = 2.0
    threshold: float = 0.1
    max_slope_deg: float = 82.0
    depth_change_penalty: float = 0.05
    segment_penalty: float = 0.1
    min_segment_mm: float = 2.0
    subpixel: bool = True

    def __post_init__(self):
        for name in ("working_pixel_mm", "min_depth_mm", "smoothing_mm", "depth_change_penalty",
                     "segment_penalty", "min_segment_mm"):
            require(getattr(self, name) >= 0, f"detector.{name}", "must be >= 0")
        for name in ("ridge_scale_mm", "ridge_saturation", "shadow_depth_mm", "tissue_depth_mm"):
            require(getattr(self, name) > 0, f"detector.{name}", "must be > 0")
        require(self.shadow_gap_mm >= 0, "detector.shadow_gap_mm", "must be >= 0")
        for name in ("intensity_power", "ridge_power", "shadow_power", "tissue_power"):
            require(0 <= getattr(self, name) <= 10, f"detector.{name}", "must lie in [0, 10]")
        require(0 <= self.shadow_reference_percentile <= 100,
                "detector.shadow_reference_percentile", "must lie in [0, 100]")
        require(0 <= self.tissue_min_fill <= 1, "detector.tissue_min_fill", "must lie in [0, 1]")
        require(0 < self.threshold < 1, "detector.threshold", "must lie in (0, 1)")
        require(0 < self.max_slope_deg < 90, "detector.max_slope_deg", "must lie in (0, 90)")
        require(self.max_depth_mm is None or self.max_depth_mm > self.min_depth_mm,
                "detector.max_depth_mm", "must be larger than min_depth_mm")


@dataclass(frozen=True)
class DenoiseConfig:
    """Point-cloud clean-up after extraction. Lengths in mm; 0 switches a step off.

    The registration needs no down-sampling (it subsets clouds over 100,000 points itself);
    ``downsample`` is for point files meant for other tools (smaller, or evenly spaced).

    Attributes:
        cluster_radius_mm: DBSCAN neighbourhood radius (0 = no cluster selection).
        cluster_min_points: neighbours (self included) that make a point a core point.
        min_cluster_fraction: keep clusters with at least this fraction of the largest
            cluster's points (1.0 = the largest cluster only). A sparse sweep (frames several
            mm apart) breaks the bone into several clusters: keep them with a small fraction.
        outlier_neighbors: k of the statistical outlier removal (0 = off).
        outlier_std_ratio: drop points whose mean distance to their k neighbours exceeds the
            mean over all points by this many standard deviations.
        downsample: "none", "voxel" (centroid per voxel of ``voxel_size_mm``) or "fps" (farthest
            points, ``target_points`` of them).
        voxel_size_mm: voxel edge for "voxel".
        target_points: points left by "fps"; with "voxel", an upper bound reached by farthest
            point sampling of the voxel centroids (0 = no bound).
    """

    cluster_radius_mm: float = 5.0
    cluster_min_points: int = 5
    min_cluster_fraction: float = 0.05
    outlier_neighbors: int = 16
    outlier_std_ratio: float = 2.5
    downsample: Literal["none", "voxel", "fps"] = "none"
    voxel_size_mm: float = 0.5
    target_points: int = 0

    def __post_init__(self):
        require(self.cluster_radius_mm >= 0, "denoise.cluster_radius_mm", "must be >= 0")
        require(self.cluster_min_points >= 1, "denoise.cluster_min_points", "must be >= 1")
        require(0 < self.min_cluster_fraction <= 1, "denoise.min_cluster_fraction",
                "must lie in (0, 1]")
        require(self.outlier_neighbors >= 0, "denoise.outlier_neighbors", "must be >= 0")
        require(self.outlier_std_ratio > 0, "denoise.outlier_std_ratio", "must be > 0")
        require(self.voxel_size_mm > 0, "denoise.voxel_size_mm", "must be > 0")
        require(self.target_points >= 0, "denoise.target_points", "must be >= 0")
        require(self.downsample != "fps" or self.target_points > 0, "denoise.target_points",
                "must be > 0 when downsample is 'fps'")


@dataclass(frozen=True)
class USExtractionConfig:
    """Everything ``comreg extract-us`` does (YAML section ``us_extraction``).

    Attributes:
        detector: the B-mode detector (used without masks).
        denoise: the clean-up of the extracted points.
        mask_top_edge: with masks, keep only the top pixel of each bone run along the beam.
        frame_step: use every n-th valid frame (a faster extraction of a densely recorded
            sweep, whose neighbouring frames image nearly the same bone).
        reference: PLUS coordinate frame the points are given in (the name in the sweep's
            PLUS device-set configuration, e.g. ``Tracker`` instead of ``Reference``).
    """

    detector: BoneDetectorConfig = field(default_factory=BoneDetectorConfig)
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)
    mask_top_edge: bool = True
    frame_step: int = 1
    reference: str = "Reference"

    def __post_init__(self):
        require(self.frame_step >= 1, "frame_step", "must be >= 1")


def load_us_extraction_config(path: str | Path | None = None,
                              overrides: dict | None = None) -> USExtractionConfig:
    """Defaults, updated from a YAML file (bare keys or a ``us_extraction`` section), then from
    ``overrides``."""
    return load_config(USExtractionConfig, path, overrides, section="us_extraction")
