"""Architecture of the installed package, checked on the source (AST only; nothing is imported).

Rooms are the folders at the repository top that install as ``elastimap.<room>``: ``solver``,
``dataset``, ``sweep``, ``training``, ``identify``, ``camera``, ``gap`` and ``workflows``
(``elastimap.workflows``, with the studies in ``elastimap.workflows.studies``).  The folder
``elastimap/`` holds two more nodes: the **core** (every module of ``elastimap/`` except the
umbrella: ``errors``, ``cli_util``, ``provenance``, ...) and the **umbrella** command
(``elastimap.cli``, ``elastimap.__main__``).

Allowed layering, bottom to top -- the README's data flow "geometry → solve → image → features →
Parquet → training → inference" with the diagnosis and the pipelines after it::

    core  <  solver  <  dataset  <  sweep  <  training  <  identify  <  camera  <  gap  <  workflows  <  umbrella

* a room imports only rooms *below* it (so the room graph has no cycle, and e.g. the solver never
  imports training, camera or gap; training never imports camera, gap or identify); every room may
  import the core;
* the core imports no room, except the lazy (function-level) imports listed in
  :data:`CORE_LAZY` (pure-data lookups such as the solver's mesh levels for the shared ``--mesh``
  choice);
* the umbrella imports rooms only lazily (inside functions, or by ``"module:attr"`` strings), so
  ``elastimap --help`` imports no stage; nothing imports the umbrella;
* no module imports another room's private name (``_name``, ``_module``), at any level;
* no bare room name is imported (``import solver``): the only installed top-level import name is
  ``elastimap``.

What counts as an import: ``import`` and ``from ... import`` statements anywhere in a module
(relative ones resolved to their installed names).  Imports by string (``importlib``,
``"module:attr"`` tables) are not seen.  ``tests/`` is not a room and is not checked.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
import textwrap
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: rooms in layering order, bottom first (the core below all, the umbrella above all)
LAYERS = ("solver", "dataset", "sweep", "training", "identify", "camera", "gap", "workflows")
CORE, UMBRELLA = "elastimap", "elastimap.cli"
UMBRELLA_MODULES = ("elastimap.cli", "elastimap.__main__")
#: (core module, imported module) pairs the core may import lazily
CORE_LAZY = {("elastimap.cli_util", "elastimap.solver.params")}


@dataclass(frozen=True)
class Imp:
    src: str  # importing module, installed name
    target: str  # imported module, installed name
    name: str  # the imported name for ``from X import name`` ('' for ``import X``)
    lazy: bool  # inside a function
    file: str
    line: int

    def where(self) -> str:
        return f"{self.file}:{self.line}"


def module_name(root: Path, path: Path) -> str:
    """Installed dotted name of a source file: ``solver/fem.py`` -> ``elastimap.solver.fem``."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts) if parts[0] == "elastimap" else ".".join(["elastimap", *parts])


def node_of(module: str) -> str | None:
    """Node of an installed module name: a room, the core, the umbrella, or None (not ours)."""
    parts = module.split(".")
    if parts[0] != "elastimap":
        return None
    if len(parts) > 1 and parts[1] in LAYERS:
        return parts[1]
    if any(module == u or module.startswith(u + ".") for u in UMBRELLA_MODULES):
        return UMBRELLA
    return CORE


def source_files(root: Path):
    for folder in (*LAYERS, "elastimap"):
        base = root / folder
        if base.is_dir():
            yield from sorted(p for p in base.rglob("*.py") if ".venv" not in p.parts)


