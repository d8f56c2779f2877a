"""The mesh levels' neighbours (``solver.params.finer`` / ``coarser``) and the solver's modules
importing one another without a cycle."""

import ast
from pathlib import Path

from elastimap.solver.params import MESH_LEVELS, coarser, finer

SOLVER = Path(__file__).resolve().parents[1] / "solver"


def test_finer_and_coarser_walk_the_levels():
    assert finer("coarse") == "default" and coarser("default") == "coarse"
    assert finer(MESH_LEVELS[-1]) is None and coarser(MESH_LEVELS[0]) is None
    for a, b in zip(MESH_LEVELS, MESH_LEVELS[1:]):
        assert finer(a) == b and coarser(b) == a


def _imports(path: Path) -> set[str]:
    """The solver modules ``path`` imports (relative or absolute, at any depth of the file)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level == 1:
                names = [mod] if mod else [a.name for a in node.names]
            elif mod.startswith("elastimap.solver."):
                names = [mod.removeprefix("elastimap.solver.")]
            else:
                continue
            out.update(n.split(".")[0] for n in names)
    return out


def test_solver_modules_import_without_a_cycle():
    graph = {p.stem: _imports(p) & {q.stem for q in SOLVER.glob("*.py")} for p in SOLVER.glob("*.py")}
    seen, stack = set(), []

    def visit(m):
        if m in stack:
            raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(m) :] + [m]))
        if m in seen:
            return
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            visit(n)
        stack.pop()
        seen.add(m)

    for m in sorted(graph):
        visit(m)
