"""``comreg report OUT_DIR``: the report of a folder written by ``comreg register``, with the
verdict recomputed from the folder's files and the metrics in words with units."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from comreg_core.progress import Progress
from comreg_core.register.folder import read_result
from comreg_core.register.judge import Evidence, judge
from comreg_core.registration.judgement.verdict import ambiguity_words
from comreg_core import runs
from comreg_core.io._files import check_output_folder, require_input_file
from comreg_core.report.html import Quantity
from comreg_core.report.report import write_report


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
    (:mod:`comreg_core.registration.judgement.verdict`) is computed again from these files. ``transform``
    (an ITK transform file of ``T_ct_us``) judges and shows that transform instead of the
    folder's (its completion is then left out). The tracked sweep the points came from is
    ``sweep`` (with ``sweep_calibration``), else the one ``result.json`` names: the page then
    shows some of its frames with the registered CT contour. Returns the path of
    ``report.html``.
    """
    from comreg_core.io import read_mesh, read_points
    from comreg_core.transforms import apply_transform

    out_dir = Path(out_dir)
    require_input_file(out_dir / runs.RESULT, "registration result")
    check_output_folder(out_dir, what="report folder")  # before reading and rendering
    result = read_result(out_dir)
    run_dir, us_paths = result.get("run_dir"), result["us_points"]
    us_paths = [Path(path) for path in (us_paths if isinstance(us_paths, list) else [us_paths])]
    ct_path = ct_mesh or result.get("ct_mesh")
    if ct_path is None:
        from comreg_core.training import run_ct_mesh

        ct = run_ct_mesh(run_dir)
    else:
        ct = read_mesh(ct_path)
    parts = [read_points(path).in_space(ct.space).points for path in us_paths]
    us_points = np.concatenate(parts)  # several sweeps in one tracker frame: joined
    T_ct_us = np.asarray(result["T_ct_us"], dtype=np.float64)
    completion_path = out_dir / runs.COMPLETION_CT
    completion = read_points(completion_path).in_space(ct.space).points \
        if completion_path.is_file() else None
    if transform is not None:
        from comreg_core.io.transform_files import load_transform

        T_ct_us, completion = load_transform(transform, space=ct.space), None
    tracked, T_us_ref = _sweep_for(result, sweep, sweep_calibration)
    evidence = Evidence.from_json(result)
    if transform is not None:  # another transform: judged by its fit alone
        evidence = replace(evidence, competitor=None, prior=None)
    verdict = judge(us_points, T_ct_us, (ct.vertices, ct.faces), evidence)
    metrics = registration_metrics_table(result, verdict.figures, judged_file=transform)
    metrics.update(uncertainty_rows(verdict))
    evaluation = _metrics_for(out_dir / runs.METRICS, T_ct_us)
    if evaluation is not None:
        metrics.update(evaluation)
    if len(parts) > 1:
        metrics["US inputs (sweeps registered together)"] = _input_rows(us_paths, parts,
                                                                        T_ct_us, ct)
    return write_report(
        out_dir, ct_mesh=ct, us_before=us_points, us_after=apply_transform(T_ct_us, us_points),
        completion=completion, metrics=metrics, verdict=verdict,
        inputs={"run folder": str(run_dir or "none (the pose search alone)"),
                "US points": "; ".join(str(path) for path in us_paths),
                "CT mesh": str(ct_path or f"stored in {run_dir}"),
                "transform": str(transform or "result.json (the registration's)")},
        seed=result.get("seed"), device=result.get("device"), embed_images=embed_images,
        progress=progress, sweep=tracked,
        T_ct_ref=None if tracked is None else T_ct_us @ T_us_ref,
        scan_next=None if verdict.ok or verdict.scan_next is None
        else np.asarray(verdict.scan_next["point_ct"]))


def _input_rows(paths: list[Path], parts: list[np.ndarray], T_ct_us: np.ndarray, ct
                ) -> dict[str, str]:
    """Several US inputs: each one's point count and median distance to the CT under
    ``T_ct_us``, in words."""
    from comreg_core.registration.geometry.surface import CTSurface
    from comreg_core.transforms import apply_transform

    surface = CTSurface((ct.vertices, ct.faces))
    return {f"Input {k}: {path.name}": f"{len(points)} points, median distance to the CT "
            f"{float(np.median(surface.distance(apply_transform(T_ct_us, points)))):.2f} mm"
            for k, (path, points) in enumerate(zip(paths, parts), start=1)}


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
    record = data["registration"]
    errors = record.get("errors_vs_truth")
    if errors:
        group: dict[str, Any] = {}
        if record.get("truth"):
            group["Truth"] = record["truth"]
        group.update({
            "Translation error at the US centroid (RTE)": Quantity(errors.get("RTE_mm"), "mm"),
            "Rotation error (RRE)": Quantity(errors.get("RRE_deg"), "deg"),
            "Success (RTE < 2 mm and RRE < 2 deg)": errors.get("success")})
        tracking = record.get("tracking_vs_truth")
        if tracking:
            group["Offset of the recorded tracking from the truth (translation)"] = Quantity(
                tracking.get("RTE_mm"), "mm")
            group["Offset of the recorded tracking from the truth (rotation)"] = Quantity(
                tracking.get("RRE_deg"), "deg")
        rows["Error against the truth"] = group
    for method, words in (("search", "the pose search alone"),
                          ("comreg", "with the network")):
        summary = (data.get("summary") or {}).get(method)
        if summary:
            rows[f"Further random starts, {words} (against the same truth)"] = {
                "Starts": summary.get("trials", summary.get("n")),
                "Success rate": Quantity(_percent(summary.get("success_rate")), "%"),
                "Flip rate": Quantity(_percent(summary.get("flip_rate")), "%"),
                "Median translation error (RTE)": Quantity((summary.get("RTE_mm") or {})
                                                           .get("median"), "mm"),
                "Median rotation error (RRE)": Quantity((summary.get("RRE_deg") or {})
                                                        .get("median"), "deg")}
    return rows