def imports(root: Path) -> tuple[list[Imp], list[str]]:
    """Every import statement of the room folders under ``root``, and the bare room-name imports."""
    out, bare = [], []
    for path in source_files(root):
        mod = module_name(root, path)
        pkg = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        rel = path.relative_to(root).as_posix()
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=rel)
        lazy_nodes = set()
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                lazy_nodes.update(id(n) for n in ast.walk(fn) if n is not fn)
        for node in ast.walk(tree):
            lazy = id(node) in lazy_nodes
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] in LAYERS:
                        bare.append(f"{rel}:{node.lineno}: import {a.name}")
                    out.append(Imp(mod, a.name, "", lazy, rel, node.lineno))
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = pkg.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                    if target.split(".")[0] in LAYERS:
                        bare.append(f"{rel}:{node.lineno}: from {target} import ...")
                for a in node.names:
                    # ``from elastimap import solver`` / ``from elastimap.training import perf`` name modules too
                    sub = f"{target}.{a.name}"
                    t = sub if (node_of(target) == CORE and node_of(sub) not in (CORE, None)) else target
                    out.append(Imp(mod, t, a.name, lazy, rel, node.lineno))
    return out, bare


def violations(root: Path) -> dict[str, list[str]]:
    """Every rule of the module docstring broken under ``root``, by rule."""
    imps, bare = imports(root)
    rank = {CORE: -1, **{r: i for i, r in enumerate(LAYERS)}, UMBRELLA: len(LAYERS)}
    v: dict[str, list[str]] = {"layering": [], "core": [], "umbrella": [], "private": [], "bare": bare, "cycle": []}
    edges: dict[str, set[str]] = {}
    for i in imps:
        a, b = node_of(i.src), node_of(i.target)
        if b is None or a == b:
            continue
        # private: a module or a name starting with one underscore, taken from another node
        parts = i.target.split(".")[1:] + ([i.name] if i.name else [])
        if any(p.startswith("_") and not p.startswith("__") for p in parts):
            v["private"].append(f"{i.where()}: {i.src} imports {i.target}{'.' + i.name if i.name else ''}")
        if a == CORE:
            if not (i.lazy and (i.src, i.target) in CORE_LAZY):
                v["core"].append(
                    f"{i.where()}: core module {i.src} imports {i.target}{'' if i.lazy else ' at module level'}"
                )
            continue
        if a == UMBRELLA:
            if not i.lazy and b != CORE:
                v["umbrella"].append(f"{i.where()}: the umbrella imports {i.target} at module level (must be lazy)")
            continue
        edges.setdefault(a, set()).add(b)
        if b == UMBRELLA or rank[b] >= rank[a]:
            v["layering"].append(
                f"{i.where()}: {a} imports {b} ({i.target}); {b} is not below {a} in "
                + " < ".join((CORE, *LAYERS, UMBRELLA))
            )
    v["cycle"] = find_cycles(edges)
    return v


def find_cycles(edges: dict[str, set[str]]) -> list[str]:
    """Room-level cycles (depth-first search), each as 'a -> b -> a'."""
    found, state = [], {}

    def visit(n, path):
        state[n] = 1
        for m in sorted(edges.get(n, ())):
            if state.get(m) == 1:
                found.append(" -> ".join(path[path.index(m) :] + [m]))
            elif m not in state:
                visit(m, path + [m])
        state[n] = 2

    for n in sorted(edges):
        if n not in state:
            visit(n, [n])
    return found


# --------------------------------------------------------------------------- the repository
@pytest.fixture(scope="module")
def repo_violations():
    return violations(ROOT)


def test_the_checker_sees_the_rooms():
    imps, _ = imports(ROOT)
    seen = {(node_of(i.src), node_of(i.target)) for i in imps}
    # edges that exist today (if one disappears the checker may have gone blind, not the code clean)
    assert ("sweep", "solver") in seen and ("camera", "identify") in seen and ("identify", "training") in seen
    assert {node_of(i.src) for i in imps} >= set(LAYERS) - {"workflows"} | {CORE}


@pytest.mark.parametrize("rule", ["cycle", "layering", "core", "umbrella", "private", "bare"])
def test_repository_keeps_the_layering(repo_violations, rule):
    assert repo_violations[rule] == [], "\n".join(repo_violations[rule])


