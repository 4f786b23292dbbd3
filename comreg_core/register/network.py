"""The pretrained network as one more provider of starts for the pose search (torch lives here).

:func:`load_network` reads a run folder of ``comreg pretrain`` (weights only, its CT checked);
:class:`Network` runs the forward pass on a US cloud: completion ``f`` -> coarse pose ``g`` ->
differentiable ICP against the CT half encoded once, and maps the poses back to millimetres.
Only :meth:`Registrar.from_run <comreg_core.register.registrar.Registrar.from_run>` imports
this module: the search alone never imports torch.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from comreg_core import runs
from comreg_core.model.comreg import ComRegNet
from comreg_core.model.ops import subsample
from comreg_core.normalization import Normalization
from comreg_core.registration.geometry.icp import refine_on_mesh
from comreg_core.training.checkpoint import (CheckpointError, check_fingerprint, check_same_bone,
                                             ct_fingerprint, load_checkpoint, network_warning)
from comreg_core.training.config import PretrainConfig, config_from_yaml
from comreg_core.training.trainer import resolve_device
from comreg_core.transforms import orthonormalize

log = logging.getLogger(__name__)


@dataclass
class NetworkPose:
    """The network's answer for one US cloud (all mm, US -> CT): ``T_ct_us`` after its ICP,
    ``T_coarse`` before it, ``completion`` ``(M, 3)`` the completed bone in the US frame,
    ``icp_rmse_mm`` the ICP's RMS residual."""

    T_ct_us: np.ndarray
    T_coarse: np.ndarray
    completion: np.ndarray
    icp_rmse_mm: float


class Network:
    """A pretrained :class:`~comreg_core.model.comreg.ComRegNet` on ``device`` for one CT
    (``ct_points`` ``(M, 3)`` mm, ``normalization``); ``config`` is the run's training config."""

    def __init__(self, model: ComRegNet, ct_points: np.ndarray, normalization: Normalization,
                 device="cpu", config: PretrainConfig | None = None):
        self.device = resolve_device(device)
        self.model = model.to(self.device).eval()
        self.ct_points = ct_points
        self.normalization = normalization
        self.config = config
        self._encoding = None

    @property
    def min_points(self) -> int:
        """Fewest US points the completion takes."""
        return int(self.model.completion.min_points)

    @contextlib.contextmanager
    def deterministic_forward(self):
        """On the CPU, run the network on one thread: torch splits its sums across threads, so
        the output would change in the last float32 digits with the thread count. One thread
        makes it bit-identical at any thread count and load."""
        if self.device.type != "cpu":
            yield
            return
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            yield
        finally:
            torch.set_num_threads(threads)

    def sync(self) -> None:
        """Wait for the GPU (stage timings on CUDA)."""
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

    def pose(self, pts: np.ndarray, seed: int, surface, timings: dict[str, float],
             start: float) -> NetworkPose:
        """The forward pass on ``(N, 3)`` US points (mm); with ``mesh_refine`` the ICP's pose
        is refined on the CT ``surface`` (a CTSurface or None). Stage times go into
        ``timings`` (``start``: when preprocessing began, ``time.perf_counter()``)."""
        torch.manual_seed(int(seed))
        norm, cfg = self.normalization, self.model.config
        src = torch.from_numpy(norm.points_to_model(pts)).float()[None].to(self.device)  # 1 N 3
        self.sync()
        timings["preprocess"] = time.perf_counter() - start
        encoding = self.encoding
        with torch.inference_mode(), self.deterministic_forward():
            mark = time.perf_counter()
            completion, coarse_pose = self.model.coarse_pose(src, encoding)
            coarse = coarse_pose.transform
            self.sync()
            timings["completion_and_coarse_pose"] = time.perf_counter() - mark
            _check_finite_output(completion.dense, coarse)  # before the ICP searches with them
            mark = time.perf_counter()
            icp = self.model.refine(subsample(src, cfg.icp.num_points, 0), encoding, coarse)
            self.sync()
        _check_finite_output(icp.transform)
        T_coarse = norm.transform_to_mm(orthonormalize(coarse[0].double().cpu().numpy()))
        T = norm.transform_to_mm(orthonormalize(icp.transform[0].double().cpu().numpy()))
        rmse = float(icp.rmse[0]) * norm.scale
        if cfg.icp.mesh_refine and surface is not None:  # then on the CT mesh
            T, rmse = refine_on_mesh(pts, T, surface.matcher())
        timings["icp"] = time.perf_counter() - mark
        mark = time.perf_counter()
        dense = norm.points_to_mm(completion.dense[0].double().cpu().numpy())  # US frame, mm
        timings["postprocess"] = time.perf_counter() - mark
        return NetworkPose(T, T_coarse, dense, rmse)


def load_network(run_dir: str | Path, device: str = "auto", *, ct_mesh=None,
                 icp_points: int | None = None) -> dict:
    """Read ``run_dir/checkpoint.pt`` (weights only) into the arguments of
    :class:`~comreg_core.register.registrar.Registrar`: ``network``, ``ct_points``,
    ``normalization``, ``ct_vertices``, ``ct_faces``, ``fingerprint``, ``space``,
    ``warnings``. ``ct_mesh`` (path or SurfaceMesh) is checked against the run's CT;
    ``icp_points``: ICP points per cloud at inference (default: the trained value).

    Raises:
        CheckpointError: no/corrupt checkpoint; one trained for another CT; weights that do
            not fit the stored network config.
    """
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
    norm = Normalization(center=state["norm_center"].numpy(), scale=float(state["norm_scale"]))
    ct_points = state["ct_points"].numpy()
    network = Network(_model(state, cfg, run_dir, icp_points), ct_points, norm, device, cfg)
    return {"network": network, "ct_points": ct_points, "normalization": norm,
            "ct_vertices": state["ct_vertices"].numpy(), "ct_faces": state["ct_faces"].numpy(),
            "fingerprint": expected, "space": str(state.get("ct_space", "LPS")),
            "warnings": [w] if (w := network_warning(state)) else []}


def _model(state: dict, cfg: PretrainConfig, run_dir, icp_points: int | None) -> ComRegNet:
    """The network the stored config describes, with the stored weights."""
    model_cfg = cfg.model
    if icp_points is not None:
        model_cfg = replace(model_cfg, icp=replace(model_cfg.icp, num_points=int(icp_points)))
    try:
        model = ComRegNet(model_cfg)
        model.load_state_dict(state["model"])
    except (RuntimeError, ValueError, TypeError, KeyError) as exc:
        raise CheckpointError(
            f"The checkpoint in '{run_dir}' does not fit its own network config "
            f"({type(exc).__name__}: {' '.join(str(exc).split())[:200]}).",
            "Train again (comreg pretrain), or use an intact run folder.") from None
    return model


def _check_finite_output(*tensors: torch.Tensor) -> None:
    """Raise :class:`CheckpointError` if the network's output holds NaN or inf."""
    if not all(bool(torch.isfinite(t).all()) for t in tensors):
        raise CheckpointError("The network gave NaN or infinite output for these points.",
                              "Its weights are unusable (a diverged or damaged training): "
                              "train again with 'comreg pretrain'.")
