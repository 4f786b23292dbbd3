"""The HTML page of a report: pure string building, no rendering, every value HTML-escaped.

The page has no scripts, no external style sheets, fonts or CDN links: the inline ``<style>`` and
the images are all it needs. Images are referenced by relative paths (``report_images/...``) by
default, so the run folder (``report.html`` + ``report_images/``) is the self-contained unit; pass
``data:`` URIs as sources to get a single-file page instead (see ``write_report(embed_images=)``).
"""

from __future__ import annotations

import datetime as _dt
import html
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np


def esc(value: Any) -> str:
    """``str(value)`` with ``& < > " '`` escaped, safe in element text and quoted attributes."""
    return html.escape(str(value), quote=True)


# --- values and units ----------------------------------------------------------------------------

def format_value(value: Any) -> str:
    """How a metric value is written: floats with 3 decimals (``3.190``; 4 significant digits
    below 0.001 or from 100000 up), integers as they are, booleans as yes/no, None as n/a,
    short sequences comma-separated."""
    if value is None:
        return "n/a"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if math.isnan(v):
            return "NaN"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5):
            return f"{v:.4g}"
        return f"{v:.3f}"
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        if len(value) <= 8:
            return ", ".join(format_value(v) for v in value)
        return f"[{len(value)} values]"
    return str(value)


@dataclass(frozen=True)
class Quantity:
    """A metric value with its unit, for a row labelled in words: ``{"Median distance to the CT
    surface": Quantity(0.42, "mm")}`` shows the label as it is, the value and ``mm`` in the unit
    column. ``unit`` is "" for a count, a ratio or yes/no."""

    value: Any
    unit: str = ""


_UNITS = (("_mm", "mm"), ("_deg", "deg"), ("_rad", "rad"), ("_s", "s"), ("_ms", "ms"),
          ("_percent", "%"), ("_pct", "%"), ("_px", "px"))

#: Metric names (without their unit suffix) of the evaluation and the network, in words.
_WORDS = {
    "RTE": "translation error (RTE)", "RRE": "rotation error (RRE)",
    "CD": "Chamfer distance (CD)", "HD95": "95th percentile Hausdorff distance (HD95)",
    "completion_CD": "Chamfer distance of the completion", "runtime": "registration time",
    "completion_HD95": "95th percentile Hausdorff distance of the completion",
    "wall": "wall-clock time", "success_rate": "success rate", "flip_rate": "flip rate",
    "ambiguous_rate": "share flagged ambiguous", "unflagged_flip_rate": "unflagged flip rate",
    "initial_RTE": "translation error before registration",
    "initial_RRE": "rotation error before registration", "p90": "90th percentile",
    "std": "standard deviation", "n": "count",
}


def _split_unit(part: str) -> tuple[str, str]:
    for suffix, unit in _UNITS:
        if part.endswith(suffix) and len(part) > len(suffix):
            return part[:-len(suffix)], unit
    return part, ""


def unit_of(key: str) -> str:
    """The unit a metric name's suffix declares (``RTE_mm`` -> ``mm``; the innermost part of
    ``"summary / RTE_mm / median"`` that declares one), else ""."""
    for part in reversed(str(key).split(" / ")):
        unit = _split_unit(part)[1]
        if unit:
            return unit
    return ""


def label_of(key: str) -> str:
    """A metric name in words, without its unit: each ``" / "`` part loses its unit suffix,
    known names are written out (``RTE_mm`` -> ``Translation error (RTE)``) and underscores
    become spaces; the first letter of each part is upper case."""
    parts = []
    for part in str(key).split(" / "):
        name = _split_unit(part)[0]
        words = _WORDS.get(name, name.replace("_", " ").strip() or name)
        parts.append(words[:1].upper() + words[1:])
    return " / ".join(parts)


def metric_rows(mapping: Mapping[str, Any]) -> list[tuple[str, Any, str]]:
    """``(label in words, value, unit)`` for every leaf of ``mapping`` (:func:`flatten`): a
    :class:`Quantity` gives its own unit and keeps its label as written; any other key is put
    into words by :func:`label_of`, its unit taken from its suffix (:func:`unit_of`)."""
    rows = []
    for key, value in flatten(mapping):
        if isinstance(value, Quantity):
            rows.append((key, value.value, value.unit))
        else:
            rows.append((label_of(key), value, unit_of(key)))
    return rows