def test_only_elastimap_is_a_top_level_name(tmp_path):
    """pyproject installs packages under ``elastimap`` only, and from a neutral directory none of the
    room folders resolves as a top-level import (``elastimap`` does)."""
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert all(p == "elastimap" or p.startswith("elastimap.") for p in cfg["packages"])
    assert all(p == "elastimap" or p.startswith("elastimap.") for p in cfg.get("package-dir", {}))
    assert {"elastimap.workflows", "elastimap.workflows.studies"} <= set(cfg["packages"])
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"].get("scripts", {})
    assert all(t.startswith("elastimap.") for t in scripts.values())
    code = textwrap.dedent(f"""
        import importlib.util
        names = {list(LAYERS) + ["studies"]!r}
        found = [n for n in names if importlib.util.find_spec(n) is not None]
        assert importlib.util.find_spec("elastimap") is not None, "elastimap is not installed"
        assert importlib.util.find_spec("elastimap.workflows.studies.crbmap") is not None
        print(",".join(found))
    """)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "", f"installed top-level names besides elastimap: {r.stdout.strip()}"


# --------------------------------------------------------------------------- the checker fails when it should
def _fake_repo(tmp_path: Path, files: dict[str, str]) -> Path:
    base = {
        "elastimap/__init__.py": "",
        "elastimap/errors.py": "class UserError(Exception): ...\n",
        "solver/__init__.py": "",
        "solver/params.py": "from elastimap.errors import UserError\n",
        "training/__init__.py": "",
        "training/perf.py": "def set_threads(n): ...\n",
        "training/_perf.py": "def tune(): ...\n",
        "camera/__init__.py": "",
        "camera/infer.py": "from elastimap.training.perf import set_threads\n",
        "elastimap/cli.py": "def main():\n    from elastimap.camera.infer import set_threads\n",
    }
    for rel, text in {**base, **files}.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return tmp_path


def test_checker_passes_a_clean_fake_repo(tmp_path):
    v = violations(_fake_repo(tmp_path, {}))
    assert all(x == [] for x in v.values()), v


@pytest.mark.parametrize(
    "files,rule,needle",
    [
        ({"solver/api.py": "def f():\n    from elastimap.camera import infer\n"}, "layering", "solver imports camera"),
        (
            {
                "solver/api.py": "from elastimap.camera.infer import set_threads\n",
                "camera/y.py": "from elastimap.solver.params import UserError\n",
            },
            "cycle",
            "camera -> solver -> camera",
        ),
        ({"training/net.py": "from ..camera.infer import set_threads\n"}, "layering", "training imports camera"),
        ({"camera/x.py": "from elastimap.training._perf import tune\n"}, "private", "_perf"),
        ({"camera/x.py": "from elastimap.training.perf import _helper\n"}, "private", "_helper"),
        ({"camera/x.py": "from elastimap.training import _perf\n"}, "private", "_perf"),
        ({"camera/x.py": "import training.perf\n"}, "bare", "import training.perf"),
        ({"camera/x.py": "from solver.params import X\n"}, "bare", "from solver.params"),
        ({"elastimap/cli.py": "from elastimap.camera.infer import set_threads\n"}, "umbrella", "module level"),
        ({"elastimap/cli_util.py": "def f():\n    from elastimap.training import perf\n"}, "core", "training"),
        ({"camera/x.py": "from elastimap.cli import main\n"}, "layering", "camera imports elastimap.cli"),
    ],
)
def test_checker_catches_a_violation(tmp_path, files, rule, needle):
    v = violations(_fake_repo(tmp_path, files))
    assert any(needle in line for line in v[rule]), v


def test_private_names_inside_one_room_are_fine(tmp_path):
    v = violations(
        _fake_repo(tmp_path, {"training/cli.py": "from ._perf import tune\nfrom .perf import set_threads\n"})
    )
    assert v["private"] == [] and v["layering"] == []
