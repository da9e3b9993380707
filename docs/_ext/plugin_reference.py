"""The plugin reference, generated from the plugins' docstrings in Mitsuba's format.

Each plugin's docstring (the module's, or the one of a class in it) is the one source of
truth for its parameters, written as Mitsuba 3 writes its plugin reference (and as
mitransient does for Python plugins):

- an RST label and a section title, ``Name (:monosp:`plugin_name`)`` underlined with ``-``;
- a ``.. pluginparameters::`` list-table of rows ``* - name / - |type| / - description``;
- substitutions for the parameter types and flags (``|float|``, ``|texture|``, ``|bsdf|``,
  ``|int|``, ``|string|``, ``|bool|``, ``|exposed|``, ...) and the ``:monosp:`` role;
- ``.. tabs::`` holding ``.. code-tab:: xml`` / ``.. code-tab:: python`` examples.

This extension reads those docstrings from the source files without importing them (no
Mitsuba, no Dr.Jit needed to build the documentation) and renders them, in the order of
``PLUGIN_MODULES``, where a page says ``.. plugin-reference::``. It also provides the
directives and roles that Mitsuba's documentation defines for that format, so the same
docstring renders here as it would there.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

from docutils import nodes
from docutils.parsers.rst import directives
from docutils.parsers.rst.directives.tables import ListTable
from docutils.statemachine import StringList
from sphinx.directives.code import container_wrapper
from sphinx.util.docutils import SphinxDirective
from sphinx.util.nodes import nested_parse_with_titles

# The modules whose docstrings are the plugin reference, in the order the page lists them.
PLUGIN_MODULES = ("mfnormal.plugins.normalmap_microfacet", "mfnormal.plugins.mfnormal_path", "mfnormal.plugins.mfnormal_prb")

SOURCE_ROOT = Path(__file__).resolve().parents[2] / "src"

# Mitsuba's substitutions for parameter types and flags (its docs/conf.py ``rst_prolog``).
PARAM_TYPES = ("spectrum", "texture", "float", "int", "bool", "string", "bsdf", "phase",
               "point", "vector", "transform", "volume", "tensor", "medium", "emitter",
               "shape", "sensor", "film", "sampler", "rfilter", "integrator")
PARAM_FLAGS = ("exposed", "differentiable", "discontinuous")
TYPE_NAMES = {"int": "integer", "bool": "boolean"}


def substitutions() -> list[str]:
    """The RST substitution definitions of Mitsuba's parameter types and flags."""
    lines = [f".. |{t}| replace:: :paramtype:`{TYPE_NAMES.get(t, t)}`" for t in PARAM_TYPES]
    lines += [f".. |{f}| replace:: :paramflags:`{f}`" for f in PARAM_FLAGS]
    lines += [".. |true| replace:: :monosp:`true`", ".. |false| replace:: :monosp:`false`"]
    return lines


