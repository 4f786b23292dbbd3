"""The paper's baselines: Open3D RANSAC on FPFH features + ICP, and the ICP pseudo ground truth.

- ``"ransac"`` (:class:`RansacIcpBaseline`): the Open3D global-registration tutorial
  (https://www.open3d.org/docs/release/tutorial/pipelines/global_registration.html) that the
  paper cites for "RANSAC+ICP with default parameters": voxel down-sampling of both clouds,
  normals (hybrid radius ``2 * voxel``, 30 neighbours), FPFH (radius ``5 * voxel``, 100
  neighbours), ``registration_ransac_based_on_feature_matching`` (mutual filter, inlier
  distance ``1.5 * voxel``, 3-point samples, edge-length 0.9 and distance checkers,
  ``RANSACConvergenceCriteria(max_iterations, confidence)``, tutorial default 100000 / 0.999),
  then ``registration_icp`` point-to-plane with distance ``0.4 * voxel`` on the full-resolution
  clouds. Every factor is a :class:`RansacConfig` field. The tutorial's voxel (0.05 m) is for
  room scans; for bones ComReg uses 1 mm (tried 1, 1.5, 2, 3 and 4 mm on 6 simulated fibula
  sweeps: 1 mm gave the most successes, ~1-2 s per 20,000-point cloud on 2 shared cores). The
  CT side is ``ct_samples`` area-uniform points of the CT mesh (with the triangles' exact normals
  for the point-to-plane ICP; the FPFH path re-estimates normals on the down-sampled cloud
  exactly as for the US cloud, as the tutorial does). One safeguard beyond the tutorial: if ICP
  ends with a lower fitness than the RANSAC pose had at the ICP distance (point-to-plane ICP can
  slide along a near-cylindrical shaft and lose every correspondence), the RANSAC pose is kept.
- ``"icp-gt"`` (:class:`IcpGtBaseline`): the paper's pseudo ground truth, ICP started from the
  ground truth ("near-perfect initialisation"): point-to-plane ICP in numpy/scipy
  (:func:`~comreg_core.registration.geometry.icp.point_to_plane_icp`, no Open3D) to the (near-)exact
  closest points of the CT mesh and their triangle normals
  (:meth:`~comreg_core.registration.geometry.surface.CTSurface.matcher`), correspondences farther than
  ``max_distance_mm`` rejected (outliers such as false hits).

Open3D is imported only here and only when a RANSAC baseline is built; it is an optional
dependency (``pip install open3d``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from comreg_core.choices import BASELINES
from comreg_core.config import from_dict, require
from comreg_core.errors import ComRegError, InvalidGeometryError
from comreg_core.evaluation.outputs import RegistrationOutput
from comreg_core.registration.geometry.icp import point_to_plane_icp
from comreg_core.registration.geometry.surface import as_surface
from comreg_core.transforms import as_points, check_rigid, orthonormalize



@dataclass(frozen=True)
class RansacConfig:
    """Open3D RANSAC (FPFH) + ICP settings; distances are ``factor * voxel_size_mm``.

    Defaults are the Open3D global-registration tutorial's, except ``voxel_size_mm`` (mm bones).
    """

    voxel_size_mm: float = 1.0
    normal_radius_factor: float = 2.0
    normal_max_nn: int = 30
    fpfh_radius_factor: float = 5.0
    fpfh_max_nn: int = 100
    distance_factor: float = 1.5
    mutual_filter: bool = True
    ransac_n: int = 3
    edge_length_check: float = 0.9
    max_iterations: int = 100_000
    confidence: float = 0.999
    icp: Literal["point_to_plane", "point_to_point"] = "point_to_plane"
    icp_distance_factor: float = 0.4
    icp_max_iterations: int = 30
    ct_samples: int = 100_000

    def __post_init__(self):
        require(self.voxel_size_mm > 0, "ransac.voxel_size_mm", "must be positive (mm)")
        for name in ("normal_radius_factor", "fpfh_radius_factor", "distance_factor",
                     "icp_distance_factor"):
            require(getattr(self, name) > 0, f"ransac.{name}", "must be positive")
        for name in ("normal_max_nn", "fpfh_max_nn", "max_iterations", "icp_max_iterations"):
            require(getattr(self, name) >= 1, f"ransac.{name}", "must be at least 1")
        require(self.ransac_n >= 3, "ransac.ransac_n", "must be at least 3")
        require(0 < self.edge_length_check <= 1, "ransac.edge_length_check", "must lie in (0, 1]")
        require(0 < self.confidence < 1, "ransac.confidence", "must lie in (0, 1)")
        require(self.ct_samples >= 100, "ransac.ct_samples", "must be at least 100")


@dataclass(frozen=True)
class IcpGtConfig:
    """Pseudo ground truth: point-to-plane ICP from the ground-truth pose.

    Attributes:
        max_distance_mm: correspondences farther apart are ignored.
        max_iterations: ICP iterations at most.
        tolerance_mm: stop when an update moves no point of the cloud by more than this (mm).
        ct_samples: area-uniform CT surface samples that nominate candidate triangles.
    """

    max_distance_mm: float = 3.0
    max_iterations: int = 50
    tolerance_mm: float = 1e-5
    ct_samples: int = 200_000

    def __post_init__(self):
        require(self.max_distance_mm > 0, "icp_gt.max_distance_mm", "must be positive (mm)")
        require(self.max_iterations >= 1, "icp_gt.max_iterations", "must be at least 1")
        require(self.tolerance_mm > 0, "icp_gt.tolerance_mm", "must be positive (mm)")
        require(self.ct_samples >= 100, "icp_gt.ct_samples", "must be at least 100")


@dataclass(frozen=True)
class BaselineConfig:
    """Config section ``baselines:`` with ``ransac:`` and ``icp_gt:`` subsections."""

    ransac: RansacConfig = field(default_factory=RansacConfig)
    icp_gt: IcpGtConfig = field(default_factory=IcpGtConfig)


def baseline_config_from_dict(data: dict | None) -> BaselineConfig:
    """:class:`BaselineConfig` from a (partial) dict, e.g. ``{"ransac": {"max_iterations":
    1000000}}``; unknown keys and bad values raise :class:`~comreg_core.config.ConfigError`."""
    return from_dict(BaselineConfig, data, "baselines")


def require_open3d():
    """Import and return ``open3d``, or raise :class:`ComRegError` saying how to install it."""
    try:
        import open3d
    except (ImportError, OSError) as exc:
        raise ComRegError(
            f"The RANSAC baseline needs Open3D, which cannot be imported ({exc}).",
            "Install it into this environment with 'python -m pip install open3d' (a ~400 MB "
            "wheel; Linux also needs the system libusb, e.g. 'apt-get install libusb-1.0-0'), "
            "or evaluate without the 'ransac' method.") from None
    return open3d


# --- RANSAC + ICP (Open3D) -----------------------------------------------------------------------

class RansacIcpBaseline:
    """Open3D RANSAC on FPFH features, then ICP: ``baseline(us_points) -> RegistrationOutput``.

    Args:
        ct_mesh: the CT bone surface (anything
            :func:`~comreg_core.registration.geometry.surface.as_surface`
            accepts), mm, in the space the US points will be given in.
        config: :class:`RansacConfig` (or a whole :class:`BaselineConfig`).
        seed: seeds Open3D's global random generator before every RANSAC run; call ``i`` uses
            the ``i``-th draw of a generator seeded with ``seed``, so a run of calls is
            reproducible up to thread scheduling: Open3D's RANSAC tries its samples in parallel
            threads and, under load, may keep a different but equally good pose (on the 2-core
            machine repeated runs agreed to 1e-11, or within ~0.01 mm after ICP when loaded).
            With ``OMP_NUM_THREADS=1`` set before Open3D is imported, repeats agree to ~1e-13.

    The CT preparation (sampling, down-sampling, normals, FPFH) happens once here and is timed
    in ``prepare_s``; it is not part of each call's ``runtime_s`` (the CT is preoperative).
    """

    name = "ransac"
    needs_ground_truth = False

    def __init__(self, ct_mesh, config: RansacConfig | BaselineConfig | None = None,
                 seed: int = 0):
        if isinstance(config, BaselineConfig):
            config = config.ransac
        self.config = config or RansacConfig()
        self._o3d = require_open3d()
        self._rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        surface = as_surface(ct_mesh)
        points, normals = surface.samples(self.config.ct_samples)
        self._target = self._cloud(points, normals)
        self._target_down, self._target_fpfh = self._features(self._cloud(points))
        self.prepare_s = time.perf_counter() - t0

    def reseed(self, seed: int) -> None:
        """Restart the seed sequence: the next call behaves like the first after construction
        with ``seed``."""
        self._rng = np.random.default_rng(seed)

    def _cloud(self, points: np.ndarray, normals: np.ndarray | None = None):
        o3d = self._o3d
        cloud = o3d.geometry.PointCloud()
        cloud.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
        if normals is not None:
            cloud.normals = o3d.utility.Vector3dVector(
                np.ascontiguousarray(normals, dtype=np.float64))
        return cloud

    def _features(self, cloud):
        o3d, c = self._o3d, self.config
        voxel = c.voxel_size_mm
        down = cloud.voxel_down_sample(voxel)
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(
            radius=c.normal_radius_factor * voxel, max_nn=c.normal_max_nn))
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            down, o3d.geometry.KDTreeSearchParamHybrid(radius=c.fpfh_radius_factor * voxel,
                                                       max_nn=c.fpfh_max_nn))
        return down, fpfh

    def __call__(self, us_points: np.ndarray) -> RegistrationOutput:
        """Register ``(N, 3)`` US points (mm) to the CT; returns ``T_ct_us`` and the runtime
        (source features + RANSAC + ICP)."""
        o3d, c = self._o3d, self.config
        reg = o3d.pipelines.registration
        pts = as_points(us_points, "US points")
        if len(pts) < 3:
            raise InvalidGeometryError(f"The US points have {len(pts)} points; registration "
                                       "needs at least 3.", "Pass a larger cloud.")
        seed = int(self._rng.integers(0, 2**31 - 1))
        t0 = time.perf_counter()
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            source = self._cloud(pts)
            source_down, source_fpfh = self._features(source)
            if len(source_down.points) < c.ransac_n:
                raise InvalidGeometryError(
                    f"After {c.voxel_size_mm} mm voxel down-sampling the US cloud has "
                    f"{len(source_down.points)} points, too few for RANSAC.",
                    "Pass a larger cloud or lower ransac.voxel_size_mm.")
            distance = c.distance_factor * c.voxel_size_mm
            o3d.utility.random.seed(seed)
            ransac = reg.registration_ransac_based_on_feature_matching(
                source_down, self._target_down, source_fpfh, self._target_fpfh,
                c.mutual_filter, distance, reg.TransformationEstimationPointToPoint(False),
                c.ransac_n,
                [reg.CorrespondenceCheckerBasedOnEdgeLength(c.edge_length_check),
                 reg.CorrespondenceCheckerBasedOnDistance(distance)],
                reg.RANSACConvergenceCriteria(c.max_iterations, c.confidence))
            t_ransac = time.perf_counter()
            icp_distance = c.icp_distance_factor * c.voxel_size_mm
            estimation = (reg.TransformationEstimationPointToPlane() if c.icp == "point_to_plane"
                          else reg.TransformationEstimationPointToPoint(False))
            T_ransac = np.asarray(ransac.transformation, dtype=np.float64)
            icp = reg.registration_icp(source, self._target, icp_distance, T_ransac, estimation,
                                       reg.ICPConvergenceCriteria(
                                           max_iteration=c.icp_max_iterations))
            start = reg.evaluate_registration(source, self._target, icp_distance, T_ransac)
        T_icp = np.asarray(icp.transformation, dtype=np.float64)
        use_icp = bool(icp.fitness >= start.fitness and np.isfinite(T_icp).all())
        T = T_icp if use_icp else T_ransac
        runtime = time.perf_counter() - t0
        info: dict[str, Any] = {
            "seed": seed, "ransac_fitness": float(ransac.fitness),
            "ransac_inlier_rmse_mm": float(ransac.inlier_rmse),
            "ransac_correspondences": len(ransac.correspondence_set),
            "icp_fitness": float(icp.fitness), "icp_inlier_rmse_mm": float(icp.inlier_rmse),
            "icp_used": use_icp, "source_down_points": len(source_down.points),
            "ransac_s": t_ransac - t0, "icp_s": runtime - (t_ransac - t0)}
        return RegistrationOutput(check_rigid(orthonormalize(T)), runtime, None, info)


class IcpGtBaseline:
    """The pseudo ground truth: ICP from the ground-truth pose.

    ``baseline(us_points, T_ct_us_gt) -> RegistrationOutput``; ``needs_ground_truth = True`` tells
    :func:`~comreg_core.evaluation.evaluate.evaluate` to pass the trial's ground truth.
    """

    name = "icp-gt"
    needs_ground_truth = True

    def __init__(self, ct_mesh, config: IcpGtConfig | BaselineConfig | None = None):
        if isinstance(config, BaselineConfig):
            config = config.icp_gt
        self.config = config or IcpGtConfig()
        t0 = time.perf_counter()
        self.surface = as_surface(ct_mesh)
        self.matcher = self.surface.matcher(self.config.max_distance_mm,
                                            n_samples=self.config.ct_samples)
        self.matcher(self.surface.vertices[:1])  # build its KD-tree now, outside the timings
        self.prepare_s = time.perf_counter() - t0

    def __call__(self, us_points: np.ndarray, T_ct_us_gt: np.ndarray) -> RegistrationOutput:
        c = self.config
        t0 = time.perf_counter()
        pts = as_points(us_points, "US points")
        if len(pts) < 6:
            raise InvalidGeometryError(f"The US points have {len(pts)} points; ICP needs at "
                                       "least 6.", "Pass a larger cloud.")
        fit = point_to_plane_icp(pts, check_rigid(T_ct_us_gt), self.matcher,
                                 iterations=c.max_iterations, tolerance_mm=c.tolerance_mm)
        info = {"iterations": int(fit.iterations), "inlier_fraction": float(fit.inlier_fraction),
                "rmse_mm": float(fit.rmse_mm), "converged": bool(fit.converged)}
        return RegistrationOutput(orthonormalize(fit.T), time.perf_counter() - t0, None, info)


def baseline_methods(names, ct_mesh, config: BaselineConfig | None = None, seed: int = 0
                     ) -> dict[str, Any]:
    """Build the named baselines (``"ransac"``, ``"icp-gt"``) for ``ct_mesh``, sharing one
    prepared CT surface. Unknown names raise :class:`ComRegError` listing the known ones."""
    if isinstance(names, str):
        names = [names]
    names = list(names)
    unknown = [n for n in names if n not in BASELINES]
    if unknown:
        raise ComRegError(f"Unknown baseline method(s) {', '.join(map(repr, unknown))}.",
                          f"Known baselines: {', '.join(BASELINES)}.")
    config = config or BaselineConfig()
    surface = as_surface(ct_mesh)
    methods: dict[str, Any] = {}
    for name in names:
        if name == "ransac":
            methods[name] = RansacIcpBaseline(surface, config.ransac, seed)
        else:
            methods[name] = IcpGtBaseline(surface, config.icp_gt)
    return methods
