"""The HTML page of a report: the values in words and units here, the markup in Jinja2 templates
(``templates/report.html.j2``, rendered with autoescape on: every value is HTML-escaped).

The page has no scripts, no external style sheets, fonts or CDN links: the inline ``<style>`` and
the images are all it needs. Images are referenced by relative paths (``report_images/...``) by
default, so the run folder (``report.html`` + ``report_images/``) is the self-contained unit; pass
``data:`` URIs as sources to get a single-file page instead (see ``write_report(embed_images=)``).
"""

from __future__ import annotations

import datetime as _dt
import functools
import html
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jinja2
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


#: Where the page's Jinja2 templates live (package data: ``report/templates/*.j2``).
TEMPLATES = Path(__file__).with_name("templates")


@functools.lru_cache(maxsize=1)
def _environment() -> jinja2.Environment:
    """The templates' environment: autoescape on for every template (all are HTML), undefined
    names are errors, block tags leave no blank lines."""
    return jinja2.Environment(loader=jinja2.FileSystemLoader(TEMPLATES), autoescape=True,
                              undefined=jinja2.StrictUndefined, trim_blocks=True,
                              lstrip_blocks=True, keep_trailing_newline=True)


@dataclass(frozen=True)
class _Row:
    """One table row as the template shows it: texts, and whether the value is a number."""

    label: str
    text: str
    number: bool
    units: tuple[str, ...]


def _table_rows(rows: Sequence[tuple], *, numbers: bool = False) -> list[_Row]:
    """Rows ``(label, value)``, or ``(label, value, unit)`` with a unit column; with ``numbers``
    values are written by :func:`format_value` and numbers right-aligned."""
    out = []
    for key, value, *unit in rows:
        text = format_value(value) if numbers else ("n/a" if value is None else str(value))
        number = numbers and isinstance(value, (int, float, np.number)) \
            and not isinstance(value, (bool, np.bool_))
        out.append(_Row(str(key), text, number, tuple(str(u) for u in unit)))
    return out


def build_html(*, title: str, sections: Sequence[Section], metrics: Mapping[str, Any] | None,
               inputs: Sequence[tuple[str, Any]], run: Sequence[tuple[str, Any]],
               versions: Sequence[tuple[str, Any]], notes: Sequence[str] = (),
               legend: Sequence[tuple[str, Sequence[int]]] = (),
               generated: _dt.datetime | None = None,
               verdict: tuple[str, Sequence[str]] | None = None) -> str:
    """The whole page as a string, rendered from ``templates/report.html.j2`` with autoescape
    on: everything given is escaped, keys and values alike.

    ``verdict``: ``(headline, reasons)``, e.g. ``("Verdict: CHECK", [...])``: the first line of
    the page, green for OK and red for CHECK, its reasons listed under it.

    ``notes`` are paragraphs (plain text, escaped) for the "How to read the images" section;
    ``legend`` names the colours (label, 0-255 RGB).
    """
    generated = generated or _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0)
    if verdict is not None:
        headline, reasons = str(verdict[0]), [str(r) for r in verdict[1]]
        verdict = {"headline": headline, "reasons": reasons,
                   "kind": "ok" if headline.upper().endswith("OK") else "check"}
    # Plain str everywhere: a value that says it is markup (``__html__``) is escaped too.
    sections = [Section(str(s.heading), str(s.text), [
        Figure(str(f.src), str(f.alt), str(f.caption), int(f.width), int(f.height))
        for f in s.figures]) for s in sections]
    return _environment().get_template("report.html.j2").render(
        title=str(title), generated=generated.isoformat(), verdict=verdict,
        legend=[(str(label), [int(c) for c in rgb]) for label, rgb in legend],
        metrics=_table_rows(metric_rows(metrics or {}), numbers=True), sections=sections,
        inputs=_table_rows(inputs), run=_table_rows(run), versions=_table_rows(versions),
        notes=[str(note) for note in notes])
