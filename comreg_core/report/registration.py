"""``comreg report OUT_DIR``: the report of a folder written by ``comreg register``, with the
verdict recomputed from the folder's files and the metrics in words with units."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from comreg_core.progress import Progress
from comreg_core import runs
from comreg_core.errors import ComRegError
from comreg_core.io._files import check_output_folder, require_input_file
from comreg_core.report.report import write_report


def read_registration_result(out_dir: Path) -> dict[str, Any]:
    """``out_dir/result.json`` checked to hold ``T_ct_us``, ``us_points`` and a ``run_dir`` or
    a ``ct_mesh`` (a registration without a network has no run). Relative paths in it (results
    written before they were stored absolute) are taken as relative to the current directory,
    as they were written."""
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
    return result


def write_report_for_registration(out_dir: str | Path, *, ct_mesh: str | Path | None = None,
                                  transform: str | Path | None = None,
                                  embed_images: bool = False,
                                  progress: Progress | None = None,
                                  sweep: str | Path | None = None,
                                  sweep_calibration: str | Path | None = None) -> Path:
    """``comreg report OUT_DIR``: the report of a folder written by ``comreg register``.

    Reads ``result.json`` (``T_ct_us``, timings, residuals, the run folder and US file it names),
    the US points as given, ``completion_ct.ply`` and ``metrics.json`` when it was made for this
    registration (it holds ``registration.T_ct_us`` equal to the judged transform, as the demo
    writes it; an evaluation of other starts left in the folder is not shown). The CT mesh is
    ``ct_mesh``, else the one ``result.json`` names, else the run's own. The verdict
    (:mod:`comreg_core.registration.verdict`) is computed again from these files. ``transform``
    (an ITK transform file of ``T_ct_us``) judges and shows that transform instead of the
    folder's (its completion is then left out). The tracked sweep the points came from is
    ``sweep`` (with ``sweep_calibration``), else the one ``result.json`` names: the page then
    shows some of its frames with the registered CT contour. Returns the path of
    ``report.html``.
    """
    from comreg_core.io import read_mesh, read_points
    from comreg_core.registration.verdict import judge_registration
    from comreg_core.transforms import apply_transform

    out_dir = Path(out_dir)
    require_input_file(out_dir / runs.RESULT, "registration result")
    check_output_folder(out_dir, what="report folder")  # before reading and rendering
    result = read_registration_result(out_dir)
    run_dir, us_path = result.get("run_dir"), Path(result["us_points"])
    ct_path = ct_mesh or result.get("ct_mesh")
    if ct_path is None:
        from comreg_core.training import run_ct_mesh

        ct = run_ct_mesh(run_dir)
    else:
        ct = read_mesh(ct_path)
    us_points = read_points(us_path).in_space(ct.space).points
    T_ct_us = np.asarray(result["T_ct_us"], dtype=np.float64)
    completion_path = out_dir / runs.COMPLETION_CT
    completion = read_points(completion_path).in_space(ct.space).points \
        if completion_path.is_file() else None
    if transform is not None:
        from comreg_core.io.transform_files import load_transform

        T_ct_us, completion = load_transform(transform, space=ct.space), None
    tracked, T_us_ref = _sweep_for(result, sweep, sweep_calibration)
    hypotheses = result.get("hypotheses") or {}
    verdict = judge_registration(us_points, T_ct_us, (ct.vertices, ct.faces),
                                 confidence=hypotheses.get("confidence"),
                                 ambiguous=hypotheses.get("ambiguous"))
    metrics = registration_metrics_table(result, verdict.figures, judged_file=transform)
    evaluation = _metrics_for(out_dir / runs.METRICS, T_ct_us)
    if evaluation is not None:
        metrics.update(evaluation)
    return write_report(
        out_dir, ct_mesh=ct, us_before=us_points, us_after=apply_transform(T_ct_us, us_points),
        completion=completion, metrics=metrics, verdict=verdict,
        inputs={"run folder": str(run_dir or "none (the pose search alone)"),
                "US points": str(us_path),
                "CT mesh": str(ct_path or f"stored in {run_dir}"),
                "transform": str(transform or "result.json (the registration's)")},
        seed=result.get("seed"), device=result.get("device"), embed_images=embed_images,
        progress=progress, sweep=tracked,
        T_ct_ref=None if tracked is None else T_ct_us @ T_us_ref)


def _sweep_for(result: dict[str, Any], sweep, calibration):
    """``(TrackedSweep or None, T_us_ref (4, 4))``: the sweep given, else the one recorded in
    ``result.json`` (with its map into the US points' frame), read in full."""
    from comreg_core.io.tracked_us import read_tracked_sweep

    recorded = result.get("sweep") or {}
    T_us_ref = np.eye(4)
    if sweep is None and recorded.get("path"):
        sweep, calibration = recorded["path"], recorded.get("calibration")
        T_us_ref = np.asarray(recorded.get("T_us_ref", T_us_ref), dtype=np.float64).reshape(4, 4)
    if sweep is None:
        return None, T_us_ref
    return read_tracked_sweep(sweep, calibration=calibration), T_us_ref


def _metrics_for(path: Path, T_ct_us: np.ndarray) -> dict[str, Any] | None:
    """The rows of ``metrics.json`` if it was made for the registration ``T_ct_us`` (its
    ``registration.T_ct_us`` equal to 1e-6 mm), else None (an evaluation of other starts, or
    of an earlier registration, is not this one's)."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        made_for = np.asarray(data["registration"]["T_ct_us"], dtype=np.float64)
    except (ValueError, KeyError, TypeError):
        return None
    if made_for.shape != (4, 4) or not np.allclose(made_for, T_ct_us, rtol=0, atol=1e-6):
        return None
    rows: dict[str, Any] = {}
    truth = data["registration"].get("errors_vs_truth")
    if truth:
        rows["Error against the known truth"] = {
            "translation at the US centroid (RTE)_mm": truth.get("RTE_mm"),
            "rotation (RRE)_deg": truth.get("RRE_deg"),
            "success (RTE < 2 mm and RRE < 2 deg)": truth.get("success")}
    summary = (data.get("summary") or {}).get("comreg")
    if summary:
        rows["Further random starts (evaluation)"] = {
            "starts": summary.get("trials", summary.get("n")),
            "success rate_percent": _percent(summary.get("success_rate")),
            "flip rate_percent": _percent(summary.get("flip_rate")),
            "median RTE_mm": (summary.get("RTE_mm") or {}).get("median"),
            "median RRE_deg": (summary.get("RRE_deg") or {}).get("median")}
    return rows


def _percent(rate) -> float | None:
    return None if rate is None else 100.0 * float(rate)


def registration_metrics_table(result: dict[str, Any], figures: dict[str, Any], *,
                               judged_file=None) -> dict[str, Any]:
    """The report's metrics as rows in words; a key's ``_mm``/``_deg``/``_s``/``_percent``
    suffix is its unit column (:func:`comreg_core.report.html.unit_of`)."""
    rows: dict[str, Any] = {
        "Fit of the US points to the CT bone": {
            "median distance to the CT surface_mm": figures["median_mm"],
            "90 % of the points within_mm": figures["p90_mm"],
            "points within 2 mm of the surface_percent": 100 * figures["within_2mm"],
            "CT surface touched by the sweep (within 2 mm)_percent": 100 * figures["coverage"],
            "a rigid refit moves the points by (RMS)_mm": figures["refit_shift_mm"],
            "best-fitting scale of the US points": figures["refit_scale"]}}
    if judged_file is not None:
        rows["Fit of the US points to the CT bone"]["transform judged"] = str(judged_file)
    hypotheses = result.get("hypotheses")
    if hypotheses:  # the pose check of the hypotheses stage (comreg_core.registration.search)
        pose = {"another pose fits nearly as well (ambiguous)":
                "YES: check the images" if hypotheses.get("ambiguous") else "no",
                "confidence (0-1; below 0.3 is ambiguous)": hypotheses.get("confidence"),
                "pose kept": _hypothesis_words(hypotheses.get("chosen")),
                "next best pose": _hypothesis_words(hypotheses.get("runner_up")),
                "trimmed mean distance of the kept pose_mm": hypotheses.get("score_mm"),
                "next best pose is worse by_mm": hypotheses.get("score_gap_mm")}
        if hypotheses.get("advice"):  # an ambiguous result: what would tell the poses apart
            pose["what would resolve it"] = hypotheses["advice"]["advice"]
        polish = hypotheses.get("polish")
        if polish:
            pose["final polish"] = (
                f"moved {polish['moved_mm']:.2f} mm in {polish['iterations']} iterations, "
                f"{100 * polish['inlier_fraction']:.0f} % of the points matched, "
                f"RMS {polish['rmse_mm']:.2f} mm")
        rows["Pose check"] = pose
    timings = result.get("timings_s") or {}
    rows["Time"] = {"registration in all_s": result.get("runtime_s"),
                    **{f"{_STAGE_WORDS.get(k, k.replace('_', ' '))}_s": v
                       for k, v in timings.items() if k != "total"}}
    if result.get("warnings"):
        rows["Warnings"] = " ".join(result["warnings"])
    return rows


_STAGE_WORDS = {"preprocess": "checks and normalisation",
                "completion_and_coarse_pose": "completion and coarse pose (network)",
                "icp": "network ICP", "hypotheses": "pose check",
                "postprocess": "back to millimetres", "residuals": "distances to the CT"}


def _hypothesis_words(name: str | None) -> str | None:
    """A hypothesis name such as ``coarse+rot45+slide96`` in words."""
    if not name:
        return name
    words = []
    for part in str(name).split("+"):
        if part.startswith("rot") and _number(part[3:]) is not None:
            words.append(f"turned {_number(part[3:]):g} deg about the bone axis")
        elif part.startswith("slide") and _number(part[5:]) is not None:
            words.append(f"slid {_number(part[5:]):g} mm along it")
        elif part == "flip":
            words.append("flipped end to end")
        else:
            words.append({"network": "the network's pose", "coarse": "the network's coarse pose",
                          "pca": "the principal-axes solve"}.get(part, part))
    return f"{name} ({', '.join(words)})"


def _number(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None
