"""One solve runs on one core: OpenMP and BLAS threads are pinned to 1 (where the environment does
not say otherwise), so that parallel sweep workers do not oversubscribe the machine.

The variables are read when a library loads its thread pool, so this module is imported before
numpy or DOLFINx where a process is going to solve: by :mod:`elastimap.solver.api` (a `solve`
process imports numpy first there; numpy's OpenBLAS otherwise starts a thread per core, whose
spinning cost a `solve` process about 0.03 s of CPU; docs/forward-model.md, 'Speed') and by
:mod:`elastimap.solver._boot` (before DOLFINx and PETSc).  A process that loaded numpy before
keeps numpy's threads; the libraries loaded later are pinned.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
