"""The documentation site: it builds with warnings as errors, and it shows what it should.

One ``python -m sphinx -W -b html docs OUT`` build (a subprocess, into a temporary folder)
feeds the tests. The plugin reference is generated from the plugins' docstrings by
``docs/_ext/plugin_reference.py``: its page must hold a section per plugin module and the
``normalmap_microfacet`` parameter table, row by row, so a generator that renders nothing, or
a docstring that loses its table, fails here. The front page and the reference are then
opened in headless Chromium (skipped, with the reason, when Chromium, chromedriver or
selenium is missing; ``scripts/setup.sh --test`` installs them as root): the front page
links to the reference, the link leads there, the table is displayed, every image loads and
the console shows no error other than an external resource that cannot be fetched offline.
"""

import ast
import importlib.util
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

# Rows the normalmap_microfacet table must have (a subset: the docstring may add more).
PLUGIN_ROWS = ("normalmap", "heightmap", "height_scale", "macro_normal", "model", "tangent_facet",
               "max_bounces", "rr_depth", "mis_boost_max", "normalmap_convention", "strength",
               "tangents")


def _generator():
    """docs/_ext/plugin_reference.py as a module (imports Sphinx and docutils, not Mitsuba)."""
    spec = importlib.util.spec_from_file_location("plugin_reference", DOCS / "_ext" / "plugin_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The built site's folder (the build must pass with warnings as errors)."""
    out = tmp_path_factory.mktemp("docs") / "html"
    proc = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
                           str(DOCS), str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, "the docs build failed or warned:\n" + proc.stdout + proc.stderr
    return out


class _Tables(HTMLParser):
    """The rows (first cell's text) of every table with class ``pluginparameters``, per table,
    and the section ids and hrefs of a page."""

    def __init__(self):
        super().__init__()
        self.tables, self.ids, self.hrefs = [], [], []
        self._depth = 0          # nesting inside a pluginparameters table
        self._cell = None        # text of the first cell of the current body row
        self._col = 0
        self._in_body = False

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if attrs.get("id"):
            self.ids.append(attrs["id"])
        if tag == "a" and attrs.get("href"):
            self.hrefs.append(attrs["href"])
        if tag == "table":
            if self._depth or "pluginparameters" in (attrs.get("class") or "").split():
                if not self._depth:
                    self.tables.append([])
                self._depth += 1
        elif self._depth:
            if tag == "tbody":
                self._in_body = True
            elif tag == "tr":
                self._col = 0
            elif tag == "td" and self._in_body:
                self._col += 1
                if self._col == 1:
                    self._cell = ""

    def handle_endtag(self, tag):
        if not self._depth:
            return
        if tag == "table":
            self._depth -= 1
        elif tag == "tbody":
            self._in_body = False
        elif tag == "td" and self._cell is not None and self._col == 1:
            self.tables[-1].append(self._cell.strip())
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data


def _parse(path):
    parser = _Tables()
    parser.feed(path.read_text(encoding="utf-8"))
    return parser


# ---------------------------------------------------------------------------
# The generator and the build
# ---------------------------------------------------------------------------

def test_the_generator_reads_every_plugin_docstring():
    gen = _generator()
    assert gen.PLUGIN_MODULES, "no plugin modules to document"
    for module in gen.PLUGIN_MODULES:
        doc = gen.plugin_docstring(module)
        assert doc.strip(), module
        ast.parse(gen.module_file(module).read_text(encoding="utf-8"))
    bsdf = gen.plugin_docstring(gen.PLUGIN_MODULES[0])
    assert ".. pluginparameters::" in bsdf and "normalmap_microfacet" in bsdf
    rst = "\n".join(gen.reference_rst())
    for row in PLUGIN_ROWS:
        assert re.search(rf"^\s*\* - {row}\s*$", rst, re.M), f"no row {row!r} in the generated reference"


def test_the_docs_build_with_warnings_as_errors(site):
    for page in ("index", "plugins", "models", "model", "faithful", "normal_sources", "cli", "gltf",
                 "differentiable", "validation", "performance", "diagnoses", "troubleshooting",
                 "development"):
        assert (site / f"{page}.html").is_file(), page


def test_the_plugin_reference_holds_the_parameter_tables(site):
    page = _parse(site / "plugins.html")
    assert page.tables, "the plugin reference has no parameter table"
    bsdf_rows = page.tables[0]
    missing = [row for row in PLUGIN_ROWS if row not in bsdf_rows]
    assert not missing, f"normalmap_microfacet's table lacks rows {missing}; it has {bsdf_rows}"
    assert "bsdf-normalmap-microfacet" in page.ids or "bsdf-normalmap_microfacet" in page.ids
    text = (site / "plugins.html").read_text(encoding="utf-8")
    for name in ("normalmap_microfacet", "mfnormal_path", "mfnormal_prb"):
        assert name in text, name
    # Mitsuba's substitutions are rendered, not left as |float| or :monosp:.
    assert "|float|" not in text and "|texture|" not in text and ":monosp:" not in text
    assert 'class="paramtype' in text
    # Every row reads as prose: no flag substitution left dangling as "(Exposed, exposed )".
    words = " ".join(re.sub(r"<[^>]+>", " ", text).split())
    assert not re.search(r"\(Exposed, exposed\s*\)", words, re.I), "a row ends in a bare flag"
    assert "what Mitsuba’s bumpmap calls scale" in words or "what Mitsuba's bumpmap calls scale" in words


def test_the_front_page_links_to_the_plugin_reference(site):
    page = _parse(site / "index.html")
    assert any(href.split("#")[0] == "plugins.html" for href in page.hrefs), page.hrefs


def test_no_parameter_table_outside_the_docstrings():
    """The docstring is the one source of truth: no markdown table lists the plugin's
    parameters elsewhere (README.md, docs/*.md): at most two table rows of a page start with a
    parameter's name (a header such as ``| `model` | ... |`` is not a parameter table)."""
    rows = re.compile(r"^\|\s*`(" + "|".join(PLUGIN_ROWS) + r")`\s*\|", re.M)
    for path in [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]:
        found = rows.findall(path.read_text(encoding="utf-8"))
        assert len(found) <= 2, f"{path.relative_to(ROOT)} repeats the parameter table ({found})"


# ---------------------------------------------------------------------------
# In headless Chromium
# ---------------------------------------------------------------------------

def _loaded(browser):
    from selenium.webdriver.support.ui import WebDriverWait
    WebDriverWait(browser, 20).until(lambda d: d.execute_script(
        "return document.readyState === 'complete' && Array.from(document.images).every(i => i.complete)"))


def _local_errors(browser):
    """Console errors, less failed loads of external resources (MathJax from its CDN offline)."""
    return [e for e in browser.get_log("browser") if e["level"] in ("SEVERE", "ERROR")
            and not re.search(r"https?://(?!localhost)", e["message"])]


def test_the_site_in_headless_chromium(site, browser):
    from selenium.webdriver.common.by import By

    browser.get((site / "index.html").as_uri())
    _loaded(browser)
    assert "mfnormal" in browser.title
    assert "normalmap_microfacet" in browser.find_element(By.TAG_NAME, "body").text
    broken = browser.execute_script(
        "return Array.from(document.images).filter(i => !(i.naturalWidth > 0)).map(i => i.src)")
    assert broken == []
    assert browser.execute_script("return document.images.length") >= 1     # the demo picture
    assert _local_errors(browser) == []

    # The front page's link leads to the plugin reference.
    links = [a for a in browser.find_elements(By.CSS_SELECTOR, "a[href]")
             if a.get_attribute("href").split("#")[0].endswith("/plugins.html")]
    assert links, "the front page does not link to the plugin reference"
    browser.get(links[0].get_attribute("href"))
    _loaded(browser)
    assert browser.current_url.split("#")[0].endswith("/plugins.html")

    # The parameter table is displayed, with its rows.
    tables = browser.find_elements(By.CSS_SELECTOR, "table.pluginparameters")
    assert tables and tables[0].is_displayed()
    first_cells = [td.text.strip() for td in tables[0].find_elements(By.CSS_SELECTOR, "tbody tr > td:first-child")]
    assert {"normalmap", "model", "strength"} <= set(first_cells), first_cells
    header = [th.text.strip() for th in tables[0].find_elements(By.CSS_SELECTOR, "thead th")]
    assert header == ["Parameter", "Type", "Description"], header
    height = browser.execute_script("return arguments[0].getBoundingClientRect().height", tables[0])
    assert height > 300          # a dozen rows of text, not an empty frame
    heading = browser.find_element(By.CSS_SELECTOR, "h2").text
    assert "normalmap_microfacet" in heading
    assert _local_errors(browser) == []
