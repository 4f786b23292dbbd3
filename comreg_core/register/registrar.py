"""Registration of a US cloud to the CT: :class:`Registrar`, the one entry point.

- ``Registrar.from_ct(ct_mesh).register(us_points)``: the pose search alone
  (:mod:`comreg_core.registration.search.search`) from the principal-axes pose of the US cloud on the
  CT (or the prior's initial pose), with its flips, turns and slides, chosen by score. This
  path never imports torch.
- ``Registrar.from_run(run_dir).register(us_points)``: the same search, then the pretrained
  network's poses (:mod:`comreg_core.register.network`: completion, coarse pose, ICP) as
  further starts (:mod:`comreg_core.registration.search.network_starts`): kept only when clearly
  better, so never worse than the search alone. ``search=False`` is the paper's plain
  pipeline (network and ICP only).

Timings per stage (s): ``preprocess``, ``completion_and_coarse_pose``, ``icp``,
``search`` (the pose search), ``postprocess``, ``total`` (their sum, ``runtime_s``), and
``residuals`` (outside ``total``). Preparing the CT side (encoding, search cloud, grids) happens
once per Registrar, outside the timings.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from comreg_core.errors import ComRegError, InvalidGeometryError
from comreg_core.io.meshes import ct_fingerprint
from comreg_core.normalization import Normalization
from comreg_core.registration import (CTSurface, SearchConfig, SurfaceCloud,
                                      as_search_config, search_poses)
from comreg_core.registration.geometry.inputs import (beam_origins_for, limit_us_points,
                                                      subset_notice)
from comreg_core.registration.search.network_starts import add_network_starts
from comreg_core.registration.judgement.prior_reasons import prior_record
from comreg_core.registration.search.priors import Prior
from comreg_core.registration.search.result import RegistrationResult, residual_statistics
from comreg_core.registration.search.scoring import SearchResult
from comreg_core.registration.search.search import principal_axes_pose, us_subset_indices
from comreg_core.registration.geometry.surface import mesh_arrays
from comreg_core.registration.search.warm import warm_search
from comreg_core.transforms import apply_transform, as_points

#: A US cloud whose largest bounding-box extent is below this (mm) is taken to be in metres.
MIN_US_EXTENT_MM = 1.0


class Registrar:
    """The CT side of a registration, ready to register US clouds (search alone or network).

    Build with :meth:`from_ct` (the pose search alone) or :meth:`from_run` (with the pretrained
    network). Calling the object registers (``registrar(points)``), so it can be passed to
    :func:`comreg_core.evaluation.evaluate` as a method.

    Args:
        network: the pretrained network (:class:`~comreg_core.register.network.Network`), or
            None for the search alone.
        ct_points: ``(M, 3)`` mm, the CT cloud.
        normalization: the CT normalisation (the network's; the US cloud's size is checked
            against its scale).
        ct_vertices, ct_faces: the CT mesh (residual distances), or None to use the CT cloud.
        fingerprint: the CT fingerprint (sha256).
        space: the CT's patient space ("LPS"/"RAS").
        search: the pose search: None or True = on with the defaults of
            :class:`~comreg_core.registration.SearchConfig`, False = off (with a network:
            the paper's plain pipeline), or a ``SearchConfig`` (its ``enabled`` decides).
        warnings: what the run's own validation says against its network; copied into every
            result's ``warnings``.
    """

    def __init__(self, network, ct_points: np.ndarray, normalization: Normalization, *,
                 ct_vertices: np.ndarray | None = None, ct_faces: np.ndarray | None = None,
                 fingerprint: str = "", space: str = "LPS",
                 search: SearchConfig | bool | None = None,
                 warnings: list[str] | None = None):
        self.network = network
        self.warnings = list(warnings or [])
        self.ct_points = as_points(ct_points, "CT points")
        self.normalization = normalization
        self.fingerprint = fingerprint
        self.space = space
        self._ct_vertices, self._ct_faces = ct_vertices, ct_faces
        self.search_config = self._as_config(search)
        self._surface = None
        self._bare_cloud: SurfaceCloud | None = None

    @property
    def model(self):
        """The network's :class:`~comreg_core.model.comreg.ComRegNet`, or None."""
        return None if self.network is None else self.network.model

    @property
    def config(self):
        """The run's training config, or None without a network."""
        return None if self.network is None else self.network.config

    @property
    def device(self) -> str:
        """Where the network runs ("cpu" for the search alone)."""
        return "cpu" if self.network is None else str(self.network.device)

    @property
    def encoding(self):
        """The CT half of the network (computed once, cached)."""
        return self.network.encoding

    def deterministic_forward(self):
        """The network's one-thread context (:meth:`Network.deterministic_forward`)."""
        return self.network.deterministic_forward()

    def _as_config(self, search) -> SearchConfig:
        """``search`` as a :class:`SearchConfig`; without a network the search is the
        whole registration (always on)."""
        config = as_search_config(search)
        if self.network is None:
            config = replace(config, enabled=True)
        return config

    @classmethod
    def from_ct(cls, ct_mesh, *, search: SearchConfig | bool | None = None
                ) -> Registrar:
        """A Registrar with no network: the pose search alone on the CT mesh ``ct_mesh`` (a
        path, SurfaceMesh, ``(V, F)``, ...; mm). ``search`` as for :meth:`from_run`, but
        the search cannot be turned off (it is the whole registration)."""
        vertices, faces, space, _ = mesh_arrays(ct_mesh)
        return cls(None, vertices, Normalization.from_ct(vertices), ct_vertices=vertices,
                   ct_faces=faces, fingerprint=ct_fingerprint(vertices, faces)["sha256"],
                   space=space, search=search)

    @classmethod
    def from_run(cls, run_dir: str | Path, device: str = "auto", *, ct_mesh=None,
                 icp_points: int | None = None,
                 search: SearchConfig | bool | None = None) -> Registrar:
        """The pose search with the network of ``run_dir`` (a folder of ``comreg pretrain`` or
        its checkpoint file; :func:`~comreg_core.register.network.load_network`: weights only,
        ``ct_mesh`` checked against the run's CT, ``icp_points`` at inference). ``device``:
        ``"auto"``, ``"cpu"`` or ``"cuda"``. ``search``: see the class (not part of the
        run: the network is the same either way).

        Raises:
            CheckpointError: no/corrupt checkpoint, or one trained for another CT.
        """
        from comreg_core.register.network import load_network

        return cls(**load_network(run_dir, device, ct_mesh=ct_mesh, icp_points=icp_points),
                   search=search)

    # ------------------------------------------------------------------------------------------

    def search_target(self, n_points: int) -> SurfaceCloud:
        """The CT side of the pose search: ``n_points`` area-uniform samples of the CT mesh
        (:meth:`CTSurface.cloud`; the run's CT cloud with estimated normals when no mesh is
        known), built once and cached."""
        if self.surface is not None:
            return self.surface.cloud(n_points)
        if self._bare_cloud is None:
            self._bare_cloud = SurfaceCloud(self.ct_points)
        return self._bare_cloud

    def check_points(self, points, seed: int = 0) -> np.ndarray:
        """The US cloud as ``(N, 3)`` float64 (at most :data:`MAX_US_POINTS`, see
        :func:`limit_us_points`), or a clear :class:`InvalidGeometryError`."""
        pts = limit_us_points(as_points(points, "US points"), seed)
        need = 6 if self.network is None else max(self.network.min_points, 6)
        if len(pts) < need:
            raise InvalidGeometryError(
                f"The US cloud has {len(pts)} points; registration needs at least {need}.",
                "Extract a denser US bone surface (more frames, less denoising).")
        extent = float((pts.max(0) - pts.min(0)).max())
        distinct = len(np.unique(pts, axis=0)) if extent < MIN_US_EXTENT_MM else len(pts)
        if distinct < need:
            raise InvalidGeometryError(
                f"The US cloud has only {distinct} distinct point(s) among its {len(pts)}; "
                f"registration needs at least {need} different points.",
                "Check the export: the points should cover the bone surface seen in the sweep.")
        if extent < MIN_US_EXTENT_MM:
            raise InvalidGeometryError(
                f"The US cloud spans only {extent:.3g} mm; its coordinates look like metres.",
                "Convert the points to millimetres (multiply by 1000).")
        if extent > 10.0 * self.normalization.scale:
            raise InvalidGeometryError(
                f"The US cloud spans {extent:.0f} mm, over 10 times the CT bone "
                f"({self.normalization.scale:.0f} mm).",
                "Check its units (millimetres) and that it shows this bone.")
        return pts

    def register(self, points, seed: int = 0, *,
                 search: SearchConfig | bool | None = None,
                 beam_origins: np.ndarray | None = None,
                 prior: Prior | None = None,
                 warm_start: RegistrationResult | None = None,
                 residuals: bool = True) -> RegistrationResult:
        """Register a US bone cloud ``(N, 3)`` (mm, in the CT's patient space) to the CT.

        Args:
            points: the US bone points.
            seed: seeds torch's generator (the forward pass is deterministic anyway).
            search: this call's pose search setting (True/False/a config); None = the
                Registrar's (:attr:`search_config`).
            beam_origins: ``(N, 3)`` mm, where each point's ultrasound beam started (the
                probe's element; same frame as ``points``), or None. The pose search then
                rules out poses under which the CT surface faces away from the probe.
            prior: a :class:`~comreg_core.registration.search.priors.Prior` (an initial pose with its
                tolerances, landmark pairs; in any space, taken to the CT's) or None. The
                search then starts around it and keeps only poses within it (without a
                network ``T_init`` replaces the principal-axes start); ``info["prior"]`` is
                its record (:func:`~comreg_core.registration.judgement.prior_reasons.prior_record`: where the
                result lies in it, ``at_edge``, ``reasons`` for the verdict).
            warm_start: an earlier result of this registrar for the same sweep before it grew
                (live registration): its poses are refined on ``points`` instead of a full
                search, with no network pass (:mod:`comreg_core.registration.search.warm`;
                ``info["warm_start"]`` says which it was).
            residuals: measure the registered points' distances to the CT (:meth:`residuals`;
                with the mesh ~9 us a point, not part of ``runtime_s``); False leaves
                ``residuals`` empty (live updates, which judge a subset themselves).
        """
        config = self.search_config if search is None else self._as_config(search)
        if prior is not None:
            if not config.enabled:
                raise ComRegError("An initial pose or landmarks need the pose search, which is "
                                  "turned off.", "Drop --no-search (search=False).")
            prior = prior.in_space(self.space)
        if warm_start is not None and (warm_start.search is None or not config.enabled):
            raise ComRegError("A warm start needs the pose search, on in both registrations.",
                              "Register with the pose search on.")
        t: dict[str, float] = {}
        start = time.perf_counter()
        pts, origins, warnings = self._inputs(points, beam_origins, seed)
        check_s = time.perf_counter() - start
        target = self._prepare_ct(config)  # built once per CT: not part of the time
        start = time.perf_counter() - check_s  # the checks count as preprocessing
        T, T_coarse, dense, icp_rmse = self._start_pose(pts, target, prior, warm_start, seed,
                                                        t, start)
        found, t["search"] = None, 0.0
        if config.enabled:
            mark = time.perf_counter()
            if warm_start is not None:
                found = warm_search(pts, warm_start.search, target, config,
                                  beam_origins=origins, prior=prior, space=self.space)
            else:
                found = self._search(pts, target, config, origins, prior,
                                   None if self.network is None else (T, T_coarse, dense))
            T, icp_rmse = found.T_ct_us, found.best.icp_rmse_mm
            if found.polish is not None and math.isfinite(found.polish["rmse_mm"]):
                icp_rmse = found.polish["rmse_mm"]
            if self.network is not None:
                self.network.sync()
            t["search"] = time.perf_counter() - mark
        mark = time.perf_counter()
        completion_ct = np.zeros((0, 3)) if dense is None else apply_transform(T, dense)
        registered = apply_transform(T, pts)
        t["postprocess"] += time.perf_counter() - mark
        t["total"] = sum(t.values())
        mark = time.perf_counter()
        residuals = self.residuals(registered) if residuals else {}
        t["residuals"] = time.perf_counter() - mark
        info = self._info(T, T_coarse, t, residuals, warnings, found, warm_start, prior, pts,
                          config)
        return RegistrationResult(
            T_ct_us=T, T_ct_us_coarse=T_coarse, registered_points=registered,
            completion_ct=completion_ct, timings=t, runtime_s=t["total"],
            device=self.device, seed=int(seed), residuals=residuals,
            icp_rmse=icp_rmse, n_points=len(pts), search=found, info=info)

    def _inputs(self, points, beam_origins, seed: int):
        """``(points (N, 3), beam origins (N, 3) or None, warnings)``: the US cloud checked
        (:meth:`check_points`), points and origins subset alike above ``MAX_US_POINTS``."""
        n_given = len(points) if hasattr(points, "__len__") else None
        origins = None
        if beam_origins is not None:  # subset both alike (above MAX_US_POINTS)
            both = np.hstack([as_points(points, "US points"),
                              beam_origins_for(beam_origins, len(points))])
            both = limit_us_points(both, seed)
            points, origins = both[:, :3], both[:, 3:]
        pts = self.check_points(points, seed)  # before the CT side is prepared
        warnings = list(self.warnings)
        if n_given is not None and n_given > len(pts):
            warnings.append(subset_notice(n_given, len(pts)))
        return pts, origins, warnings

    def _prepare_ct(self, config: SearchConfig) -> SurfaceCloud | None:
        """The search's CT cloud (None with the search off), with everything a registration
        reads built once per CT: the network's CT half, the closest-point grid, the mesh's
        KD-tree."""
        if self.network is not None:
            self.network.encoding  # cached CT half
        target = self.search_target(config.target_points) if config.enabled else None
        if target is not None and config.refine_top:
            target.closest_point_grid
        mesh_refine = self.network is not None and self.network.model.config.icp.mesh_refine
        if (target is not None or mesh_refine) and self.surface is not None:
            self.surface.closest(self.ct_points[:1])
        return target

    def _start_pose(self, pts, target, prior, warm_start, seed: int, t: dict[str, float],
                    start: float):
        """``(T_ct_us, T_coarse (4, 4), completion (M, 3) US frame or None, ICP RMS mm)``
        before the search: the warm start's pose, the search's own start, or the network's
        answer; stage times into ``t``."""
        if warm_start is not None or self.network is None:
            T = warm_start.T_ct_us if warm_start is not None else search_start(pts, target,
                                                                                prior)
            t.update(preprocess=time.perf_counter() - start, completion_and_coarse_pose=0.0,
                     icp=0.0, postprocess=0.0)
            return T, T, None, float("nan")
        answer = self.network.pose(pts, seed, self.surface, t, start)
        return answer.T_ct_us, answer.T_coarse, answer.completion, answer.icp_rmse_mm

    @staticmethod
    def _info(T, T_coarse, timings, residuals, warnings, found, warm_start, prior, pts,
              config: SearchConfig) -> dict:
        """The result's ``info``: the coarse pose, timings, residuals, warnings, the search's
        record and flags, and the prior's record."""
        info = {"T_ct_us_coarse": T_coarse.tolist(), "timings_s": dict(timings),
                "residuals_mm": residuals, "warnings": warnings,
                "search": None if found is None else found.to_json(),
                "warm_start": warm_start is not None}
        if found is not None:  # the flag where other consumers (the plugin) look for it
            info.update(ambiguous=found.ambiguous, confidence=found.confidence)
        if prior is not None:
            info["prior"] = prior_record(prior, T, pts.mean(axis=0), found,
                                         min_confidence=config.min_confidence,
                                         score_floor_mm=config.score_floor_mm)
        return info

    __call__ = register

    def _search(self, pts: np.ndarray, target: SurfaceCloud, config: SearchConfig,
                origins: np.ndarray | None, prior: Prior | None,
                network: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> SearchResult:
        """The pose search alone (its own starts, always all of them), then with a network
        its poses ``(T_ct_us after its ICP, coarse T_ct_us, completion (M, 3) US frame)`` as
        further starts that win only by a clearly better score
        (:mod:`~comreg_core.registration.search.network_starts`)."""
        start_name = "pca" if getattr(prior, "T_init", None) is None else "init"
        result = search_poses(pts, search_start(pts, target, prior), target, None, config,
                              start_name=start_name, beam_origins=origins,
                              space=self.space, prior=prior)
        if network is None:
            return result
        T_network, T_coarse, completion = network
        starts = {"network": T_network, "coarse": T_coarse}
        if completion is not None and len(completion) >= 4:
            starts["completion"] = principal_axes_pose(completion, target)
        return add_network_starts(result, starts, pts, target, config,
                                  subset_indices=us_subset_indices(len(pts), config.icp_points),
                                  beam_origins=origins, prior=prior, space=self.space)

    @property
    def surface(self):
        """The CT mesh as a :class:`~comreg_core.registration.geometry.surface.CTSurface` (built
        once, shared by the residuals and the verdict), or None when no mesh is known."""
        if self._surface is None and self._ct_vertices is not None:
            self._surface = CTSurface((self._ct_vertices, self._ct_faces))
        return self._surface

    def residuals(self, registered: np.ndarray) -> dict[str, float]:
        """Distance statistics (mm) of registered US points to the CT surface (the mesh when
        known, else the CT cloud)."""
        if self.surface is not None:
            d = self.surface.distance(registered)
        else:
            from scipy.spatial import cKDTree

            d = cKDTree(self.ct_points).query(registered)[0]
        return residual_statistics(d)


def search_start(pts: np.ndarray, target: SurfaceCloud, prior: Prior | None) -> np.ndarray:
    """``(4, 4)`` the pose search's own base pose for ``(N, 3)`` US points (mm): the prior's
    initial pose when it has one, else the principal-axes pose on the CT."""
    T_init = getattr(prior, "T_init", None)
    return principal_axes_pose(pts, target) if T_init is None else T_init


