"""Process set-up that must happen before DOLFINx, PETSc or mpi4py are imported.

Every module of ``solver`` that touches DOLFINx imports this module first.

* The DOLFINx wheel's guard (``dolfinx_solver``'s ``bootstrap``, :func:`_guard`) checks the
  environment and imports ``mpi4py.MPI`` first, which makes the wheel's bundled MPI/PETSc
  libraries loadable (without it dolfinx fails with ``libmpi.so.12`` not found).
* One solve runs on one core: OpenMP/BLAS threads are pinned to 1 so that
  parallel sweep workers do not oversubscribe the machine (:mod:`._threads`).
* PETSc is initialised on ``MPI.COMM_SELF`` so that independent worker
  processes (dask, mpi4py.futures) never wait on each other.
* UCX, the network layer the wheel's MPICH loads with ``mpi4py.MPI``, is told not to hook the
  process's memory calls (``UCX_MEM_EVENTS=no`` where the environment does not set it): the hooks
  (binary patches of mmap/munmap/brk installed when the library loads) exist to keep a cache of
  RDMA memory registrations valid, and a process here communicates with no other (every
  communicator is ``COMM_SELF``); without them UCX registers memory uncached.  Loading
  ``mpi4py.MPI`` then costs 0.01 instead of 0.03-0.05 s of CPU (docs/forward-model.md, 'Speed').
* The DOLFINx JIT cache is checked for the poison left by a process killed
  mid-compile (a ``.c`` file without its ``.c.cached`` marker), which makes
  every later compile of that form time out; such leftovers are removed.
"""

from __future__ import annotations

import os
import sys

from . import _threads  # noqa: F401  (OpenMP/BLAS threads pinned to 1)

os.environ.setdefault("UCX_MEM_EVENTS", "no")  # read when mpi4py.MPI loads UCX (module docstring)


def _distribution_names() -> list[str]:
    """The normalised names of the installed distributions, from the names of their metadata
    folders on ``sys.path`` (``NAME-VERSION.dist-info``, ``NAME[-VERSION...].egg-info``: installers
    write the normalised name there, the packaging spec's 'Recording installed projects'), as
    ``importlib.metadata`` finds them, without parsing every ``METADATA`` file."""
    import re

    names = []
    for entry in sys.path:
        try:
            items = os.scandir(entry or ".")
        except OSError:  # a zip file, a missing folder
            continue
        with items:
            for item in items:
                if item.name.endswith((".dist-info", ".egg-info")) and item.is_dir():
                    stem = item.name.rsplit(".", 1)[0].partition("-")[0]
                    names.append(re.sub(r"[-_.]+", "-", stem).lower())
    return names


def _guard():
    """The DOLFINx wheel's environment guard, :func:`dolfinx_solver._bootstrap.bootstrap` (it
    refuses both scalar variants installed together, a PETSc/SLEPc distribution beside the wheel, a
    foreign petsc4py on the path; then imports ``mpi4py.MPI`` ahead of every compiled module), run
    from the wheel's own file with the installed distributions' names read from their folder names
    (:func:`_distribution_names`; the guard takes that list as an argument, its checks and messages
    unchanged).  Its default reads them by parsing the ``METADATA`` file of every installed
    distribution: 0.02-0.05 s more CPU in a `solve` process (docs/forward-model.md, 'Speed').
    Where the wheel's layout differs from the one read here, ``import dolfinx_solver`` runs the
    guard as it ships."""
    import importlib.util

    try:
        spec = importlib.util.find_spec("dolfinx_solver")  # finds the package, runs nothing
        path = os.path.join(spec.submodule_search_locations[0], "_bootstrap.py")
        boot_spec = importlib.util.spec_from_file_location("_elastimap_dolfinx_guard", path)
        module = importlib.util.module_from_spec(boot_spec)
        boot_spec.loader.exec_module(module)  # plain Python: importlib, re, pathlib
        bootstrap = module.bootstrap
    except Exception:  # not the layout read here: the guard as the wheel runs it
        bootstrap = None
    if bootstrap is None:
        import dolfinx_solver  # noqa: F401

        return
    bootstrap(installed_distribution_names=_distribution_names)


_guard()  # must precede dolfinx / petsc4py / mpi4py

import petsc4py  # noqa: E402
from mpi4py import MPI  # noqa: E402

petsc4py.init(comm=MPI.COMM_SELF)


def jit_cache_dir() -> str:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "fenics")


def clean_jit_cache(max_age_s: float = 120.0) -> list[str]:
    """Remove half-written JIT sources (``*.c`` with no ``*.c.cached`` marker).

    Only files older than ``max_age_s`` are removed, so a compile that is
    running right now in another process is left alone.  Returns the paths
    removed.
    """
    import glob
    import time

    removed = []
    now = time.time()
    for src in glob.glob(os.path.join(jit_cache_dir(), "*.c")):
        if os.path.exists(src + ".cached"):
            continue
        try:
            if now - os.path.getmtime(src) < max_age_s:
                continue
            stem = src[:-2]
            for path in glob.glob(stem + "*"):
                os.remove(path)
                removed.append(path)
        except OSError:
            pass
    return removed


clean_jit_cache()
