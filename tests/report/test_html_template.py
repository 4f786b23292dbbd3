"""The report page from its Jinja2 templates: the same page the string-building code made
(tests/report/data/page_before_*.html, written by it at commit 65caaef), and every value escaped."""

from __future__ import annotations

import datetime as dt
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from comreg_core.report.html import TEMPLATES, Figure, Quantity, Section, build_html

DATA = Path(__file__).parent / "data"
WHEN = dt.datetime(2024, 5, 6, 7, 8, 9, tzinfo=dt.timezone.utc)
ODD = "<script>alert('x')</script> & \"quoted\" 'single'"


def _escaping_page_inputs() -> dict:
    """Every place a value can go, with a ``<script>``, ``&`` and quotes in each."""
    return dict(
        title=ODD, generated=WHEN,
        sections=[Section(ODD, ODD, [Figure("a&b.png", ODD, ODD, 10, 20),
                                     Figure("data:image/png;base64,AAAA", "alt", "cap", 1, 2)]),
                  Section("empty", "", [])],
        metrics={"RTE_mm": 3.19, ODD: ODD, "n": np.int64(3), "ok": np.bool_(True),
                 "nan_mm": float("nan"), "inf": float("-inf"), "big": 123456.0,
                 "list": [1.0, 2.5], "long": list(range(20)), "arr": np.array([0.5, 1.5]),
                 "nested": {"a": {"b_deg": 2.0}, "empty": {}},
                 "q": Quantity(0.42, "mm"), "qodd": Quantity(ODD, ODD), "none": None},
        inputs=[(ODD, ODD), ("path", "/x/<y>.ply"), ("none", None), ("num", 1.5)],
        run=[("Seed", 7), ("Device", "cpu")], versions=[("ComReg", "1.0"), (ODD, ODD)],
        notes=["first note", ODD], legend=[("CT bone", (200, 200, 200)), (ODD, (1.9, 2, 3))],
        verdict=("Verdict: OK", ["fine", ODD]))


def _check_page_inputs() -> dict:
    return dict(title="check2", generated=WHEN, sections=[], metrics={}, inputs=[], run=[],
                versions=[], verdict=("Verdict: CHECK", ["a", "b"]), legend=[("x", (0, 0, 0))],
                notes=["n"])


def _as_before(page: str) -> str:
    """Quotes as ``html.escape`` wrote them (Jinja2's autoescape writes ``&#34;``, ``&#39;``)."""
    return page.replace("&#34;", "&quot;").replace("&#39;", "&#x27;")


def test_the_page_is_the_one_the_string_building_code_made():
    for inputs, name in ((_escaping_page_inputs(), "page_before_escaping.html"),
                         (_check_page_inputs(), "page_before_check.html")):
        before = (DATA / name).read_text(encoding="utf-8")
        assert _as_before(build_html(**inputs)) == before, name


class _Page(HTMLParser):
    """Tags with their attributes, and the visible text."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.tags, self.text = [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data):
        self.text.append(data)


def test_script_and_ampersand_are_escaped_everywhere():
    source = build_html(**_escaping_page_inputs())
    assert "<script>" not in source and "</script>" not in source
    assert "&lt;script&gt;" in source and "a&amp;b.png" in source and " & " not in source
    page = _Page()
    page.feed(source)
    assert [tag for tag, _ in page.tags].count("script") == 0
    images = [attrs for tag, attrs in page.tags if tag == "img"]
    assert images[0] == {"src": "a&b.png", "alt": ODD, "width": "10", "height": "20"}
    text = "".join(page.text)
    # the browser shows every value as it was given: title, heading, caption, metric, note...
    assert text.count(ODD) >= 12, text.count(ODD)
    assert 'rgb(1, 2, 3)' in source  # legend colours are integers


def test_values_with_markup_methods_are_still_escaped():
    """An object that says it is HTML (``__html__``) is shown as its text, like any value."""

    class Sneaky:
        def __html__(self):
            return "<script>bad()</script>"

        def __str__(self):
            return "<i>sneaky</i>"

    from markupsafe import Markup

    sneaky, bold = Sneaky(), Markup("<b>bold</b>")
    source = build_html(title=bold, sections=[Section(sneaky, bold, [Figure(
        bold, sneaky, bold, 1, 2)])], metrics={"v": sneaky}, inputs=[(bold, sneaky)], run=[],
        versions=[], notes=[sneaky], legend=[(bold, (1, 2, 3))], generated=WHEN,
        verdict=(bold, [sneaky]))
    assert "<script>" not in source and "<i>" not in source and "<b>" not in source
    assert source.count("&lt;i&gt;sneaky&lt;/i&gt;") == 6
    assert source.count("&lt;b&gt;bold&lt;/b&gt;") == 8


def test_templates_are_package_data():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+

    pyproject = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    patterns = pyproject["tool"]["setuptools"]["package-data"]["comreg_core"]
    shipped = {p.relative_to(TEMPLATES.parent.parent).as_posix()
               for pattern in patterns for p in TEMPLATES.parent.parent.glob(pattern)}
    assert {"report/templates/report.html.j2", "report/templates/macros.html.j2"} <= shipped
