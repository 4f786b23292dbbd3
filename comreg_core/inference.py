"""Registration of a US cloud to the CT: ``Registrar`` (``register_output`` writes its folder).

Two ways, one result type (:class:`~comreg_core.registration.result.RegistrationResult`):

- ``Registrar.from_ct(ct_mesh).register(us_points)``: no network. The pose search
  (:mod:`comreg_core.registration.search`) starts from the principal-axes pose of the US cloud
  on the CT (base ``pca``) with its flips, turns and slides, and chooses by score.
- ``Registrar.from_run(run_dir).register(us_points)``, the pretrained network:

1. checks the US cloud (``(N, 3)`` finite mm, enough points, not in metres), normalises it with
   the *CT's* centre and scale (as in training);
2. one forward pass: completion ``f`` -> coarse pose ``g`` -> differentiable ICP, against the CT
   half encoded once per Registrar (cached);
3. maps the estimate back to mm: ``T_ct_us`` (``T_ct_us @ p_us = p_ct``), the coarse estimate,
   the completed bone in the CT frame, and residual statistics of the registered US points
   (exact distances to the CT mesh surface).

4. unless turned off, the **pose search** (:mod:`comreg_core.registration.search`) exactly as
   without a network (every one of its starts), then the network's poses (after its ICP, its
   coarse pose, the principal-axes solve of its completion) as further starts
   (:mod:`comreg_core.registration.network_starts`): refined, the best polished, and kept only
   when it scores better than the search's choice by more than a tie. The chosen score is
   never worse than the search alone's. On by default; ``hypotheses=False`` (``comreg register
   --no-hypotheses``) is the paper's plain pipeline, bit for bit.

Timings per stage (seconds): ``preprocess`` (checks, normalisation, transfer),
``completion_and_coarse_pose`` (``f`` on the US cloud and ``g``), ``icp`` (FPS subset + ICP),
``hypotheses`` (0.0 when off), ``postprocess`` (back to mm, the completion), ``total`` (their sum, =
``runtime_s``), and ``residuals`` (distance statistics; outside ``total``). On CUDA each stage
ends with a synchronisation. Preparing the CT side (its encoding, the hypotheses' dense CT
cloud, closest-point grid and mesh matcher) happens once per Registrar, outside the timings.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from comreg_core import runs
from comreg_core.errors import ComRegError, InvalidGeometryError
from comreg_core.registration import (CTSurface, HypothesisConfig, SurfaceCloud,
                                      as_hypothesis_config, search_hypotheses)
from comreg_core.registration.icp import refine_on_mesh
from comreg_core.registration.inputs import beam_origins_for, limit_us_points, subset_notice
from comreg_core.registration.result import RegistrationResult, residual_statistics
from comreg_core.registration.priors import Prior, prior_record
from comreg_core.registration.network_starts import add_network_starts
from comreg_core.registration.scoring import HypothesisResult
from comreg_core.registration.search import principal_axes_pose, us_subset_indices
from comreg_core.registration.warm import warm_search
from comreg_core.registration.surface import mesh_arrays
from comreg_core.model.comreg import ComRegNet
from comreg_core.model.normalization import Normalization
from comreg_core.model.ops import subsample
from comreg_core.training.checkpoint import (CheckpointError, check_fingerprint, check_same_bone,
                                             ct_fingerprint, load_checkpoint, network_warning)
from comreg_core.training.config import PretrainConfig, config_from_yaml
from comreg_core.training.trainer import resolve_device
from comreg_core.transforms import apply_transform, as_points, orthonormalize

log = logging.getLogger(__name__)

#: A US cloud whose largest bounding-box extent is below this (mm) is taken to be in metres.
MIN_US_EXTENT_MM = 1.0


class Registrar:
    """A pretrained ComReg network for one CT, ready to register US clouds.

    Build with :meth:`from_run`. Calling the object registers (``registrar(points)``), so it can
    be passed to :func:`comreg_core.evaluation.evaluate` as a method.

    Args:
        model: the network (its config decides the ICP point count).
        ct_points: ``(M, 3)`` mm, the run's CT cloud.
        normalization: the run's CT normalisation.
        ct_vertices, ct_faces: the CT mesh (residual distances), or None to use the CT cloud.
        fingerprint: the CT fingerprint (sha256) the model was trained for.
        space: the CT's patient space ("LPS"/"RAS").
        device: torch device.
        config: the run's training config (kept for reference).
        hypotheses: the test-time hypotheses stage: None or True = on with the defaults of
            :class:`~comreg_core.registration.HypothesisConfig`, False = off (the paper's plain
            pipeline), or a ``HypothesisConfig`` (its ``enabled`` decides).
        warnings: what the run's own validation says against its network
            (:func:`~comreg_core.training.checkpoint.network_warning`); copied into every
            result's ``warnings``.
    """

    def __init__(self, model: ComRegNet | None, ct_points: np.ndarray,
                 normalization: Normalization,
                 *, ct_vertices: np.ndarray | None = None, ct_faces: np.ndarray | None = None,
                 fingerprint: str = "", space: str = "LPS", device: str | torch.device = "cpu",
                 config: PretrainConfig | None = None,
                 hypotheses: HypothesisConfig | bool | None = None,
                 warnings: list[str] | None = None):
        self.device = resolve_device(device)
        self.warnings = list(warnings or [])
        self.model = None if model is None else model.to(self.device).eval()
        self.ct_points = as_points(ct_points, "CT points")
        self.normalization = normalization
        self.fingerprint = fingerprint
        self.space = space
        self.config = config
        self._ct_vertices, self._ct_faces = ct_vertices, ct_faces
        self.hypothesis_config = self._search_config(hypotheses)
        self._surface = None
        self._encoding = None
        self._bare_cloud: SurfaceCloud | None = None

    def _search_config(self, hypotheses) -> HypothesisConfig:
        """``hypotheses`` as a :class:`HypothesisConfig`; without a network the search is the
        whole registration (always on) and ties go to the best score (no network's pose)."""
        config = as_hypothesis_config(hypotheses)
        if self.model is None:
            config = replace(config, enabled=True)
        return config

    @classmethod
    def from_ct(cls, ct_mesh, *, hypotheses: HypothesisConfig | bool | None = None
                ) -> Registrar:
        """A Registrar with no network: the pose search alone on the CT mesh ``ct_mesh`` (a
        path, SurfaceMesh, ``(V, F)``, ...; mm). ``hypotheses`` as for :meth:`from_run`, but
        the search cannot be turned off (it is the whole registration) and ties are broken by
        score (there is no network's pose to prefer)."""
        vertices, faces, space, _ = mesh_arrays(ct_mesh)
        return cls(None, vertices, Normalization.from_ct(vertices), ct_vertices=vertices,
                   ct_faces=faces, fingerprint=ct_fingerprint(vertices, faces)["sha256"],
                   space=space, device="cpu", hypotheses=hypotheses)

    @classmethod
    def from_run(cls, run_dir: str | Path, device: str = "auto", *, ct_mesh=None,
                 icp_points: int | None = None,
                 hypotheses: HypothesisConfig | bool | None = None) -> Registrar:
        """Load ``run_dir/checkpoint.pt`` (weights_only).

        Args:
            run_dir: a folder written by :func:`comreg_core.training.pretrain` (or the
                checkpoint file itself).
            device: ``"auto"``, ``"cpu"`` or ``"cuda"``.
            ct_mesh: optional CT mesh (path or SurfaceMesh) to check against the run's CT
                fingerprint.
            icp_points: ICP points per cloud at inference (default: the trained value; ICP has
                no weights, so e.g. 4096 with a model trained at 2048 is valid).
            hypotheses: the hypotheses stage (see the class): None/True = on (defaults), False
                = off, or a :class:`~comreg_core.registration.HypothesisConfig`. Not part of the
                run: the network is the same either way.

        Raises:
            CheckpointError: no/corrupt checkpoint; the checkpoint was trained for another CT
                (``ct_mesh`` given and different, or the run's ``ct_fingerprint.json`` differs).
        """
        dev = resolve_device(device)
        state = load_checkpoint(run_dir, map_location="cpu")
        expected = state["ct_fingerprint"]
        stored = ct_fingerprint(state["ct_vertices"].numpy(), state["ct_faces"].numpy())
        check_fingerprint(expected, stored, " (its stored CT mesh)")
        fp_file = Path(run_dir) / runs.FINGERPRINT if Path(run_dir).is_dir() else None
        if fp_file is not None and fp_file.is_file():
            check_fingerprint(expected, json.loads(fp_file.read_text(encoding="utf-8")),
                              f" in '{run_dir}' (ct_fingerprint.json)")
        if ct_mesh is not None:
            gap = check_same_bone(state, ct_mesh, f" in '{run_dir}'")
            if gap > 0:
                log.info("The given CT mesh is the run's bone re-meshed (%.2f mm apart); the "
                         "run's own mesh is used.", gap)
        cfg = config_from_yaml(state["config_yaml"], f"config stored in '{run_dir}'")
        model_cfg = cfg.model
        if icp_points is not None:
            model_cfg = replace(model_cfg, icp=replace(model_cfg.icp, num_points=int(icp_points)))
        try:  # the stored weights must fit the network the stored config describes
            model = ComRegNet(model_cfg)
            model.load_state_dict(state["model"])
        except (RuntimeError, ValueError, TypeError, KeyError) as exc:
            raise CheckpointError(
                f"The checkpoint in '{run_dir}' does not fit its own network config "
                f"({type(exc).__name__}: {' '.join(str(exc).split())[:200]}).",
                "Train again (comreg pretrain), or use an intact run folder.") from None
        norm = Normalization(center=state["norm_center"].numpy(),
                             scale=float(state["norm_scale"]))
        return cls(model, state["ct_points"].numpy(), norm,
                   ct_vertices=state["ct_vertices"].numpy(), ct_faces=state["ct_faces"].numpy(),
                   fingerprint=expected, space=str(state.get("ct_space", "LPS")), device=dev,
                   config=cfg, hypotheses=hypotheses,
                   warnings=[w] if (w := network_warning(state)) else [])

    # ------------------------------------------------------------------------------------------

    @contextlib.contextmanager
    def deterministic_forward(self):
        """On the CPU, run the network on one thread: torch splits its sums across threads, so
        the output would change in the last float32 digits with the thread count (measured: the
        coarse pose by up to 5e-5 mm at 1 vs 2 threads). One thread makes it bit-identical at any
        thread count and load; the forward pass of the ``cpu`` preset takes ~0.04 s either way."""
        if self.device.type != "cpu":
            yield
            return
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            yield
        finally:
            torch.set_num_threads(threads)

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @property
    def encoding(self):
        """The CT half of the network (computed once, cached)."""
        if self._encoding is None:
            ct = torch.from_numpy(self.normalization.points_to_model(self.ct_points)).float()
            with torch.inference_mode(), self.deterministic_forward():
                self._encoding = self.model.encode_target(ct[None].to(self.device))
        return self._encoding

    def hypothesis_target(self, n_points: int) -> SurfaceCloud:
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
        need = 6 if self.model is None else max(self.model.completion.min_points, 6)
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
                 hypotheses: HypothesisConfig | bool | None = None,
                 beam_origins: np.ndarray | None = None,
                 prior: Prior | None = None,
                 warm_start: RegistrationResult | None = None,
                 residuals: bool = True) -> RegistrationResult:
        """Register a US bone cloud ``(N, 3)`` (mm, in the CT's patient space) to the CT.

        Args:
            points: the US bone points.
            seed: seeds torch's generator (the forward pass is deterministic anyway).
            hypotheses: this call's hypotheses setting (True/False/a config); None = the
                Registrar's (:attr:`hypothesis_config`).
            beam_origins: ``(N, 3)`` mm, where each point's ultrasound beam started (the
                probe's element; same frame as ``points``), or None. The pose search then
                rules out poses under which the CT surface faces away from the probe.
            prior: a :class:`~comreg_core.registration.priors.Prior` (an initial pose with its
                tolerances, landmark pairs; in any space, taken to the CT's) or None. The
                search then starts around it and keeps only poses within it (without a
                network ``T_init`` replaces the principal-axes start); ``info["prior"]`` is
                its record (:func:`~comreg_core.registration.priors.prior_record`: where the
                result lies in it, ``at_edge``, ``reasons`` for the verdict).
            warm_start: an earlier result of this registrar for the same sweep before it grew
                (live registration): its poses are refined on ``points`` instead of a full
                search, with no network pass (:mod:`comreg_core.registration.warm`;
                ``info["warm_start"]`` says which it was).
            residuals: measure the registered points' distances to the CT (:meth:`residuals`;
                with the mesh ~9 us a point, not part of ``runtime_s``); False leaves
                ``residuals`` empty (live updates, which judge a subset themselves).
        """
        hyp_cfg = (self.hypothesis_config if hypotheses is None
                   else self._search_config(hypotheses))
        if prior is not None:
            if not hyp_cfg.enabled:
                raise ComRegError("An initial pose or landmarks need the pose search, which is "
                                  "turned off.", "Drop --no-hypotheses (hypotheses=False).")
            prior = prior.in_space(self.space)
        t = {}
        start = time.perf_counter()
        n_given = len(points) if hasattr(points, "__len__") else None
        origins = None
        if beam_origins is not None:  # subset both alike (above MAX_US_POINTS)
            both = np.hstack([as_points(points, "US points"),
                              beam_origins_for(beam_origins, len(points))])
            both = limit_us_points(both, seed)
            points, origins = both[:, :3], both[:, 3:]
        pts = self.check_points(points, seed)  # before the CT side is prepared
        check_s = time.perf_counter() - start
        if self.model is not None:
            self.encoding  # cached CT half: not part of a registration's time
        target = self.hypothesis_target(hyp_cfg.target_points) if hyp_cfg.enabled else None
        if target is not None and hyp_cfg.refine_top:
            target.closest_point_grid  # built once per CT: not part of a registration's time
        mesh_refine = self.model is not None and self.model.config.icp.mesh_refine
        if (target is not None or mesh_refine) and self.surface is not None:
            self.surface.closest(self.ct_points[:1])  # likewise (its KD-tree)
        start = time.perf_counter() - check_s  # the checks count as preprocessing
        warnings = list(self.warnings)
        if n_given is not None and n_given > len(pts):
            warnings.append(subset_notice(n_given, len(pts)))
        if warm_start is not None:
            if warm_start.hypotheses is None or not hyp_cfg.enabled:
                raise ComRegError("A warm start needs the pose search, on in both "
                                  "registrations.", "Register with hypotheses on.")
            T = T_coarse = warm_start.T_ct_us
            dense, icp_rmse = None, float("nan")
            t.update(preprocess=time.perf_counter() - start, completion_and_coarse_pose=0.0,
                     icp=0.0, postprocess=0.0)
        elif self.model is None:
            T = T_coarse = search_start(pts, target, prior)
            dense, icp_rmse = None, float("nan")
            t.update(preprocess=time.perf_counter() - start, completion_and_coarse_pose=0.0,
                     icp=0.0, postprocess=0.0)
        else:
            T, T_coarse, dense, icp_rmse = self._network_pose(pts, seed, t, start)
        hyp, t["hypotheses"] = None, 0.0
        if hyp_cfg.enabled:
            mark = time.perf_counter()
            if warm_start is not None:
                hyp = warm_search(pts, warm_start.hypotheses, target, hyp_cfg,
                                  beam_origins=origins, prior=prior, space=self.space)
            else:
                hyp = self._search(pts, target, hyp_cfg, origins, prior,
                                   None if self.model is None else (T, T_coarse, dense))
            T, icp_rmse = hyp.T_ct_us, hyp.best.icp_rmse_mm
            if hyp.polish is not None and math.isfinite(hyp.polish["rmse_mm"]):
                icp_rmse = hyp.polish["rmse_mm"]
            self._sync()
            t["hypotheses"] = time.perf_counter() - mark
        mark = time.perf_counter()
        completion_ct = np.zeros((0, 3)) if dense is None else apply_transform(T, dense)
        registered = apply_transform(T, pts)
        t["postprocess"] += time.perf_counter() - mark
        t["total"] = sum(t.values())
        mark = time.perf_counter()
        residuals = self.residuals(registered) if residuals else {}
        t["residuals"] = time.perf_counter() - mark
        info = {"T_ct_us_coarse": T_coarse.tolist(), "timings_s": dict(t),
                "residuals_mm": residuals, "warnings": warnings,
                "hypotheses": None if hyp is None else hyp.to_json(),
                "warm_start": warm_start is not None}
        if hyp is not None:  # the flag where other consumers (the plugin) look for it
            info.update(ambiguous=hyp.ambiguous, confidence=hyp.confidence)
        if prior is not None:
            info["prior"] = prior_record(prior, T, pts.mean(axis=0), hyp,
                                         min_confidence=hyp_cfg.min_confidence,
                                         score_floor_mm=hyp_cfg.score_floor_mm)
        return RegistrationResult(
            T_ct_us=T, T_ct_us_coarse=T_coarse, registered_points=registered,
            completion_ct=completion_ct, timings=t, runtime_s=t["total"],
            device=str(self.device), seed=int(seed), residuals=residuals,
            icp_rmse=icp_rmse, n_points=len(pts), hypotheses=hyp, info=info)

    __call__ = register

    def _search(self, pts: np.ndarray, target: SurfaceCloud, config: HypothesisConfig,
                origins: np.ndarray | None, prior: Prior | None,
                network: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> HypothesisResult:
        """The pose search alone (its own starts, always all of them), then with a network
        its poses ``(T_ct_us after its ICP, coarse T_ct_us, completion (M, 3) US frame)`` as
        further starts that win only by a clearly better score
        (:mod:`~comreg_core.registration.network_starts`)."""
        start_name = "pca" if getattr(prior, "T_init", None) is None else "init"
        result = search_hypotheses(pts, search_start(pts, target, prior), target, None, config,
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

    def _network_pose(self, pts: np.ndarray, seed: int, t: dict[str, float], start: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """The network's forward pass on ``(N, 3)`` US points (mm): ``(T_ct_us after its ICP,
        the coarse T_ct_us, the completion (M, 3) in the US frame, the ICP's RMS residual
        mm)``; stage timings go into ``t`` (``start``: when preprocessing began)."""
        torch.manual_seed(int(seed))
        norm = self.normalization
        model, cfg = self.model, self.model.config
        src = torch.from_numpy(norm.points_to_model(pts)).float()[None].to(self.device)  # 1 N 3
        self._sync()
        t["preprocess"] = time.perf_counter() - start
        encoding = self.encoding
        with torch.inference_mode(), self.deterministic_forward():
            mark = time.perf_counter()
            completion, pose = model.coarse_pose(src, encoding)
            coarse = pose.transform
            self._sync()
            t["completion_and_coarse_pose"] = time.perf_counter() - mark
            _check_finite_output(completion.dense, coarse)  # before the ICP searches with them
            mark = time.perf_counter()
            icp = model.refine(subsample(src, cfg.icp.num_points, 0), encoding, coarse)
            self._sync()
        _check_finite_output(icp.transform)
        T_coarse = norm.transform_to_mm(orthonormalize(coarse[0].double().cpu().numpy()))
        T = norm.transform_to_mm(orthonormalize(icp.transform[0].double().cpu().numpy()))
        rmse = float(icp.rmse[0]) * norm.scale
        if cfg.icp.mesh_refine and self.surface is not None:  # then on the CT mesh
            T, rmse = refine_on_mesh(pts, T, self.surface.matcher())
        t["icp"] = time.perf_counter() - mark
        mark = time.perf_counter()
        dense = norm.points_to_mm(completion.dense[0].double().cpu().numpy())  # US frame, mm
        t["postprocess"] = time.perf_counter() - mark
        return T, T_coarse, dense, rmse

    @property
    def surface(self):
        """The CT mesh as a :class:`~comreg_core.registration.surface.CTSurface` (built
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


def _check_finite_output(*tensors: torch.Tensor) -> None:
    """Raise :class:`CheckpointError` if the network's output holds NaN or inf."""
    if not all(bool(torch.isfinite(t).all()) for t in tensors):
        raise CheckpointError("The network gave NaN or infinite output for these points.",
                              "Its weights are unusable (a diverged or damaged training): "
                              "train again with 'comreg pretrain'.")
