"""``comreg register``'s output folder: :func:`register_to_directory` registers a US points
file with :class:`~comreg_core.inference.Registrar` and writes the transform, the registered
points, the completion, the settings and ``result.json`` (with the verdict)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from comreg_core import runs
from comreg_core.config import to_dict
from comreg_core.errors import ComRegError, InvalidGeometryError
from comreg_core.inference import Registrar
from comreg_core.io import PointCloud, read_points, write_points
from comreg_core.io._files import atomic_output, check_output_folder
from comreg_core.io.transform_files import save_transform
from comreg_core.registration.config import HypothesisConfig
from comreg_core.registration.verdict import judge_registration
from comreg_core.registration.result import RegistrationResult
from comreg_core.transforms import apply_transform, check_rigid, invert_rigid

log = logging.getLogger(__name__)


def registration_verdict(result: RegistrationResult, registrar: Registrar):
    """The :class:`~comreg_core.registration.verdict.Verdict` of ``result`` on the registrar's CT
    mesh (:attr:`Registrar.surface`); the points judged are the US points the registration
    used (``registered_points`` moved back by ``T_ct_us``)."""
    if registrar.surface is None:
        raise InvalidGeometryError("No CT mesh is known for this model, so the registration "
                                   "cannot be judged.", "Load the run folder with its CT mesh.")
    points = apply_transform(invert_rigid(result.T_ct_us), result.registered_points)
    return judge_registration(points, result.T_ct_us, registrar.surface,
                              confidence=result.confidence, ambiguous=result.ambiguous)


def register_to_directory(run_dir: str | Path | None, us_points_path: str | Path,
                          out_dir: str | Path, *, device: str = "auto", seed: int = 0,
                          ct_mesh: str | Path | None = None, icp_points: int | None = None,
                          hypotheses: HypothesisConfig | bool | None = None,
                          sweep: str | Path | None = None,
                          sweep_calibration: str | Path | None = None,
                          T_us_ref: np.ndarray | None = None) -> RegistrationResult:
    """Register the US cloud in ``us_points_path`` with the run in ``run_dir`` (or, with
    ``run_dir`` None, by the pose search alone on the CT mesh ``ct_mesh``); write ``out_dir``.

    Files (each written atomically; ``result.json`` last):

    - ``transform.tfm``: ``T_ct_us`` as an ITK transform (LPS, ITK's resampling direction, as
      3D Slicer writes it: :func:`comreg_core.io.save_transform`).
    - ``registered_us.ply``: the US points mapped into the CT frame (CT space tag).
    - ``completion_ct.ply``: the completed bone in the CT frame (not without a network).
    - ``config.yaml``: inputs and settings (run folder, US file, device, seed, ICP points, the
      hypotheses settings).
    - ``result.json``: ``T_ct_us``, ``T_ct_us_coarse`` (4x4 mm), ``timings_s`` (per stage),
      ``runtime_s``, ``device``, ``seed``, ``n_points``, ``residuals_mm``, ``icp_rmse_mm``,
      ``confidence``, ``ambiguous`` and ``hypotheses`` (:meth:`RegistrationResult.to_json`;
      null with ``hypotheses=False``), ``verdict`` ("ok"/"check"), ``verdict_reasons`` and
      ``verdict_figures`` (:mod:`comreg_core.registration.verdict`), ``space``,
      ``ct_fingerprint``, ``run_dir``, ``us_points`` and ``ct_mesh`` (absolute paths, so
      ``comreg report`` works from any directory), ``files``, and ``sweep`` (null, or the
      tracked sweep the points came from: ``path``, ``calibration`` and ``T_us_ref``, the
      ``(4, 4)`` map from its reference frame to the US points' frame, identity for points
      straight from ``comreg extract-us``), from which the report draws B-mode frames with the
      registered CT contour.

    The US cloud is converted into the CT's patient space first (PLY/PCD ``SPACE=`` tag).
    ``out_dir`` is checked before any work (:func:`~comreg_core.io._files.check_output_folder`:
    never a run folder or inside one, never an input, writable).
    """
    import yaml

    if run_dir is None and ct_mesh is None:
        raise ComRegError("Nothing to register to: no CT mesh and no pretrained run.",
                          "Give the CT bone mesh (--ct CT_MESH), and a run (--model RUN_DIR) "
                          "to use the network too.")
    out = check_output_folder(out_dir, inputs=[run_dir, us_points_path, ct_mesh])
    sweep_record = _sweep_record(sweep, sweep_calibration, T_us_ref)
    cloud = read_points(us_points_path)  # the cheap input first
    if run_dir is None:
        if hypotheses is False or getattr(hypotheses, "enabled", True) is False:
            raise ComRegError("Without a pretrained run the pose search is the registration; "
                              "it cannot be turned off.",
                              "Drop --no-hypotheses, or give --model RUN_DIR.")
        registrar = Registrar.from_ct(ct_mesh, hypotheses=hypotheses)
    else:
        registrar = Registrar.from_run(run_dir, device, ct_mesh=ct_mesh, icp_points=icp_points,
                                       hypotheses=hypotheses)
    cloud = cloud.in_space(registrar.space)
    result = registrar.register(cloud.points, seed=seed, beam_origins=cloud.beam_origins)
    out.mkdir(parents=True, exist_ok=True)
    files = {"transform": runs.TRANSFORM, "registered_us": runs.REGISTERED_US,
             "completion_ct": runs.COMPLETION_CT, "config": runs.CONFIG}
    if registrar.model is None:
        del files["completion_ct"]
    save_transform(result.T_ct_us, out / files["transform"], space=registrar.space)
    write_points(PointCloud(result.registered_points, registrar.space),
                 out / files["registered_us"])
    if "completion_ct" in files:
        write_points(PointCloud(result.completion_ct, registrar.space),
                     out / files["completion_ct"])
    inputs = {"run_dir": None if run_dir is None else str(run_dir),
              "us_points": str(us_points_path), "device": device, "seed": int(seed),
              "icp_points": None if registrar.model is None
              else registrar.model.config.icp.num_points,
              "ct_mesh": None if ct_mesh is None else str(ct_mesh),
              "beam_origins": cloud.beam_origins is not None}
    settings = {"hypotheses": to_dict(registrar.hypothesis_config), "inputs": inputs}
    with atomic_output(out / files["config"]) as tmp:  # comreg register --config reads it
        tmp.write_text(yaml.safe_dump(settings, sort_keys=False), encoding="utf-8")
    verdict = registration_verdict(result, registrar)
    payload = {**result.to_json(), **verdict.to_json(), "space": registrar.space,
               "beam_origins_used": cloud.beam_origins is not None,
               "ct_fingerprint": registrar.fingerprint,
               "run_dir": None if run_dir is None else str(Path(run_dir).absolute()),
               "us_points": str(Path(us_points_path).absolute()),
               "ct_mesh": None if ct_mesh is None else str(Path(ct_mesh).absolute()),
               "sweep": sweep_record, "files": files}
    with atomic_output(out / runs.RESULT) as tmp:
        tmp.write_text(json.dumps(payload, indent=2) + "\n", encoding="utf-8")
    log.info("Registered %d points in %.3f s (%s); result in '%s'", result.n_points,
             result.runtime_s, result.device, out)
    for warning in registrar.warnings:
        log.warning("%s", warning)
    if not verdict.ok:
        log.warning("%s: %s", verdict.headline, " ".join(verdict.reasons))
    if result.ambiguous:
        log.warning("Ambiguous registration: hypothesis '%s' fits the US points within %.2f mm "
                    "of '%s' (confidence %.2f); check the result visually.",
                    result.hypotheses.runner_up, result.hypotheses.score_gap_mm,
                    result.hypotheses.chosen, result.confidence)
    return result


def summary_lines(result: RegistrationResult, out_dir, *, with_network: bool) -> list[str]:
    """What ``comreg register`` prints: the folder, points, time and residual; the chosen
    hypothesis, the competing pose and confidence; what to scan when it is ambiguous."""
    how = f"on {result.device}" if with_network else "by the pose search (no network)"
    lines = [f"wrote {out_dir}: {result.n_points} points registered in {result.runtime_s:.2f} s "
             f"{how}; median residual {result.residuals['median']:.2f} mm"]
    h = result.hypotheses
    if h is not None:
        gap = "no competing pose" if h.score_gap_mm is None else \
            f"next different pose ('{h.runner_up}') {h.score_gap_mm:.3f} mm worse"
        lines.append(f"hypothesis '{h.chosen}' of {h.starts_tried} starts"
                     + (" (a short sweep: all orientations tried)" if h.patch else "")
                     + f", {gap}; confidence {h.confidence:.2f}"
                     + ("; AMBIGUOUS: check the result visually" if h.ambiguous else ""))
        if h.advice:
            lines.append(h.advice["advice"])
    return lines


def _sweep_record(sweep, calibration, T_us_ref) -> dict | None:
    """``result.json``'s ``sweep`` entry (absolute paths), checked before any work: the sweep
    (a file or frame folder) and its calibration exist and ``T_us_ref`` is rigid."""
    from comreg_core.errors import InputFileNotFoundError

    if sweep is None:
        if calibration is not None:
            raise ComRegError("A sweep calibration was given without the sweep.",
                              "Give --sweep too, or drop --calibration.")
        return None
    if not Path(sweep).exists():
        raise InputFileNotFoundError(Path(sweep), "tracked sweep")
    if calibration is not None and not Path(calibration).is_file():
        raise InputFileNotFoundError(Path(calibration), "sweep calibration")
    T = np.eye(4) if T_us_ref is None else check_rigid(np.asarray(T_us_ref, float))
    return {"path": str(Path(sweep).absolute()),
            "calibration": None if calibration is None else str(Path(calibration).absolute()),
            "T_us_ref": T.tolist()}