def flatten(mapping: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """Nested mappings as ``("outer / inner", value)`` rows, in their order."""
    rows: list[tuple[str, Any]] = []
    for key, value in mapping.items():
        name = f"{prefix} / {key}" if prefix else str(key)
        if isinstance(value, Mapping):
            rows.extend(flatten(value, name) if value else [(name, "")])
        else:
            rows.append((name, value))
    return rows


# --- the page ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Figure:
    """One image on the page: ``src`` (relative path or ``data:`` URI), alt text and caption."""

    src: str
    alt: str
    caption: str
    width: int
    height: int


@dataclass(frozen=True)
class Section:
    """A group of figures (one scene) with a heading and an explanation."""

    heading: str
    text: str
    figures: Sequence[Figure]


_STYLE = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 1.5em auto;
       max-width: 1280px; color: #141414; padding: 0 1em; line-height: 1.4; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { font-size: 1.25em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
.meta { color: #555; }
table { border-collapse: collapse; margin: 0.5em 0; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.7em; text-align: left; vertical-align: top; }
th { background: #f2f2f2; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.figures { display: flex; flex-wrap: wrap; gap: 12px; }
figure { margin: 0; flex: 1 1 300px; max-width: 420px; }
figure img { width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #333; }
.swatch { display: inline-block; width: 0.9em; height: 0.9em; border-radius: 50%;
          vertical-align: -0.1em; margin-right: 0.25em; }
code { font-size: 0.95em; }
.verdict { font-size: 1.8em; font-weight: bold; margin: 0.2em 0; }
.verdict.ok { color: #007a3d; }
.verdict.check { color: #b00020; }
"""


def _table(rows: Sequence[tuple], header: tuple[str, ...], *, numbers: bool = False) -> str:
    """Rows ``(label, value)``, or ``(label, value, unit)`` with a unit column."""
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = []
    for key, value, *unit in rows:
        cells = [f"<td>{esc(key)}</td>"]
        text = format_value(value) if numbers else ("n/a" if value is None else str(value))
        cls = ' class="num"' if numbers and isinstance(value, (int, float, np.number)) \
            and not isinstance(value, (bool, np.bool_)) else ""
        cells.append(f"<td{cls}>{esc(text)}</td>")
        cells.extend(f"<td>{esc(u)}</td>" for u in unit)
        body.append("<tr>" + "".join(cells) + "</tr>")
    if not body:
        return "<p class=\"meta\">None given.</p>"
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def swatch(rgb: Sequence[int]) -> str:
    r, g, b = (int(c) for c in rgb)
    return f'<span class="swatch" style="background: rgb({r}, {g}, {b})"></span>'


def build_html(*, title: str, sections: Sequence[Section], metrics: Mapping[str, Any] | None,
               inputs: Sequence[tuple[str, Any]], run: Sequence[tuple[str, Any]],
               versions: Sequence[tuple[str, Any]], notes: Sequence[str] = (),
               legend: Sequence[tuple[str, Sequence[int]]] = (),
               generated: _dt.datetime | None = None,
               verdict: tuple[str, Sequence[str]] | None = None) -> str:
    """The whole page as a string. Everything given is escaped, keys and values alike.

    ``verdict``: ``(headline, reasons)``, e.g. ``("Verdict: CHECK", [...])``: the first line of
    the page, green for OK and red for CHECK, its reasons listed under it.

    ``notes`` are paragraphs (plain text, escaped) for the "How to read the images" section;
    ``legend`` names the colours (label, 0-255 RGB).
    """
    generated = generated or _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0)
    parts = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
             '<meta name="viewport" content="width=device-width, initial-scale=1">',
             f"<title>{esc(title)}</title>", f"<style>{_STYLE}</style>", "</head>", "<body>"]
    if verdict is not None:
        headline, reasons = verdict
        kind = "ok" if headline.upper().endswith("OK") else "check"
        parts.append(f'<p class="verdict {kind}">{esc(headline)}</p>')
        if reasons:
            parts.append('<ul class="reasons">' + "".join(f"<li>{esc(r)}</li>" for r in reasons)
                         + "</ul>")
    parts += [f"<h1>{esc(title)}</h1>",
             f'<p class="meta">Generated {esc(generated.isoformat())} by ComReg.</p>']
    if legend:
        items = " &nbsp; ".join(f"{swatch(rgb)}{esc(label)}" for label, rgb in legend)
        parts.append(f'<p class="legend">{items}</p>')
    parts.append("<h2>Metrics</h2>")
    parts.append(_table(metric_rows(metrics or {}), ("Metric", "Value", "Unit"), numbers=True))
    for section in sections:
        parts.append(f"<h2>{esc(section.heading)}</h2>")
        if section.text:
            parts.append(f"<p>{esc(section.text)}</p>")
        parts.append('<div class="figures">')
        for fig in section.figures:
            parts.append(
                f'<figure><img src="{esc(fig.src)}" alt="{esc(fig.alt)}" width="{fig.width}" '
                f'height="{fig.height}"><figcaption>{esc(fig.caption)}</figcaption></figure>')
        parts.append("</div>")
    parts.append("<h2>Inputs</h2>")
    parts.append(_table(inputs, ("Input", "Value")))
    parts.append("<h2>Run</h2>")
    parts.append(_table(run, ("Setting", "Value")))
    parts.append("<h2>Versions</h2>")
    parts.append(_table(versions, ("Component", "Version")))
    if notes:
        parts.append("<h2>How to read the images</h2>")
        parts.extend(f"<p>{esc(note)}</p>" for note in notes)
    parts += ["</body>", "</html>", ""]
    return "\n".join(parts)
