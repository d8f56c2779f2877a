"""One vocabulary: the feature/target names, their units, the design box and the default slab
thickness are defined once (``elastimap.dataset.schema``, with the solver's own defaults in
``elastimap.solver.params``, whose slab thickness is the paper's sensor's, ``elastimap/sensor.py``)
and every room imports them."""

import ast
import subprocess
import sys
from pathlib import Path

from elastimap.dataset import schema

ROOT = Path(__file__).resolve().parents[2]
ROOMS = ("elastimap", "solver", "sweep", "dataset", "training", "camera", "gap", "identify", "workflows")
HOME = {
    "FEATURES": "dataset/schema.py",
    "TARGETS": "dataset/schema.py",
    "UNITS": "dataset/schema.py",
    "THICKNESS": "solver/params.py",
    "DESIGN_BOX": "solver/params.py",
    "PHANTOMS_CSV": "dataset/schema.py",
}


def _sources():
    for room in ROOMS:
        for path in sorted((ROOT / room).rglob("*.py")):
            yield path.relative_to(ROOT).as_posix(), ast.parse(path.read_text(encoding="utf-8"))


def _literal(node):
    try:
        return ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        return None


def test_vocabulary_is_defined_once():
    thick = schema.THICKNESS
    found = []
    for rel, tree in _sources():
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign):
                value = _literal(node.value)
                for t in node.targets:
                    # (UNITS is checked by value: camera/features.py has the camera's own units)
                    if isinstance(t, ast.Name) and t.id in HOME and t.id != "UNITS" and HOME[t.id] != rel:
                        found.append(f"{rel}:{node.lineno} defines {t.id}")
                if value in (schema.FEATURES, schema.TARGETS) and rel != HOME["TARGETS"]:
                    found.append(f"{rel}:{node.lineno} spells out {value}")
                if (
                    isinstance(value, dict)
                    and value
                    and rel != HOME["UNITS"]
                    and all(
                        k in schema.UNITS and str(u).replace("²", "^2") == schema.UNITS[k] for k, u in value.items()
                    )
                ):
                    found.append(f"{rel}:{node.lineno} spells out the units {value}")
            # a parameter or field named like the slab thickness with a literal default
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                args = node.args.args + node.args.kwonlyargs
                defaults = (
                    [None] * (len(node.args.args) - len(node.args.defaults))
                    + node.args.defaults
                    + node.args.kw_defaults
                )
                for a, d in zip(args, defaults):
                    if d is not None and "thick" in a.arg and "skin" not in a.arg and _literal(d) == thick:
                        found.append(f"{rel}:{node.lineno} default {a.arg}={thick}")
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.value is not None:
                # the paper's sensor (elastimap/sensor.py) is where the slab's 20 mm is defined
                if node.target.id == "thickness" and _literal(node.value) == thick and rel != "elastimap/sensor.py":
                    found.append(f"{rel}:{node.lineno} field thickness = {thick}")
    assert not found, "\n".join(found)


def test_vocabulary_values_and_units():
    assert schema.FEATURES == ("O1", "O2", "O3") and schema.TARGETS == ("d", "h", "E")
    assert schema.UNITS == {"O1": "mm", "O2": "mm", "O3": "mm^2", "d": "mm", "h": "mm", "E": "kPa"}
    assert schema.THICKNESS == 20.0 and schema.DESIGN_BOX == {"d": (2.0, 15.0), "E": (10.0, 200.0)}
    from elastimap.solver.params import Tissue, depth_range
    from elastimap.sweep.design import DEFAULT_RANGES

    assert Tissue().thickness == schema.THICKNESS and schema.depth_range is depth_range
    assert DEFAULT_RANGES == "d=2:15,h=auto,E=10:200:log"


def test_schema_imports_nothing_heavy():
    code = (
        "import sys, elastimap.dataset.schema; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'dolfinx', 'torch', 'gmsh', 'petsc4py', 'ufl'}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
