"""The cohort summary of ``comreg batch``: ``summary.csv`` (one row per case) and
``summary.html`` (the same with each case's thumbnail and a link to its report, the cohort's
success rate and timings on top), from the stages' status files and each registration's
``result.json``. Run by the Snakefile's ``summary`` rule::

    python -m comreg_core.batch.summary --manifest MANIFEST --out OUT [--pretrain-minutes M]

Columns of ``summary.csv`` (:data:`COLUMNS`): ``case``; ``status`` (``ok``: every stage ran,
``failed``); ``failed_stage`` and ``error`` (its one-line error); from ``result.json``:
``verdict`` (``ok``/``check``), ``p_correct`` (with a verdict calibration), ``confidence``,
``ambiguous``, ``n_points``, ``residual_median_mm``, ``residual_p95_mm`` (distances of the
registered US points to the CT), ``extent_share`` (the sweep's spread over the CT's length);
with a ``gt``: ``RTE_mm`` (at the US centroid), ``RRE_deg`` and ``success`` (RTE < 4 mm and
RRE < 5 deg, the real-data tolerance of :mod:`comreg_core.registration.judgement.calibration`); the
seconds of each stage's command (``time_<stage>_s``, empty when the stage did not run) and
their sum; ``report`` (the report's path relative to ``OUT``). Empty cells mean "not known".
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from comreg_core import runs
from comreg_core.batch.plan import STAGES, SUMMARY_CSV, SUMMARY_HTML, CasePlan, plan_cases
from comreg_core.batch.stage import OK, read_status
from comreg_core.errors import ComRegError
from comreg_core.io._files import atomic_output

COLUMNS = ("case", "status", "failed_stage", "error", "verdict", "p_correct", "confidence",
           "ambiguous", "n_points", "residual_median_mm", "residual_p95_mm", "extent_share",
           "RTE_mm", "RRE_deg", "success", *(f"time_{stage}_s" for stage in STAGES),
           "time_total_s", "report")


def case_row(plan: CasePlan) -> dict[str, Any]:
    """The summary row of one case (module docstring); None for what is not known."""
    row: dict[str, Any] = dict.fromkeys(COLUMNS)
    row.update(case=plan.case.name, status=OK)
    total = 0.0
    for stage in plan.stages:
        path = plan.status(stage)
        record = read_status(path) if path.is_file() else {
            "status": "failed", "failed_stage": stage, "error": "not run", "seconds": 0.0,
            "exit_code": None}
        if record["exit_code"] is not None:  # the command ran (not skipped after a failure)
            row[f"time_{stage}_s"] = record["seconds"]
            total += record["seconds"]
        if record["status"] != OK and row["status"] == OK:
            row.update(status="failed", failed_stage=record["failed_stage"],
                       error=record["error"])
    row["time_total_s"] = round(total, 3)
    result_path = plan.registration / runs.RESULT
    if plan.status("register").is_file() and \
            read_status(plan.status("register"))["status"] == OK and result_path.is_file():
        result = json.loads(result_path.read_text(encoding="utf-8"))
        residuals = result.get("residuals_mm") or {}
        search = result.get("search") or result.get("hypotheses") or {}  # its earlier name
        row.update(verdict=result.get("verdict"), p_correct=result.get("p_correct"),
                   confidence=result.get("confidence", search.get("confidence")),
                   ambiguous=result.get("ambiguous"), n_points=result.get("n_points"),
                   residual_median_mm=residuals.get("median"),
                   residual_p95_mm=residuals.get("p95"),
                   extent_share=result.get("extent_share"))
        if plan.case.gt is not None:
            try:
                row.update(evaluate(plan, result))
            except ComRegError as exc:
                row["error"] = f"cannot evaluate against 'gt': {exc}"
        if (plan.registration / runs.REPORT).is_file():
            row["report"] = (plan.registration / runs.REPORT).relative_to(plan.out).as_posix()
    if plan.case.gt is not None and row["success"] is None:
        row["success"] = False  # a case with a truth that did not register is no success
    return row


def evaluate(plan: CasePlan, result: dict[str, Any]) -> dict[str, Any]:
    """``{"RTE_mm", "RRE_deg", "success"}`` of the registration in ``result`` against the
    case's ``gt`` (``T_ct_us``, an ITK transform file): RTE at the centroid of the US points it
    registered (``registered_us.ply`` moved back by its ``T_ct_us``), RRE of the rotations;
    success within the real-data tolerance (4 mm, 5 deg)."""
    from comreg_core.io import load_transform, read_points
    from comreg_core.registration.judgement.calibration import TOLERANCE_DEG, TOLERANCE_MM
    from comreg_core.registration.geometry.metrics import rotation_error_deg, translation_error_mm
    from comreg_core.transforms import apply_transform, invert_rigid

    space = result.get("space", "LPS")
    T_est = np.asarray(result["T_ct_us"], dtype=np.float64)
    T_true = load_transform(plan.case.gt, space=space)
    registered = read_points(plan.registration / runs.REGISTERED_US).in_space(space).points
    centroid = apply_transform(invert_rigid(T_est), registered).mean(axis=0)
    rte = translation_error_mm(T_est, T_true, centroid)
    rre = rotation_error_deg(T_est[:3, :3], T_true[:3, :3])
    return {"RTE_mm": rte, "RRE_deg": rre,
            "success": bool(rte < TOLERANCE_MM and rre < TOLERANCE_DEG)}


def summary_rows(plans: dict[str, CasePlan]) -> list[dict[str, Any]]:
    """One row per case, in the manifest's order."""
    return [case_row(plan) for plan in plans.values()]


