"""The package's shape (issue 15): data flows one way, and every function fits on a screen.

Read from the source with ``ast`` (nothing is imported): the import graph of
``src/mfnormal`` has no cycle, counting every import statement, those inside
functions too (a deferred import is still a dependency), except the ones under
``if __name__ == "__main__":`` (a module run as a program is not imported);
``report.py`` imports nothing of the package but image writing (it only writes
HTML); no function in ``src/`` is longer than ``MAX_FUNCTION_LINES``.
"""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "mfnormal"
MAX_FUNCTION_LINES = 90


def _is_main_guard(node) -> bool:
    return (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
            and isinstance(node.test.left, ast.Name) and node.test.left.id == "__name__")


def _imported_modules(path: Path, modules: set) -> set:
    """The package's modules that ``path`` imports (``from . import x``, ``from .x import y``,
    ``import mfnormal.x``, ``from mfnormal import x``)."""
    tree = ast.parse(path.read_text())
    skipped = {id(n) for guard in ast.walk(tree) if _is_main_guard(guard) for n in ast.walk(guard)}
    found = set()
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.ImportFrom):
            package = node.level == 1 or (node.level == 0 and (node.module or "").split(".")[0] == "mfnormal")
            if not package:
                continue
            module = (node.module or "").split(".")[1 if node.level == 0 else 0:]
            names = module[:1] if module and module[0] else [a.name for a in node.names]
            found.update(names)
        elif isinstance(node, ast.Import):
            found.update(a.name.split(".")[1] for a in node.names if a.name.startswith("mfnormal."))
    return found & modules - {path.stem}


def import_graph() -> dict:
    modules = {p.stem for p in PACKAGE.glob("*.py")}
    return {p.stem: _imported_modules(p, modules) for p in PACKAGE.glob("*.py")}


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
    assert {"cli", "compare", "report", "demo", "plugin"} <= set(graph)
    assert "report" in graph["compare"] and "demo" in graph["cli"]     # the graph sees real imports
    assert cycles(graph) == []


def test_the_report_only_writes_html():
    assert import_graph()["report"] <= {"images"}


def test_no_function_is_longer_than_a_screen():
    long = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                start = min([node.lineno] + [d.lineno for d in node.decorator_list])
                if node.end_lineno - start + 1 > MAX_FUNCTION_LINES:
                    long.append(f"{path.name}:{node.lineno} {node.name} ({node.end_lineno - start + 1} lines)")
    assert long == []