def _percent(rate) -> float | None:
    return None if rate is None else 100.0 * float(rate)


def uncertainty_rows(verdict) -> dict[str, Any]:
    """The report's "How far off the pose can be" rows: the 95 % bound, the weakest slide and
    rotation, ``p_correct`` and where to scan next (empty when the verdict has none)."""
    u = verdict.uncertainty
    if u is None:
        return {}
    rows: dict[str, Any] = {
        "95 % bound of the error at the bone under the sweep": Quantity(u["bound_mm"], "mm"),
        "Probability that the pose is within 4 mm / 5 deg":
            Quantity(verdict.figures.get("p_correct")),
        "Noise of the US points about the CT (robust)": Quantity(u["noise_mm"], "mm")}
    for d in u["directions"]:
        label = f"Weakest {'slide' if d['kind'] == 'slide' else 'rotation'} ({d['words']})"
        rows[label] = ("unbounded: the data do not pin it" if d["unbounded"] else
                       Quantity(d["bound_mm"], "mm") if d["kind"] == "slide"
                       else Quantity(d["bound_deg"], "deg"))
    if verdict.scan_next is not None:
        rows["Where to scan next"] = (f"{verdict.scan_next['words']} The pose's bound would be "
                                      f"about {verdict.scan_next['bound_mm']:.1f} mm.")
    return {"How far off the pose can be": rows}


def registration_metrics_table(result: dict[str, Any], figures: dict[str, Any], *,
                               judged_file=None) -> dict[str, Any]:
    """The report's metrics: groups of rows labelled in words, each value a
    :class:`~comreg_core.report.html.Quantity` with its unit (shown in its own column) or a
    word."""
    rows: dict[str, Any] = {
        "Fit of the US points to the CT bone": {
            "Median distance to the CT surface": Quantity(figures["median_mm"], "mm"),
            "90 % of the points within": Quantity(figures["p90_mm"], "mm"),
            "Points within 2 mm of the surface": Quantity(_percent(figures["within_2mm"]), "%"),
            "CT surface touched by the sweep (within 2 mm)":
                Quantity(_percent(figures["coverage"]), "%"),
            "A rigid refit moves the points by (RMS)": Quantity(figures["refit_shift_mm"], "mm"),
            "Best-fitting scale of the US points": Quantity(figures["refit_scale"])}}
    if judged_file is not None:
        rows["Fit of the US points to the CT bone"]["Transform judged"] = str(judged_file)
    search = result.get("search") or result.get("hypotheses")  # "hypotheses": its earlier name
    if search:  # the pose search's choice (comreg_core.registration.search.search)
        weighed = (result.get("uncertainty") or {}).get("competitor")
        pose = {"Another pose fits nearly as well (ambiguous)":
                ambiguity_words(bool(search.get("ambiguous")), weighed),
                "Confidence (0-1; below 0.3 is ambiguous)": Quantity(search.get("confidence")),
                "Pose kept": _start_words(search.get("chosen")),
                "Next best pose": _start_words(search.get("runner_up")),
                "Trimmed mean distance of the kept pose": Quantity(search.get("score_mm"),
                                                                   "mm"),
                "Next best pose is worse by": Quantity(search.get("score_gap_mm"), "mm")}
        competitor = result.get("competitor") or {}
        if competitor.get("name"):
            where = ", ".join(f"{x:.0f}" for x in competitor["centroid_ct"])
            pose["Best clinically different pose"] = (
                f"{_start_words(competitor['name'])}: {competitor['distance_mm']:.0f} mm and "
                f"{competitor['rotation_deg']:.0f} deg from the kept pose, its sweep centred at "
                f"({where}) mm on the CT; margin {competitor['margin']:.2f}")
        if search.get("advice"):  # an ambiguous result: what would tell the poses apart
            pose["What would resolve it"] = search["advice"]["advice"]
        polish = search.get("polish")
        if polish:
            pose["Final polish"] = (
                f"moved {polish['moved_mm']:.2f} mm in {polish['iterations']} iterations, "
                f"{100 * polish['inlier_fraction']:.0f} % of the points matched, "
                f"RMS {polish['rmse_mm']:.2f} mm")
        rows["Pose search"] = pose
    timings = result.get("timings_s") or {}
    rows["Time"] = {"Registration in all": Quantity(result.get("runtime_s"), "s"),
                    **{_stage_words(k): Quantity(v, "s") for k, v in timings.items()
                       if k != "total"}}
    if result.get("warnings"):
        rows["Warnings"] = " ".join(result["warnings"])
    return rows


_STAGE_WORDS = {"preprocess": "Checks and normalisation",
                "completion_and_coarse_pose": "Completion and coarse pose (network)",
                "icp": "Network ICP", "search": "Pose search",
                "hypotheses": "Pose search",  # the search's earlier name in timings_s
                "postprocess": "Back to millimetres", "residuals": "Distances to the CT"}


def _stage_words(key: str) -> str:
    """A ``timings_s`` key in words (an unknown stage: its name, spaced and capitalised)."""
    words = _STAGE_WORDS.get(key) or str(key).replace("_", " ").strip()
    return words[:1].upper() + words[1:]


def _start_words(name: str | None) -> str | None:
    """A start's name such as ``coarse+rot45+slide96`` in words."""
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