def cohort_figures(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The cohort's figures: counts, the success rate over the cases with a ``gt`` (a failed
    case counts as not a success), median and total seconds of each stage."""
    with_truth = [row for row in rows if row["success"] is not None]
    figures: dict[str, Any] = {
        "cases": len(rows),
        "registered": sum(row["status"] == OK for row in rows),
        "failed": sum(row["status"] != OK for row in rows),
        "verdict OK": sum(row["verdict"] == "ok" for row in rows),
        "cases with a gt": len(with_truth),
        "success rate": (sum(bool(row["success"]) for row in with_truth) / len(with_truth)
                         if with_truth else None)}
    for stage in STAGES:
        seconds = [row[f"time_{stage}_s"] for row in rows if row[f"time_{stage}_s"] is not None]
        if seconds:
            figures[f"{stage} median s"] = float(np.median(seconds))
            figures[f"{stage} total s"] = float(np.sum(seconds))
    return figures


def write_csv(rows: list[dict[str, Any]], path: str | Path) -> Path:
    """``summary.csv``: :data:`COLUMNS`, floats to 4 decimals, None as an empty cell."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({key: _cell(row[key]) for key in COLUMNS})
    with atomic_output(path) as tmp:
        tmp.write_text(buffer.getvalue(), encoding="utf-8")
    return Path(path)


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.4f}"
    return str(value)


def main(argv: list[str] | None = None) -> int:
    """``python -m comreg_core.batch.summary``'s entry point: write both summary files."""
    from comreg_core.batch.summary_html import write_html

    parser = argparse.ArgumentParser(prog="python -m comreg_core.batch.summary",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--manifest", required=True, type=Path)
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--pretrain-minutes", type=float, default=0.0)
    options = parser.parse_args(argv)
    plans = plan_cases(options.manifest, options.out, pretrain_minutes=options.pretrain_minutes)
    rows = summary_rows(plans)
    figures = cohort_figures(rows)
    write_csv(rows, options.out / SUMMARY_CSV)
    write_html(rows, figures, plans, options.out / SUMMARY_HTML)
    print(f"wrote {options.out / SUMMARY_CSV} and {options.out / SUMMARY_HTML}: "
          f"{figures['registered']} of {figures['cases']} cases registered")
    return 0


if __name__ == "__main__":
    sys.exit(main())
