"""Provenance stamps: code version, library versions and host, recorded with every output.

:func:`stamp` is the one record every output that holds results writes (sweep manifest, model,
calibration, diagnosis, infer output): the code version and the versions of the libraries that
make the numbers, read from the installed metadata (nothing heavy is imported: importing DOLFINx
or torch alone takes seconds).
"""

from __future__ import annotations

import functools
import importlib.metadata
import importlib.util
import os
import re
import socket
import subprocess

from . import __version__


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """Package version plus the git commit (and ``+dirty``) when run from a checkout."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        sha = subprocess.run(
            ["git", "-C", here, "rev-parse", "--short=12", "HEAD"], capture_output=True, text=True, timeout=5
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", here, "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        sha, dirty = "", ""
    if not sha:
        return __version__
    return f"{__version__}+g{sha}{'.dirty' if dirty else ''}"


def host() -> str:
    return socket.gethostname()


#: the libraries whose versions make the numbers: (label, distribution names to try, module name)
LIBRARIES = (
    ("dolfinx", ("fenics-dolfinx", "dolfinx-solver-real", "dolfinx-solver-complex"), "dolfinx"),
    ("petsc", ("petsc4py",), "petsc4py"),
    ("gmsh", ("gmsh",), "gmsh"),
    ("torch", ("torch",), "torch"),
    ("numpy", ("numpy",), "numpy"),
)


def _module_version(module: str) -> str | None:
    """``__version__ = "..."`` read from a module's source without importing it (bundled packages
    such as the petsc4py inside the DOLFINx wheel have no metadata of their own)."""
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin or not os.path.isfile(spec.origin):
        return None
    try:
        with open(spec.origin, encoding="utf-8") as fh:
            m = re.search(r"^__version__\s*=\s*['\"]([^'\"]+)['\"]", fh.read(), re.MULTILINE)
    except (OSError, UnicodeDecodeError):
        return None
    return m.group(1) if m else None


@functools.lru_cache(maxsize=1)
def library_versions() -> dict[str, str | None]:
    """Installed versions of DOLFINx, PETSc (petsc4py), gmsh, torch and numpy; None when absent.

    The module's own ``__version__`` comes first (what is imported is what ran; a wheel can bundle
    a library without its metadata), the distribution's metadata second.
    """
    out: dict[str, str | None] = {}
    for label, dists, module in LIBRARIES:
        version = _module_version(module)
        for dist in dists:
            if version:
                break
            try:
                version = importlib.metadata.version(dist)
            except importlib.metadata.PackageNotFoundError:
                pass
        out[label] = version
    return out


def stamp() -> dict:
    """The provenance every output records: ``{"code_version": ..., "versions": {...}}``."""
    return {"code_version": code_version(), "versions": library_versions()}