def module_file(module: str) -> Path:
    """The source file of a module of the package (``a.b`` -> src/a/b.py or src/a/b/__init__.py)."""
    base = SOURCE_ROOT.joinpath(*module.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    raise FileNotFoundError(f"plugin reference: no source file for module {module!r} under {SOURCE_ROOT}")


def plugin_docstring(module: str) -> str:
    """The plugin's docstring: the module's if it holds a parameter table, else the first class
    docstring that does, else the module's."""
    tree = ast.parse(module_file(module).read_text(encoding="utf-8"))
    candidates = [ast.get_docstring(tree, clean=True)]
    candidates += [ast.get_docstring(node, clean=True) for node in ast.walk(tree)
                   if isinstance(node, ast.ClassDef)]
    candidates = [doc for doc in candidates if doc]
    if not candidates:
        raise ValueError(f"plugin reference: module {module!r} has no docstring")
    for doc in candidates:
        if ".. pluginparameters::" in doc:
            return doc
    return candidates[0]


def has_title(lines: list[str]) -> bool:
    """Does the docstring open with a section title (its first text line underlined)?"""
    text = [i for i, line in enumerate(lines) if line.strip() and not line.startswith("..")]
    if not text or text[0] + 1 >= len(lines):
        return False
    under = lines[text[0] + 1].strip()
    return len(under) >= 3 and set(under) <= set("-=~^\"'`#*+")


def plugin_rst(module: str) -> list[str]:
    """One plugin's section: its docstring, given a title if it has none: from a first line
    ````name``: summary.`` as ``Summary (:monosp:`name`)``, else from the module's name."""
    lines = plugin_docstring(module).splitlines()
    if not has_title(lines):
        first = re.match(r"^``([\w.]+)``:\s*(.+?)\.?\s*$", lines[0]) if lines else None
        if first and (len(lines) == 1 or not lines[1].strip()):
            summary = first.group(2)
            title = f"{summary[0].upper()}{summary[1:]} (:monosp:`{first.group(1)}`)"
            lines = lines[1:]
        else:
            title = f":monosp:`{module.rsplit('.', 1)[-1]}`"
        lines = [title, "-" * len(title), ""] + lines
    return lines + [""]


def reference_rst(modules=PLUGIN_MODULES) -> list[str]:
    """The whole reference: the substitutions, then every plugin's section."""
    out = substitutions() + [""]
    for module in modules:
        out += plugin_rst(module)
    return out


class PluginReference(SphinxDirective):
    """``.. plugin-reference::``: every plugin of ``PLUGIN_MODULES``, from its docstring."""

    has_content = False

    def run(self):
        for module in PLUGIN_MODULES:
            self.env.note_dependency(str(module_file(module)))
        source = self.state.document.current_source or "plugin-reference"
        content = StringList(reference_rst(), source=source)
        node = nodes.section()
        node.document = self.state.document
        nested_parse_with_titles(self.state, content, node)
        return node.children


class PluginParameters(ListTable):
    """Mitsuba's ``.. pluginparameters::``: a list-table of (parameter, type, description)
    rows, given its header row and column widths here."""

    option_spec = dict(ListTable.option_spec, **{"extra-rows": directives.unchanged})

    def run(self):
        header = StringList(["* - Parameter", "  - Type", "  - Description", ""],
                            source="pluginparameters")
        self.content = header + self.content
        self.options["header-rows"] = 1
        self.options.setdefault("widths", [18, 17, 65])
        self.options["class"] = ["pluginparameters"]
        self.options.pop("extra-rows", None)
        return super().run()


class Tabs(SphinxDirective):
    """``.. tabs::`` (sphinx-tabs): here a plain container of its code tabs, one after another."""

    has_content = True

    def run(self):
        node = nodes.container(classes=["plugin-example"])
        self.state.nested_parse(self.content, self.content_offset, node)
        return [node]


CODE_TAB_CAPTIONS = {"xml": "XML", "python": "Python (mi.load_dict)", "py": "Python"}


class CodeTab(SphinxDirective):
    """``.. code-tab:: language``: a code block captioned with its language."""

    has_content = True
    required_arguments = 1

    def run(self):
        language = self.arguments[0].strip()
        code = "\n".join(self.content)
        literal = nodes.literal_block(code, code, language=language)
        self.set_source_info(literal)
        caption = CODE_TAB_CAPTIONS.get(language.lower(), language)
        return [container_wrapper(self, literal, caption)]


def literal_role(classes):
    def role(name, rawtext, text, lineno, inliner, options=None, content=None):
        return [nodes.literal(rawtext, text, classes=list(classes))], []
    return role


def setup(app):
    app.add_directive("plugin-reference", PluginReference)
    app.add_directive("pluginparameters", PluginParameters)
    app.add_directive("tabs", Tabs)
    app.add_directive("code-tab", CodeTab)
    app.add_role("monosp", literal_role(["monosp"]))
    app.add_role("paramtype", literal_role(["paramtype"]))
    app.add_role("paramflags", literal_role(["paramflags"]))
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
