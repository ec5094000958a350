"""The package's imports run one way: no cycle among ``rrtcolearn.*`` modules, counting
imports inside functions (a cycle deferred into a function is still a cycle)."""

from __future__ import annotations

import ast
from pathlib import Path

import rrtcolearn

ROOT = Path(rrtcolearn.__file__).parent


def import_graph() -> dict[str, set[str]]:
    """Module -> the ``rrtcolearn`` modules it imports anywhere in its source (ast)."""
    files = {}
    for path in ROOT.rglob("*.py"):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        files[".".join(parts)] = path
    graph: dict[str, set[str]] = {m: set() for m in files}
    for module, path in files.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                names = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            graph[module] |= {n for n in names if n in files and n != module}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a list of modules (first == last), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(v: str) -> list[str] | None:
        state[v] = 1
        path.append(v)
        for w in sorted(graph[v]):
            if state.get(w) == 1:
                return [*path[path.index(w):], w]
            if w not in state and (found := visit(w)):
                return found
        state[v] = 2
        path.pop()
        return None

    for v in sorted(graph):
        if v not in state and (found := visit(v)):
            return found
    return None


def test_the_graph_sees_function_level_imports():
    graph = import_graph()
    # runner imports the report at module level, the report the experiment's layout, and
    # the planner registry imports its peers inside its factories
    assert "rrtcolearn.experiment.report" in graph["rrtcolearn.experiment.runner"]
    assert "rrtcolearn.baselines.random_rrt" in graph["rrtcolearn.planners"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_no_import_cycle():
    assert find_cycle(import_graph()) is None


# the pipeline's modules in the order of docs/architecture.md's table
PIPELINE = ["configure", "layout", "model", "offline", "plans", "inspection"]


def test_the_pipeline_modules_import_down_their_table():
    """Each module of `rrtcolearn.pipeline` imports only those before it in its table (none
    the package itself, which re-exports them all), and every one is in the table."""
    graph = import_graph()
    package = "rrtcolearn.pipeline"
    assert {m.rpartition(".")[2] for m in graph if m.startswith(package + ".")} == set(PIPELINE)
    for k, name in enumerate(PIPELINE):
        used = {m.rpartition(".")[2] for m in graph[f"{package}.{name}"]
                if m == package or m.startswith(package + ".")}
        assert used <= set(PIPELINE[:k]), (name, used)
