"""``comreg register``'s output folder: :func:`register_to_directory` registers US points files
with :class:`~comreg_core.register.registrar.Registrar`, judges the result
(:mod:`comreg_core.register.judge`) and writes the transform, the registered points, the
completion, the settings and ``result.json``; :func:`read_result` reads it back."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from comreg_core import runs
from comreg_core.config import to_dict
from comreg_core.errors import ComRegError
from comreg_core.io import PointCloud, read_points, write_points
from comreg_core.io._files import atomic_output, check_output_folder, require_input_file
from comreg_core.io.json_files import write_json
from comreg_core.io.transform_files import save_transform
from comreg_core.register.inputs import (calibration_path, input_paths, join_clouds,
                                         prior_inputs, prior_lines)
from comreg_core.register.judge import Evidence, judge
from comreg_core.register.registrar import Registrar
from comreg_core.registration.judgement.calibration import Calibration
from comreg_core.registration.search.config import SearchConfig
from comreg_core.registration.geometry.inputs import MAX_US_POINTS
from comreg_core.registration.judgement.prior_reasons import prior_allows
from comreg_core.registration.judgement.verdict import ambiguity_words, competitor_ruled_out
from comreg_core.registration.search.priors import Prior, prior_kind
from comreg_core.registration.search.result import RegistrationResult
from comreg_core.registration.geometry.surface import ct_length_mm
from comreg_core.transforms import apply_transform, check_rigid, invert_rigid

log = logging.getLogger(__name__)


def registration_verdict(result: RegistrationResult, registrar: Registrar,
                         calibration: Calibration | None = None, allowed=None):
    """``(verdict, evidence)`` of ``result`` on the registrar's CT mesh (:func:`judge` with
    :meth:`Evidence.of`): the points judged are the US points the registration used;
    ``allowed``: which poses a prior allows (the competitor is looked for among them)."""
    if registrar.surface is None:
        raise ComRegError("No CT mesh is known for this model, so the registration cannot be "
                          "judged.", "Load the run folder with its CT mesh.")
    points = apply_transform(invert_rigid(result.T_ct_us), result.registered_points)
    length = (calibration.ct_length_mm if calibration is not None else
              ct_length_mm(registrar.search_target(
                  registrar.search_config.target_points)))
    evidence = Evidence.of(result, points, length, calibration, allowed)
    return judge(points, result.T_ct_us, registrar.surface, evidence), evidence


def register_to_directory(run_dir: str | Path | None,
                          us_points_path: str | Path | Sequence[str | Path],
                          out_dir: str | Path, *, device: str = "auto", seed: int = 0,
                          ct_mesh: str | Path | None = None, icp_points: int | None = None,
                          search: SearchConfig | bool | None = None,
                          sweep: str | Path | None = None,
                          sweep_calibration: str | Path | None = None,
                          T_us_ref: np.ndarray | None = None,
                          calibration: str | Path | None = None,
                          prior: Prior | None = None,
                          registrar: Registrar | None = None) -> RegistrationResult:
    """Register the US cloud in ``us_points_path`` with the run in ``run_dir`` (or, with
    ``run_dir`` None, by the pose search alone on the CT mesh ``ct_mesh``); write ``out_dir``.

    ``us_points_path`` may be a list of files: several tracked sweeps in one tracker frame,
    joined (each in the CT's space) and registered as one rigid body; their beam origins are
    used only when every file has them. ``sweep``/``sweep_calibration``/``T_us_ref`` describe
    one sweep's points (the report draws its frames). ``calibration``: the verdict's
    calibration file (default: the run folder's own), checked before any work and against the
    CT. ``prior``: an initial pose and/or landmarks (:func:`~comreg_core.register.inputs.
    load_prior`): the search keeps to it, and its reasons join the verdict's. ``registrar``: one
    already built from this ``run_dir``/``ct_mesh`` with its own settings (the 3D Slicer module
    keeps one per CT), used instead of building it again (``search`` must then be None).

    Files (each written atomically once the result and its verdict are known, ``result.json``
    last; their contents: docs/guide.md, "result.json"): ``transform.tfm`` (``T_ct_us``, ITK,
    LPS), ``registered_us.ply`` (and ``registered_us_<k>.ply`` per input), ``completion_ct.ply``
    (with a network), ``config.yaml`` (a valid ``--config``) and ``result.json`` (strict JSON).
    ``out_dir`` is checked before any work (never a run folder, never an input, writable).
    """
    paths = input_paths(us_points_path)
    _check_request(run_dir, ct_mesh, paths, (sweep, sweep_calibration, T_us_ref))
    out = check_output_folder(out_dir, inputs=[run_dir, *paths, ct_mesh])
    sweep_record = _sweep_record(sweep, sweep_calibration, T_us_ref)
    calibration_file = calibration_path(calibration, run_dir)
    calibration_record = None if calibration_file is None else Calibration.load(calibration_file)
    clouds = [read_points(path) for path in paths]  # the cheap inputs first
    if registrar is None:
        registrar = _registrar(run_dir, ct_mesh, device, icp_points, search)
    elif search is not None or icp_points is not None:
        raise ComRegError("A registrar already built keeps its own search settings.",
                          "Give either the registrar or the settings, not both.")
    notes = []  # the calibration's (logged here; a join's is logged by join_clouds)
    if calibration_record is not None:
        notes.append(calibration_record.check_fits(registrar.fingerprint, prior_kind(prior),
                                                   calibration_file))
        if notes[-1]:
            log.warning("%s", notes[-1])
    clouds = [cloud.in_space(registrar.space) for cloud in clouds]
    points, origins, joined_note = join_clouds(clouds)
    result = registrar.register(points, seed=seed, beam_origins=origins, prior=prior)
    for note in [joined_note, *notes]:
        if note:
            result.info.setdefault("warnings", []).append(note)
    inputs_record = input_records(paths, clouds, result, registrar)
    result.info["us_inputs"] = inputs_record
    files = _output_files(registrar, inputs_record)
    settings = {"search": to_dict(registrar.search_config),
                "inputs": _inputs_setting(run_dir, paths, device, seed, registrar, ct_mesh,
                                          origins is not None, prior)}
    allowed = None
    if prior is not None:  # the competitor is looked for among the poses the prior allows
        allowed = prior_allows(prior.in_space(registrar.space), result)
    verdict, evidence = registration_verdict(result, registrar, calibration_record, allowed)
    result.info["verdict"] = verdict
    payload = {**result.to_json(), **verdict.to_json(), **evidence.to_json(),
               "verdict_calibration": _calibration_summary(calibration_record),
               "space": registrar.space,
               "beam_origins_used": origins is not None,
               "ct_fingerprint": registrar.fingerprint,
               "run_dir": None if run_dir is None else str(Path(run_dir).absolute()),
               "us_points": inputs_record[0]["path"] if len(paths) == 1
               else [record["path"] for record in inputs_record],
               "us_inputs": inputs_record,
               "ct_mesh": None if ct_mesh is None else str(Path(ct_mesh).absolute()),
               "sweep": sweep_record, "prior": result.info.get("prior"), "files": files}
    _write_outputs(out, files, result, registrar, clouds, settings, payload)
    _log_outcome(result, registrar, verdict, out)
    return result


def _check_request(run_dir, ct_mesh, paths: list[Path], one_sweep: tuple) -> None:
    """Refuse what cannot be registered: no CT and no run; a sweep's record (``one_sweep``:
    sweep, its calibration, ``T_us_ref``) with several US points files."""
    if run_dir is None and ct_mesh is None:
        raise ComRegError("Nothing to register to: no CT mesh and no pretrained run.",
                          "Give the CT bone mesh (--ct CT_MESH), and a run (--model RUN_DIR) "
                          "to use the network too.")
    if len(paths) > 1 and any(x is not None for x in one_sweep):
        raise ComRegError(f"--sweep and --probe-calibration describe one sweep's points, but "
                          f"{len(paths)} US points files were given.",
                          "Drop --sweep/--probe-calibration, or register one US points file.")


def _inputs_setting(run_dir, paths: list[Path], device: str, seed: int, registrar: Registrar,
                    ct_mesh, beam_origins: bool, prior: Prior | None) -> dict:
    """``config.yaml``'s ``inputs:`` record."""
    given = [str(path) for path in paths]
    return {"run_dir": None if run_dir is None else str(run_dir),
            "us_points": given[0] if len(given) == 1 else given,
            "device": device, "seed": int(seed),
            "icp_points": None if registrar.model is None
            else registrar.model.config.icp.num_points,
            "ct_mesh": None if ct_mesh is None else str(ct_mesh),
            "beam_origins": beam_origins,
            "prior": None if prior is None else prior_inputs(prior)}


def _calibration_summary(calibration: Calibration | None) -> dict | None:
    """``result.json``'s ``calibration``: what the verdict's calibration was fitted on."""
    if calibration is None:
        return None
    return {"sweeps": calibration.sweeps, "correct_share": calibration.correct_share,
            "ok_probability": calibration.ok_probability, "knots": calibration.knots}


def _log_outcome(result: RegistrationResult, registrar: Registrar, verdict, out: Path) -> None:
    """Log what a user should know: time and place, the run's warnings, a CHECK verdict and
    an ambiguous result."""
    log.info("Registered %d points in %.3f s (%s); result in '%s'", result.n_points,
             result.runtime_s, result.device, out)
    for warning in registrar.warnings:
        log.warning("%s", warning)
    if not verdict.ok:
        log.warning("%s: %s", verdict.headline, " ".join(verdict.reasons))
    if result.ambiguous and not competitor_ruled_out(_competitor(verdict)):
        log.warning("Ambiguous registration: the pose '%s' fits the US points within %.2f mm "
                    "of '%s' (confidence %.2f); check the result visually.",
                    result.search.runner_up, result.search.score_gap_mm,
                    result.search.chosen, result.confidence)


def _registrar(run_dir, ct_mesh, device: str, icp_points, search) -> Registrar:
    """The registrar of ``register_to_directory``: the run's network (``run_dir``) or the pose
    search alone on ``ct_mesh``."""
    if run_dir is not None:
        return Registrar.from_run(run_dir, device, ct_mesh=ct_mesh, icp_points=icp_points,
                                  search=search)
    if search is False or getattr(search, "enabled", True) is False:
        raise ComRegError("Without a pretrained run the pose search is the registration; "
                          "it cannot be turned off.",
                          "Drop --no-search, or give --model RUN_DIR.")
    return Registrar.from_ct(ct_mesh, search=search)


def _output_files(registrar: Registrar, inputs_record: list[dict]) -> dict:
    """``result.json``'s ``files``: the name of each file written (module files of
    :mod:`comreg_core.runs`)."""
    files = {"transform": runs.TRANSFORM, "registered_us": runs.REGISTERED_US,
             "completion_ct": runs.COMPLETION_CT, "config": runs.CONFIG}
    if registrar.model is None:
        del files["completion_ct"]
    if len(inputs_record) > 1:
        files["registered_us_inputs"] = [record["registered_us"] for record in inputs_record]
    return files


def _write_outputs(out: Path, files: dict, result: RegistrationResult, registrar: Registrar,
                   clouds: list[PointCloud], settings: dict, payload: dict) -> None:
    """Write the folder of ``register_to_directory``, once everything in it is known (each
    file atomically, ``result.json`` last)."""
    import yaml

    out.mkdir(parents=True, exist_ok=True)
    save_transform(result.T_ct_us, out / files["transform"], space=registrar.space)
    write_points(PointCloud(result.registered_points, registrar.space),
                 out / files["registered_us"])
    for cloud, name in zip(clouds, files.get("registered_us_inputs", ())):
        write_points(PointCloud(apply_transform(result.T_ct_us, cloud.points),
                                registrar.space), out / name)
    if "completion_ct" in files:
        write_points(PointCloud(result.completion_ct, registrar.space),
                     out / files["completion_ct"])
    with atomic_output(out / files["config"]) as tmp:  # comreg register --config reads it
        tmp.write_text(yaml.safe_dump(settings, sort_keys=False), encoding="utf-8")
    write_json(payload, out / runs.RESULT)


def summary_lines(result: RegistrationResult, out_dir, *, with_network: bool) -> list[str]:
    """What ``comreg register`` prints: the folder, points, time and residual; the chosen
    start, the competing pose and confidence; what to scan when it is ambiguous."""
    how = f"on {result.device}" if with_network else "by the pose search (no network)"
    lines = [f"wrote {out_dir}: {result.n_points} points registered in {result.runtime_s:.2f} s "
             f"{how}; median residual {result.residuals['median']:.2f} mm"]
    h = result.search
    if h is not None:
        gap = "no competing pose" if h.score_gap_mm is None else \
            f"next different pose ('{h.runner_up}') {h.score_gap_mm:.3f} mm worse"
        lines.append(f"pose '{h.chosen}', best of {h.starts_tried} starts"
                     + (" (a short sweep: all orientations tried)" if h.patch
                        and not result.info.get("prior") else "")
                     + f", {gap}; confidence {h.confidence:.2f}"
                     + _ambiguity_note(h.ambiguous, result.info.get("verdict")))
        if h.advice and result.info.get("verdict") is None:
            lines.append(h.advice["advice"])
    lines += prior_lines(result.info.get("prior"))
    lines += verdict_lines(result.info.get("verdict"))
    records = result.info.get("us_inputs") or []
    for k, record in enumerate(records if len(records) > 1 else [], start=1):
        lines.append(f"  input {k}: {Path(record['path']).name}: {record['n_points']} points, "
                     f"median residual {record['residuals_mm']['median']:.2f} mm")
    return lines


def _competitor(verdict) -> dict | None:
    """The verdict's uncertainty's competitor record (None: none, or not judged)."""
    return None if verdict is None or verdict.uncertainty is None else \
        verdict.uncertainty.get("competitor")


def _ambiguity_note(ambiguous: bool, verdict) -> str:
    """The terminal's word on an ambiguous search: a warning, unless the verdict's uncertainty
    rules the close pose out."""
    if not ambiguous:
        return ""
    competitor = _competitor(verdict)
    if not competitor_ruled_out(competitor):
        return "; AMBIGUOUS: check the result visually"
    return f"; a different pose scored {ambiguity_words(True, competitor)}"


def verdict_lines(verdict) -> list[str]:
    """The verdict in the terminal: ``Verdict: OK, p_correct 0.99; within 1.2 mm (95 %);
    weakest: ...``, its reasons and, when CHECK, where to scan next."""
    if verdict is None:
        return []
    p = verdict.figures.get("p_correct")
    line = verdict.headline + ("" if p is None else f", p_correct {p:.2f}")
    if verdict.uncertainty is not None:
        line += f"; {verdict.uncertainty['summary']}"
    lines = [line] + [f"  {reason}" for reason in verdict.reasons]
    if not verdict.ok and verdict.scan_next is not None:
        lines.append(f"  {verdict.scan_next['words']}")
    return lines


def input_records(paths: list[Path], clouds: list[PointCloud], result: RegistrationResult,
                   registrar: Registrar) -> list[dict]:
    """``result.json``'s ``us_inputs``: per input file its absolute path, point count, whether
    it has beam origins, the distance statistics of its points after registration (a single
    input: the registration's own ``residuals_mm``; several: each file's points, at most
    :data:`~comreg_core.registration.geometry.inputs.MAX_US_POINTS` of them, evenly strided) and the
    file of its registered points."""
    records = []
    for k, (path, cloud) in enumerate(zip(paths, clouds), start=1):
        if len(clouds) == 1:
            residuals, name = dict(result.residuals), runs.REGISTERED_US
        else:
            step = -(-len(cloud.points) // MAX_US_POINTS)
            residuals = registrar.residuals(apply_transform(result.T_ct_us,
                                                            cloud.points[::step]))
            name = runs.REGISTERED_US_INPUT.format(k)
        records.append({"path": str(Path(path).absolute()), "n_points": len(cloud.points),
                        "beam_origins": cloud.beam_origins is not None,
                        "residuals_mm": residuals, "registered_us": name})
    return records


def _sweep_record(sweep, calibration, T_us_ref) -> dict | None:
    """``result.json``'s ``sweep`` entry (absolute paths), checked before any work: the sweep
    (a file or frame folder) reads with its calibration (what the report will read: 1.3 s for
    the fibula's 111 frames) and ``T_us_ref`` is rigid."""
    from comreg_core.errors import InputFileNotFoundError
    from comreg_core.io.tracked_us import read_tracked_sweep

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
    read_tracked_sweep(sweep, calibration=calibration)  # a sweep the report cannot read: refused
    return {"path": str(Path(sweep).absolute()),
            "calibration": None if calibration is None else str(Path(calibration).absolute()),
            "T_us_ref": T.tolist()}


# ------------------------------------------------------------------------------------- priors


#: ``result.json``'s keys under an earlier name, still read: ``{old: new}`` (in the result
#: and in its ``timings_s``).
RENAMED_RESULT_KEYS = {"hypotheses": "search"}


def upgraded_result(result: dict[str, Any]) -> dict[str, Any]:
    """The content of a ``result.json`` with its keys under an earlier name
    (:data:`RENAMED_RESULT_KEYS`) under today's, in their place (a copy)."""
    def renamed(record: dict[str, Any]) -> dict[str, Any]:
        names = {old: new for old, new in RENAMED_RESULT_KEYS.items() if new not in record}
        return {names.get(key, key): value for key, value in record.items()}

    out = renamed(result)
    if isinstance(out.get("timings_s"), dict):
        out["timings_s"] = renamed(out["timings_s"])
    return out


def read_result(out_dir: str | Path) -> dict[str, Any]:
    """``out_dir/result.json`` checked to hold ``T_ct_us``, ``us_points`` and a ``run_dir`` or
    a ``ct_mesh`` (a registration without a network has no run), its keys as today's
    (:func:`upgraded_result`). Relative paths in it (results written before they were stored
    absolute) are taken as relative to the current directory, as they were written."""
    path = require_input_file(Path(out_dir) / runs.RESULT, "registration result")
    try:
        result = json.loads(path.read_text(encoding="utf-8"))
        np.asarray(result["T_ct_us"], dtype=np.float64).reshape(4, 4)
        str(result["us_points"])
        if result.get("run_dir") is None and result.get("ct_mesh") is None:
            raise KeyError("run_dir or ct_mesh")
    except (ValueError, KeyError, TypeError) as exc:
        raise ComRegError(f"'{path}' is not a ComReg registration result ({exc}).",
                          "Run 'comreg register' into this folder first.") from None
    return upgraded_result(result)
