"""Process set-up that must happen before DOLFINx, PETSc or mpi4py are imported.

Every module of ``solver`` that touches DOLFINx imports this module first.

* ``import dolfinx_solver`` makes the wheel's bundled MPI/PETSc libraries
  loadable (without it dolfinx fails with ``libmpi.so.12`` not found).
* One solve runs on one core: OpenMP/BLAS threads are pinned to 1 so that
  parallel sweep workers do not oversubscribe the machine.
* PETSc is initialised on ``MPI.COMM_SELF`` so that independent worker
  processes (dask, mpi4py.futures) never wait on each other.
* The DOLFINx JIT cache is checked for the poison left by a process killed
  mid-compile (a ``.c`` file without its ``.c.cached`` marker), which makes
  every later compile of that form time out; such leftovers are removed.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import dolfinx_solver  # noqa: E402,F401  (must precede dolfinx / petsc4py / mpi4py)
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
