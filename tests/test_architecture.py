"""The package's shape: data flows one way, and every function fits on a screen.

Read from the source with ``ast`` (nothing is imported): the import graph of
``src/mfnormal`` (modules named by their dotted path below it, ``models.walk``; the package's
face, ``mfnormal/__init__.py``, is ``""``) has no cycle, counting every import statement, those
inside functions too (a deferred import is still a dependency), except the ones under ``if
__name__ == "__main__":`` (a module run as a program is not imported); every import runs down
the layers of :data:`LAYERS` (a module imports its own package and those below it, never one
above); the installed package imports nothing of the repository's ``validation`` harnesses;
``report.html`` imports nothing of the package but file and image writing (it only writes
HTML); no function in ``src/`` is longer than ``MAX_FUNCTION_LINES``; nothing in the
repository monkeypatches, and no harness, benchmark, script or example edits ``sys.path``.
"""

import ast
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "mfnormal"
MAX_FUNCTION_LINES = 60
#: The package's layers, lowest first: a module imports its own package and those below it.
#: Data flows one way, scene → plugin → model → microsurface (STYLE.md), and the tools sit on
#: top: the bundled scenes and the methods' catalogue below the input and output, rendering
#: (here or on a cluster) below both the report and the command line. ``""`` is the package's
#: face (``mfnormal/__init__.py``: ``register``, the plugins); a top-level module is its own package.
LAYERS = ("_llvm", "files", "surface", "models", "normals", "plugins", "", "methods", "scenes", "io",
          "render", "report", "cli", "__main__")


def _is_main_guard(node) -> bool:
    return (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
            and isinstance(node.test.left, ast.Name) and node.test.left.id == "__name__")


def module_name(path: Path) -> str:
    """``models.walk`` for src/mfnormal/models/walk.py, ``cli`` for src/mfnormal/cli/__init__.py."""
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _targets(node, here: str) -> list:
    """The dotted module names (below ``mfnormal``, or ``validation...``) that one import names."""
    if isinstance(node, ast.Import):
        return [a.name.partition(".")[2] if a.name.startswith("mfnormal.") else a.name.replace("mfnormal", "")
                for a in node.names if a.name.startswith(("mfnormal.", "validation")) or a.name == "mfnormal"]
    if node.level:
        base = here.split(".")[:len(here.split(".")) - node.level + (1 if here.endswith("__init__") else 0)]
        module = ".".join(base + ([node.module] if node.module else []))
    elif node.module == "mfnormal" or (node.module or "").startswith("mfnormal."):
        module = node.module.partition(".")[2]
    elif (node.module or "").startswith("validation"):
        return [node.module]
    else:
        return []
    return [f"{module}.{a.name}".strip(".") for a in node.names] + [module]


def _imported_modules(path: Path, modules: set) -> set:
    """The package's modules (and validation harnesses) that ``path`` imports."""
    tree = ast.parse(path.read_text())
    skipped = {id(n) for guard in ast.walk(tree) if _is_main_guard(guard) for n in ast.walk(guard)}
    here = module_name(path)
    found = set()
    for node in ast.walk(tree):
        if id(node) in skipped or not isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        for target in _targets(node, here):
            if target.startswith("validation") or target in modules:
                found.add(target)
    return found - {here}


def import_graph() -> dict:
    paths = sorted(PACKAGE.rglob("*.py"))
    modules = {module_name(p) for p in paths}
    return {module_name(p): _imported_modules(p, modules) for p in paths}


def cycles(graph: dict) -> list:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while not component or w != v:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_package_has_no_import_cycle():
    graph = import_graph()
    assert {"cli.commands", "report.compare", "report.html", "cli.demo", "plugins.normalmap_microfacet"} <= set(graph)
    assert "report.html" in graph["report.compare"] and "cli.demo" in graph["cli.commands"]  # real imports
    assert cycles(graph) == []


def _package(module: str) -> str:
    return module.split(".")[0]


def upward_imports(graph: dict) -> list:
    """``"a imports b"`` for each import in ``graph`` whose target lies in a higher layer of
    :data:`LAYERS` than its importer (or in a package that no layer names)."""
    rank = {package: i for i, package in enumerate(LAYERS)}
    return [f"{m} imports {t}" for m, targets in sorted(graph.items()) for t in sorted(targets)
            if not t.startswith("validation")
            and rank.get(_package(t), len(LAYERS)) > rank.get(_package(m), -1)]


def test_every_package_has_its_layer():
    assert {_package(m) for m in import_graph()} == set(LAYERS)


def test_imports_run_down_the_layers():
    assert upward_imports(import_graph()) == []


