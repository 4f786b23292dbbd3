"""``summary.html`` of ``comreg batch``: the cohort's figures on top, then one row per case with
its verdict, figures, a thumbnail (the report's ``registered_anterior.png``) and a link to its
report. Pure string building, every value HTML-escaped, images by relative path (the page
lives in ``OUT`` beside ``cases/``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from comreg_core.batch.plan import CasePlan
from comreg_core.io._files import atomic_output
from comreg_core.report.html import esc, format_value

#: The report picture shown as each case's thumbnail (``comreg report``'s screenshot).
THUMBNAIL = ("registered", "anterior")

_STYLE = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 1.5em auto;
       max-width: 1400px; color: #141414; padding: 0 1em; line-height: 1.4; }
table { border-collapse: collapse; margin: 0.5em 0; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; vertical-align: top; }
th { background: #f2f2f2; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
img { width: 160px; height: auto; border: 1px solid #ddd; }
.ok { color: #007a3d; font-weight: bold; }
.check, .failed { color: #b00020; font-weight: bold; }
.error { color: #b00020; max-width: 28em; }
"""

#: The case table's columns: (heading, row key).
_CASE_COLUMNS = (("verdict", "verdict"), ("p_correct", "p_correct"),
                 ("median residual (mm)", "residual_median_mm"),
                 ("95th pct residual (mm)", "residual_p95_mm"),
                 ("extent share", "extent_share"), ("RTE (mm)", "RTE_mm"),
                 ("RRE (deg)", "RRE_deg"), ("success", "success"), ("time (s)", "time_total_s"))


def write_html(rows: list[dict[str, Any]], figures: dict[str, Any],
               plans: dict[str, CasePlan], path: str | Path) -> Path:
    """Write ``summary.html`` (module docstring) atomically; returns its path."""
    path = Path(path)
    cohort = "".join(f"<tr><td>{esc(name)}</td><td class=\"num\">{esc(_text(value, name))}"
                     "</td></tr>" for name, value in figures.items())
    head = "".join(f"<th>{esc(title)}</th>" for title in
                   ("case", "status", *(title for title, _ in _CASE_COLUMNS), "report", "error"))
    body = "".join(_case_row(row, plans[row["case"]], path.parent) for row in rows)
    page = (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>ComReg cohort summary</title><style>{_STYLE}</style></head><body>"
        "<h1>ComReg cohort summary</h1>"
        f"<p>{figures['registered']} of {figures['cases']} cases registered, "
        f"{figures['failed']} failed. Success: RTE &lt; 4 mm and RRE &lt; 5 deg against the "
        "case's <code>gt</code>. Times: seconds of each stage's command.</p>"
        f"<h2>Cohort</h2><table><tbody>{cohort}</tbody></table>"
        f"<h2>Cases</h2><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"
        "</body></html>\n")
    with atomic_output(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return path


def _case_row(row: dict[str, Any], plan: CasePlan, root: Path) -> str:
    status = row["status"]
    cells = [f"<td>{esc(row['case'])}</td>", f"<td class=\"{esc(status)}\">{esc(status)}</td>"]
    for _, key in _CASE_COLUMNS:
        value = row[key]
        css = f" class=\"{esc(value)}\"" if key == "verdict" and value else \
            " class=\"num\"" if isinstance(value, (int, float)) and not isinstance(value, bool) \
            else ""
        cells.append(f"<td{css}>{esc(_text(value, key))}</td>")
    report = ""
    if row["report"]:
        from comreg_core.report.report import IMAGES_DIR, image_name

        thumbnail = plan.registration / IMAGES_DIR / image_name(*THUMBNAIL)
        picture = (f"<img src=\"{esc(thumbnail.relative_to(root).as_posix())}\" "
                   f"alt=\"{esc(row['case'])}: registered US points on the CT\">"
                   if thumbnail.is_file() else "report")
        report = f"<a href=\"{esc(row['report'])}\">{picture}</a>"
    cells.append(f"<td>{report}</td>")
    error = "" if not row["error"] else f"{row['failed_stage'] or ''}: {row['error']}"
    cells.append(f"<td class=\"error\">{esc(error.lstrip(': '))}</td>")
    return "<tr>" + "".join(cells) + "</tr>"


def _text(value: Any, key: str) -> str:
    if value is None:
        return ""
    if key == "success rate":
        return f"{100 * value:.0f} %"
    if key.endswith(" s") or key.startswith("time"):
        return f"{value:.1f}"
    return format_value(value)

