"""write_report: files, page content (numbers, escaping, versions), embedding, atomicity."""

from __future__ import annotations

import base64
import io
import platform
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from comreg_core import __version__
from comreg_core.errors import InvalidGeometryError
from comreg_core import runs
from comreg_core.report import (IMAGES_DIR, OpenGLUnavailableError, image_name,
                                write_report)
from comreg_core.report.cameras import VIEW_NAMES
from comreg_core.report.html import (Quantity, build_html, flatten, format_value, label_of,
                                     metric_rows, unit_of)
from comreg_core.report.scenes import SCENES
from tests.helpers import paths_under
from tests.report.support import TEST_WINDOW

METRICS = {
    "Median distance to the CT surface": Quantity(0.42, "mm"),
    "Best-fitting scale": Quantity(1.0017),
    "RTE_mm": 3.19, "RRE_deg": 2.93, "CD_mm": 1.2712, "HD95_mm": 3.27, "runtime_s": 0.28,
    "success": False, "flips": 0, "tiny_mm": 0.00012345,
    "summary": {"RTE_mm": {"median": 1.5, "p90": 2.25}},
    "<b>odd & key</b>": "a<b>c",
}
INPUTS = {"US sweep": "/data/<sweep> & \"co\".seq.nrrd", "checkpoint": "/runs/fibula/model.pt"}
TITLE = "Fibula <script>alert('x')</script> report"


