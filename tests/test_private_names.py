"""No module uses another module's private names: a module that needs another's internals
gets a public function or method instead (docs/architecture.md).

The rule, checked on the source with `ast` (no import):
- attribute access ``obj._name`` (not a dunder) where ``obj`` is not ``self`` or ``cls`` is
  an error unless ``_name`` is defined in the same module (a function, class, assignment,
  attribute assignment, argument or import of that name): ``planner._shoot_edge(...)`` in
  improve/goal.py is one, ``other._size`` inside the class that assigns ``self._size`` is not;
- in the planning package, ``from ... import _name`` is an error too.
Tests may still reach into private names (e.g. a compiled kernel's signatures).
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).parents[1] / "src" / "rrtcolearn"


def _own_names(tree: ast.AST) -> set[str]:
    own = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            own.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            own.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            own.add(node.attr)
        elif isinstance(node, ast.arg):
            own.add(node.arg)
        elif isinstance(node, ast.alias):
            own.add(node.asname or node.name.split(".")[-1])
    return own


def private_uses(source: str, planning: bool = False) -> list[tuple[int, str]]:
    """(line, expression) of each use of another module's private name in ``source``."""
    tree = ast.parse(source)
    own = _own_names(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") \
                and not node.attr.startswith("__") \
                and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")) \
                and node.attr not in own:
            found.append((node.lineno, ast.unparse(node)))
        elif planning and isinstance(node, ast.ImportFrom):
            found.extend((node.lineno, f"import {a.name}") for a in node.names
                         if a.name.startswith("_") and not a.name.startswith("__"))
    return sorted(found)


def test_the_rule_catches_a_friend_module():
    friend = ("def shortcut(planner):\n"
              "    return planner._shoot_edge(1) + planner.model._cache\n")
    assert private_uses(friend) == [(2, "planner._shoot_edge"), (2, "planner.model._cache")]
    own = ("class A:\n"
           "    def __init__(self):\n        self._size = 0\n"
           "    def merge(self, other):\n        return self._size + other._size\n")
    assert private_uses(own) == []
    assert private_uses("from rrtcolearn.planning.rrt import _grown\n", planning=True) \
        == [(1, "import _grown")]


def test_no_module_uses_another_modules_private_names():
    bad = []
    for path in sorted(SRC.rglob("*.py")):
        planning = path.parent.name == "planning"
        bad += [f"{path.relative_to(SRC.parent)}:{line}: {expr}"
                for line, expr in private_uses(path.read_text(), planning)]
    assert bad == []