def test_the_layer_check_sees_an_upward_import():
    """What the check forbids, it finds: a model importing the plugin, the microsurface a model,
    the catalogue the report, a package no layer names."""
    graph = {"models.walk": {"plugins.normalmap_microfacet", "surface.shading"},
             "surface.shading": {"models.walk"}, "methods": {"report.compare"}, "cli.demo": {"tools.x"},
             "render.passes": {"", "io.messages"}}
    assert upward_imports(graph) == ["cli.demo imports tools.x", "methods imports report.compare",
                                     "models.walk imports plugins.normalmap_microfacet",
                                     "surface.shading imports models.walk"]


def test_no_harness_edits_sys_path():
    """The harnesses, benchmarks, scripts and examples run as modules from the repository's root
    (``python -m validation.run``) or as files beside what they import: none edits ``sys.path``."""
    files = subprocess.run(["git", "ls-files", "validation/*.py", "benchmarks/*.py", "scripts/*.py",
                            "examples/*.py"], cwd=ROOT, capture_output=True, text=True).stdout.split()
    assert files and [f for f in files if (ROOT / f).exists() and "sys.path" in (ROOT / f).read_text()] == []


def test_the_installed_package_imports_no_validation_harness():
    assert [m for m, targets in import_graph().items() if any(t.startswith("validation") for t in targets)] == []


def test_the_report_only_writes_html():
    assert import_graph()["report.html"] <= {"files", "io.images", "io"}


def test_the_import_graph_sees_a_back_reference():
    """The checks above fail on what they forbid: a model importing the plugin."""
    fake = PACKAGE / "models" / "walk.py"
    tree_targets = _targets(ast.parse("from mfnormal.plugins import normalmap_microfacet").body[0],
                            module_name(fake))
    assert "plugins.normalmap_microfacet" in tree_targets


def test_no_function_is_longer_than_a_screen():
    long = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                start = min([node.lineno] + [d.lineno for d in node.decorator_list])
                if node.end_lineno - start + 1 > MAX_FUNCTION_LINES:
                    long.append(f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name} "
                                f"({node.end_lineno - start + 1} lines)")
    assert long == []


def _module_names(tree) -> set:
    """Names a file binds to modules: ``import x [as y]``, and ``from package import module``
    where the module is one of the package's or of the validation harnesses."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith(("mfnormal", "validation")):
            folder = (ROOT / "src" if node.module.startswith("mfnormal") else ROOT).joinpath(*node.module.split("."))
            names.update(a.asname or a.name for a in node.names
                         if (folder / f"{a.name}.py").exists() or (folder / a.name).is_dir())
    return names


#: Attributes a module documents as the way to customise it, not patches: the warnings module's
#: ``showwarning`` ("you may replace this function ... by assigning to warnings.showwarning"),
#: which the command line sets inside ``warnings.catch_warnings()`` to print one-line warnings.
HOOKS = {("warnings", "showwarning")}


def monkeypatches(source: str) -> list:
    """The lines of ``source`` that replace attributes at run time: pytest's ``monkeypatch``,
    ``mock.patch``, or ``setattr`` on or assignment to an attribute of a module (a name the file
    binds to a module)."""
    tree = ast.parse(source)
    modules = _module_names(tree)
    hits = {n.lineno for n in ast.walk(tree)
            if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == "setattr"
            and n.args and isinstance(n.args[0], ast.Name) and n.args[0].id in modules}
    hits |= {n.lineno for n in ast.walk(tree) if isinstance(n, (ast.Assign, ast.AugAssign))
             for t in (n.targets if isinstance(n, ast.Assign) else [n.target])
             if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id in modules
             and (t.value.id, t.attr) not in HOOKS}
    hits |= {i for i, line in enumerate(source.splitlines(), 1) if "monkeypatch" in line or "mock.patch" in line}
    return sorted(hits)


def test_the_monkeypatch_finder_finds_one():
    assert monkeypatches("import os\nsetattr(os, 'sep', '/')\n") == [2]
    assert monkeypatches("from mfnormal.models import faithful\nsetattr(faithful, 'X', 1)\n") == [2]
    assert monkeypatches("def t(monkeypatch):\n    pass\n") == [1]
    assert monkeypatches("from mfnormal.models import walk\nwalk.FLAG = True\n") == [2]
    assert monkeypatches("class S:\n    pass\nbs = S()\nsetattr(bs, 'wo', 1)\n") == []


def test_nothing_monkeypatches():
    """No test or tool replaces a module's attributes at run time (pytest's ``monkeypatch``,
    ``setattr`` on a module, ``unittest.mock.patch``): what a test needs to vary is a parameter."""
    files = subprocess.run(["git", "ls-files", "*.py"], cwd=ROOT, capture_output=True, text=True).stdout.split()
    me = Path(__file__).relative_to(ROOT).as_posix()
    hits = [f"{name}:{i}" for name in files if name != me and (ROOT / name).exists()
            for i in monkeypatches((ROOT / name).read_text())]
    assert hits == []
