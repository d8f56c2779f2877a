"""The core (``elastimap/`` without the umbrella) has no module-level import cycle, lazy imports included.

``tests/contracts/test_architecture.py`` checks cycles between rooms; this checks the modules inside the core,
where ``errors`` <-> ``constraints`` used to import each other (the lazy import hid it from the room graph).
"""

from __future__ import annotations

import ast
from pathlib import Path

CORE = Path(__file__).resolve().parents[2] / "elastimap"


def core_imports() -> dict[str, set[str]]:
    """``module -> core modules it imports`` (any level, relative or absolute), by module file name."""
    names = {p.stem for p in CORE.glob("*.py")} - {"__init__", "__main__", "cli"}
    edges: dict[str, set[str]] = {}
    for n in names:
        tree = ast.parse((CORE / f"{n}.py").read_text(encoding="utf-8"))
        out = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                mod = node.module or ""
                if node.level == 1 or mod.startswith("elastimap"):
                    parts = mod.removeprefix("elastimap").lstrip(".").split(".")
                    out |= {parts[0]} & names if parts[0] else {a.name for a in node.names} & names
            elif isinstance(node, ast.Import):
                out |= {a.name.split(".")[1] for a in node.names if a.name.startswith("elastimap.")} & names
        edges[n] = out - {n}
    return edges


def test_core_modules_import_no_cycle():
    edges = core_imports()
    assert "constraints" in edges["cli_util"] or "errors" in edges["cli_util"]  # the checker sees imports
    state: dict[str, int] = {}
    cycles = []

    def visit(n, path):
        state[n] = 1
        for m in sorted(edges[n]):
            if state.get(m) == 1:
                cycles.append(" -> ".join(path[path.index(m) :] + [m]))
            elif m not in state:
                visit(m, path + [m])
        state[n] = 2

    for n in sorted(edges):
        if n not in state:
            visit(n, [n])
    assert cycles == []


def test_errors_imports_nothing_of_the_package():
    assert core_imports()["errors"] == set()
