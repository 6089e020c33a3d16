"""The package's layering: the data flow io -> grid -> coarse / fine -> quality -> report, with
the stages, the pipeline and the command line on top, and no import that runs back up.

Read from the source's own import statements (those inside functions too), not by importing.
The size of its modules and functions is read the same way.
"""

from __future__ import annotations

import ast
from pathlib import Path

import tiereg

ROOT = Path(tiereg.__file__).parent

# the orchestration and the outputs: nothing below them may import them
TOP = ("cli", "cli_options", "pipeline", "stages", "report", "batch", "mosaic", "overlap",
       "demo", "calibrate", "distributed", "simulate")
# the kernels of the data flow, lowest first: each may import only those before it (and the
# small core of value types, which imports none of them). The grid (its GridSpec a value type
# that io writes as GeoTIFF) lies below io; reading, gridding and preparing the reference come
# before the coarse and fine stages, and their heights are measured (evaluate) after them
FLOW = ("grid", "io", "reference", "coarse", "fine", "evaluate")


def _component(path: Path) -> str:
    """The top-level module or sub-package a source file belongs to."""
    rel = path.relative_to(ROOT)
    return rel.parts[0].removesuffix(".py")


def _imports(path: Path) -> set[str]:
    """The top-level tiereg components a source file imports."""
    package = path.relative_to(ROOT).parent.parts
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the file's package
                base = list(package[: len(package) - (node.level - 1)])
                parts = base + (node.module.split(".") if node.module else [])
                if not parts:  # `from . import x`: the names are components
                    found.update(a.name for a in node.names)
                else:
                    found.add(parts[0])
            elif node.module and node.module.split(".")[0] == "tiereg":
                parts = node.module.split(".")
                found.add(parts[1] if len(parts) > 1 else "tiereg")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == "tiereg" and len(parts) > 1:
                    found.add(parts[1])
    return found


def _graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for path in ROOT.rglob("*.py"):
        if path.name == "__init__.py" and path.parent == ROOT:
            continue  # the public facade imports everything by design
        comp = _component(path)
        graph.setdefault(comp, set()).update(_imports(path) - {comp})
    return graph


def test_the_import_reader_sees_relative_absolute_and_nested_imports(tmp_path):
    """The reader itself, on a known file: it must find what each form of import names."""
    graph = _graph()
    assert "coarse" in graph["stages"] and "verdict" in graph["stages"]
    assert "pipeline" in graph["cli"]  # imported inside a function there
    assert "grid" in graph["coarse"]  # `from ..grid import` in a sub-package


def test_no_component_imports_one_above_it_and_there_is_no_cycle():
    graph = _graph()
    for low in FLOW + tuple(c for c in graph if c not in TOP and c not in FLOW):
        assert not graph.get(low, set()) & set(TOP), (
            f"{low} imports {sorted(graph[low] & set(TOP))}, which are above it")
    for i, low in enumerate(FLOW):
        above = set(FLOW[i + 1:])
        assert not graph.get(low, set()) & above, (
            f"{low} imports {sorted(graph[low] & above)}, later in the data flow")
    state: dict[str, int] = {}  # depth-first search: 1 on the path, 2 done

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                raise AssertionError("import cycle: " + " -> ".join(path + [node, nxt]))
            if nxt in graph and state.get(nxt) is None:
                visit(nxt, path + [node])
        state[node] = 2

    for node in sorted(graph):
        if state.get(node) is None:
            visit(node, [])


def test_the_report_measures_heights_without_registering_again():
    """The report, a reader of RESULT.json, sits below the pipeline: it measures the heights at
    the poses it is given (evaluate) instead of calling register."""
    graph = _graph()
    assert "evaluate" in graph["report"]
    assert not graph["report"] & {"pipeline", "stages", "cli", "cli_options"}


MAX_FUNCTION_LINES = 80  # a function reads at one sitting
MAX_MODULE_LINES = 600  # a module holds one idea


def _sizes() -> tuple[dict[str, int], dict[str, int]]:
    """Lines of every module and of every function (methods and nested ones included)."""
    modules, functions = {}, {}
    for path in sorted(ROOT.rglob("*.py")):
        name = str(path.relative_to(ROOT))
        text = path.read_text()
        modules[name] = text.count("\n")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                functions[f"{name}:{node.name}"] = node.end_lineno - node.lineno + 1
    return modules, functions


def test_modules_and_functions_stay_readable():
    modules, functions = _sizes()
    assert "fine/solver.py:solve_helmert" in functions and "pipeline.py" in modules
    assert functions["pipeline.py:register"] > 10  # the reader measures what it should
    long_functions = {k: v for k, v in functions.items() if v > MAX_FUNCTION_LINES}
    long_modules = {k: v for k, v in modules.items() if v > MAX_MODULE_LINES}
    assert not long_functions, f"functions over {MAX_FUNCTION_LINES} lines: {long_functions}"
    assert not long_modules, f"modules over {MAX_MODULE_LINES} lines: {long_modules}"