class _Page(HTMLParser):
    """Tags, image sources, link targets and the visible text of a page."""

    def __init__(self):
        super().__init__()
        self.tags, self.images, self.links, self.text = [], [], [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        attrs = dict(attrs)
        if tag == "img":
            self.images.append(attrs["src"])
        if "href" in attrs:
            self.links.append(attrs["href"])

    def handle_data(self, data):
        self.text.append(data)


def _parse(path: Path) -> tuple[str, _Page]:
    source = path.read_text(encoding="utf-8")
    page = _Page()
    page.feed(source)
    return source, page


@pytest.fixture(scope="module")
def report(case, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    (out / "config.yaml").write_text("seed: 7\n")  # the run's own files stay untouched
    calls = []
    path = write_report(out, ct_mesh=case.ct, us_before=case.us_before, us_after=case.us_after,
                        completion=case.completion, metrics=METRICS, inputs=INPUTS, seed=7,
                        device="cpu", title=TITLE, window_size=TEST_WINDOW,
                        progress=lambda done, total, note="": calls.append((done, total)))
    return path, calls


def test_report_files(report):
    path, calls = report
    out = path.parent
    assert path == out / runs.REPORT and path.is_file()
    names = sorted(p.name for p in (out / IMAGES_DIR).iterdir())
    cuts = ["section_25.png", "section_50.png", "section_75.png"]  # CT cross-sections
    assert names == sorted([image_name(s, v) for s in SCENES for v in VIEW_NAMES] + cuts)
    from PIL import Image

    for name in names:
        with Image.open(out / IMAGES_DIR / name) as image:
            size = (480, 480) if name in cuts else TEST_WINDOW
            assert image.size == size and image.mode == "RGB"
    assert (out / "config.yaml").read_text() == "seed: 7\n"
    assert sorted(p.name for p in out.iterdir()) == sorted(["config.yaml", IMAGES_DIR,
                                                           runs.REPORT])  # no staging left
    assert calls == [(k, 9) for k in range(1, 10)]


def test_page_references_every_image_relatively_and_nothing_external(report):
    path, _ = report
    _, page = _parse(path)
    assert len(page.images) == 9 + 3  # screenshots + CT cross-sections
    for src in page.images:
        assert src.startswith(f"{IMAGES_DIR}/") and (path.parent / src).is_file()
    assert not page.links
    assert "script" not in page.tags  # no scripts at all (the title's one is text)
    assert not [t for t in page.tags if t in ("link", "iframe", "object")]


def test_page_has_the_metric_values_with_units(report):
    source, page = _parse(report[0])
    text = " ".join(page.text)
    rows = re.findall(r"<tr><td>(.*?)</td><td[^>]*>(.*?)</td><td>(.*?)</td></tr>", source)
    table = {key: (value, unit) for key, value, unit in rows}
    assert table["Translation error (RTE)"] == ("3.190", "mm")
    assert table["Rotation error (RRE)"] == ("2.930", "deg")
    assert table["Chamfer distance (CD)"] == ("1.271", "mm")
    assert table["95th percentile Hausdorff distance (HD95)"] == ("3.270", "mm")
    assert table["Registration time"] == ("0.280", "s")
    assert table["Success"] == ("no", "")
    assert table["Flips"] == ("0", "")
    assert table["Tiny"] == ("0.0001234", "mm")
    assert table["Summary / Translation error (RTE) / Median"] == ("1.500", "mm")
    assert table["Summary / Translation error (RTE) / 90th percentile"] == ("2.250", "mm")
    assert table["Median distance to the CT surface"] == ("0.420", "mm")  # a Quantity
    assert table["Best-fitting scale"] == ("1.002", "")
    assert "a<b>c" in text  # the value, as text
    # every label is in words: no key suffix, no underscore
    for label in table:
        assert "_" not in label and not label.endswith(("mm", "deg")), label


def test_page_escapes_everything(report):
    source, page = _parse(report[0])
    assert "<script>" not in source and "<b>" not in source
    # quotes as Jinja2's autoescape (markupsafe) writes them
    assert "Fibula &lt;script&gt;alert(&#39;x&#39;)&lt;/script&gt; report" in source
    assert "&lt;b&gt;odd &amp; key&lt;/b&gt;" in source
    assert "/data/&lt;sweep&gt; &amp; &#34;co&#34;.seq.nrrd" in source
    assert "b" not in page.tags
    text = " ".join(page.text)
    assert TITLE in text and INPUTS["US sweep"] in text  # the browser shows them as given


def test_page_has_inputs_run_and_versions(report, case):
    import vtk

    source, page = _parse(report[0])
    text = " ".join(page.text)
    assert "/runs/fibula/model.pt" in text
    assert f"{len(case.us_before)} points" in text and f"{len(case.completion)} points" in text
    assert f"{len(case.ct.vertices)} vertices, {len(case.ct.faces)} triangles, space LPS" in text
    assert str(case.ct.path) in text
    rows = dict(re.findall(r"<tr><td>(.*?)</td><td>(.*?)</td></tr>", source))
    assert rows["Seed"] == "7" and rows["Device"] == "cpu"
    assert rows["comreg"] == __version__
    assert rows["vtk"] == vtk.vtkVersion.GetVTKVersion()
    assert rows["python"].startswith(platform.python_version())
    from importlib import metadata

    try:
        torch_version = metadata.version("torch")
    except metadata.PackageNotFoundError:
        torch_version = "not installed"
    assert rows["torch"] == torch_version
    assert rows["off-screen rendering"].startswith(("EGL (", "OSMesa ("))
    assert "principal axis" in text and "LPS" in text


def test_embedded_images_make_one_file(case, tmp_path):
    from PIL import Image

    path = write_report(tmp_path, ct_mesh=case.ct, us_after=case.us_after, views=["anterior"],
                        window_size=(160, 120), embed_images=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == [runs.REPORT]
    _, page = _parse(path)
    assert len(page.images) == 1 + 3  # the view and the three CT cross-sections
    prefix = "data:image/png;base64,"
    assert page.images[0].startswith(prefix)
    with Image.open(io.BytesIO(base64.b64decode(page.images[0][len(prefix):]))) as image:
        assert image.size == (160, 120)


def test_a_failed_report_leaves_the_previous_one_untouched(case, tmp_path, monkeypatch):
    from comreg_core.report import report as report_module

    old_page = "<html>old report</html>"
    (tmp_path / runs.REPORT).write_text(old_page)
    (tmp_path / IMAGES_DIR).mkdir()
    (tmp_path / IMAGES_DIR / "old.png").write_bytes(b"old")
    before = paths_under(tmp_path)

    real = report_module.write_png
    written = []

    def failing(image, path):
        if len(written) == 2:
            raise OSError(28, "No space left on device")
        written.append(path)
        real(image, path)

    monkeypatch.setattr(report_module, "write_png", failing)
    with pytest.raises(OSError, match="No space left"):
        write_report(tmp_path, ct_mesh=case.ct, us_before=case.us_before,
                     us_after=case.us_after, window_size=(96, 96))
    assert len(written) == 2  # it failed half-way through the screenshots
    assert paths_under(tmp_path) == before
    assert (tmp_path / runs.REPORT).read_text() == old_page

    # Once it can write, the new report replaces the old one completely.
    monkeypatch.setattr(report_module, "write_png", real)
    write_report(tmp_path, ct_mesh=case.ct, us_after=case.us_after, views=["lateral"],
                 window_size=(96, 96))
    assert sorted(p.name for p in (tmp_path / IMAGES_DIR).iterdir()) == [
        image_name("registered", "lateral"), "section_25.png", "section_50.png",
        "section_75.png"]
    assert "old report" not in (tmp_path / runs.REPORT).read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == [runs.REPORT, IMAGES_DIR]


def test_without_opengl_the_typed_error_comes_and_nothing_is_written(case, tmp_path, no_opengl):
    out = tmp_path / "run"
    with pytest.raises(OpenGLUnavailableError, match="libosmesa6"):
        write_report(out, ct_mesh=case.ct, us_after=case.us_after)
    assert not out.exists()


def test_bad_input_writes_nothing(case, tmp_path):
    bad = case.us_after.copy()
    bad[0] = np.inf
    out = tmp_path / "run"
    with pytest.raises(InvalidGeometryError):
        write_report(out, ct_mesh=case.ct, us_after=bad)
    assert not out.exists()


def test_ct_mesh_may_be_a_file(tmp_path):
    from tests.helpers import FIBULA_STL

    path = write_report(tmp_path, ct_mesh=FIBULA_STL, views=["anterior"], window_size=(96, 96))
    _, page = _parse(path)
    assert page.images == [f"{IMAGES_DIR}/{image_name('ct', 'anterior')}"]
    assert str(FIBULA_STL) in " ".join(page.text)


# --- the page builder alone ---------------------------------------------------------------------

@pytest.mark.parametrize("value, text", [
    (3.19, "3.190"), (np.float32(2.5), "2.500"), (0.0, "0.000"), (-1.23456, "-1.235"),
    (0.0001234, "0.0001234"), (123456.0, "1.235e+05"), (float("nan"), "NaN"),
    (float("inf"), "inf"), (7, "7"), (np.int64(12), "12"), (True, "yes"), (np.bool_(False), "no"),
    (None, "n/a"), ([1.0, 2], "1.000, 2"), (list(range(20)), "[20 values]"), ("x", "x"),
])
def test_format_value(value, text):
    assert format_value(value) == text


def test_units_and_flatten():
    assert [unit_of(k) for k in ("RTE_mm", "RRE_deg", "runtime_s", "rate", "a / HD95_mm / p90")] \
        == ["mm", "deg", "s", "", "mm"]
    assert flatten({"a": 1, "b": {"c": 2, "d": {}}}) == [("a", 1), ("b / c", 2), ("b / d", "")]


def test_labels_in_words_and_units_apart():
    assert [label_of(k) for k in ("RTE_mm", "success_rate", "initial_RRE_deg", "tiny_mm",
                                  "summary / HD95_mm / p90", "wall_s", "a_b_c")] == [
        "Translation error (RTE)", "Success rate", "Rotation error before registration", "Tiny",
        "Summary / 95th percentile Hausdorff distance (HD95) / 90th percentile",
        "Wall-clock time", "A b c"]
    assert metric_rows({"Fit": {"Median distance to the CT surface": Quantity(0.4, "mm"),
                                "Scale": Quantity(1.0)}, "runtime_s": 2.0}) == [
        ("Fit / Median distance to the CT surface", 0.4, "mm"), ("Fit / Scale", 1.0, ""),
        ("Registration time", 2.0, "s")]


def test_build_html_without_metrics_or_images():
    page = build_html(title="t", sections=[], metrics=None, inputs=[], run=[("Seed", None)],
                      versions=[])
    assert "None given." in page and "<td>n/a</td>" in page
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
