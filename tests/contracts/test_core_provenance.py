"""Provenance (elastimap/provenance.py): the code version and the library versions, cheaply."""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys

import numpy as np

from elastimap.provenance import library_versions, stamp


def test_stamp_holds_code_and_library_versions():
    s = stamp()
    assert s["code_version"].startswith(importlib.metadata.version("elastimap"))
    v = s["versions"]
    assert set(v) == {"dolfinx", "petsc", "gmsh", "torch", "numpy"}
    assert v["numpy"] == np.__version__
    assert v["torch"] == importlib.metadata.version("torch")
    assert v["gmsh"] == importlib.metadata.version("gmsh")
    assert all(isinstance(x, str) and x[0].isdigit() for x in v.values()), v


def test_stamp_imports_no_heavy_library():
    code = (
        "import sys; from elastimap.provenance import stamp; stamp(); "
        "print(sorted(m for m in ('torch', 'dolfinx', 'petsc4py', 'gmsh', 'numpy') if m in sys.modules))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_versions_are_read_once():
    assert library_versions() is library_versions()
