"""A fake solver for tests and dry runs: ``ELASTIMAP_SWEEP_SOLVER=elastimap.sweep.testing``.

It has the solver module's interface (``solve``, ``warmup``) and returns a
:class:`elastimap.solver.params.SolveResult` with a smooth analytic difference image
(a Gaussian bump whose height grows with d and E and falls with h), so the
sweep, the dataset tools and the plots can be exercised without DOLFINx.

Environment knobs (all optional):

* ``ELASTIMAP_FAKE_SECONDS``  seconds each solve sleeps (default 0.02)
* ``ELASTIMAP_FAKE_CRASH``    ``d=VALUE``: the process dies with SIGSEGV when the
  inclusion diameter equals VALUE (a hard crash, as a segfaulting solver would)
* ``ELASTIMAP_FAKE_FAIL``     ``d=VALUE``: raise :class:`FakeSolverError` instead
* ``ELASTIMAP_FAKE_HANG``     ``d=VALUE``: sleep for an hour (a hung solve)
* ``ELASTIMAP_FAKE_LOG``      a file that gets one line ``d h E pid`` per solve started
"""

from __future__ import annotations

import ctypes
import os
import time

import numpy as np

from elastimap.solver.image import features
from elastimap.solver.params import SolveParams, SolveResult


class FakeSolverError(RuntimeError):
    pass


def _match(env: str, d: float) -> bool:
    spec = os.environ.get(env, "")
    if not spec.startswith("d="):
        return False
    return any(abs(d - float(v)) < 1e-9 for v in spec[2:].split("|") if v)


def warmup(params: SolveParams) -> None:
    return None


def solve(params: SolveParams) -> SolveResult:
    p = params.validate()
    inc = p.inclusion
    log = os.environ.get("ELASTIMAP_FAKE_LOG")
    if log:
        fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        os.write(fd, f"{inc.d:g} {inc.h:g} {inc.E:g} {os.getpid()}\n".encode())
        os.close(fd)
    t0 = time.perf_counter()
    time.sleep(float(os.environ.get("ELASTIMAP_FAKE_SECONDS", "0.02")))
    if _match("ELASTIMAP_FAKE_CRASH", inc.d):
        ctypes.string_at(0)  # SIGSEGV
    if _match("ELASTIMAP_FAKE_HANG", inc.d):
        time.sleep(3600)
    if _match("ELASTIMAP_FAKE_FAIL", inc.d):
        raise FakeSolverError(f"fake divergence for d={inc.d:g} mm, h={inc.h:g} mm, E={inc.E:g} kPa")
    n = int(round(p.probe.size / p.image.pixel))
    c = -p.probe.size / 2 + p.image.pixel * (np.arange(n) + 0.5)
    x, y = np.meshgrid(c, c)
    ratio = inc.E / p.tissue.E
    amp = 0.02 * (inc.d / 8.0) ** 2 * (ratio / (ratio + 4.0)) * np.exp(-(inc.h - inc.d / 2) / 6.0)
    sigma = 0.6 * inc.d + 0.4 * inc.h
    img = amp * np.exp(-(x ** 2 + y ** 2) / (2 * sigma ** 2))
    o1, o2, o3 = features(img, p.image.pixel, p.image.threshold, p.image.supersample)
    force_ref = 40.0 * p.tissue.E * p.loading.delta
    return SolveResult(params=p, O1=o1, O2=o2, O3=o3, force=force_ref * (1 + 10 * amp), force_ref=force_ref,
                       delta=p.loading.delta, image=img, image_raw=img + p.loading.delta / 3, pixel=p.image.pixel,
                       ndofs=1000, ncells=500, newton_iterations=2, seconds=time.perf_counter() - t0,
                       timings={}, peak_memory_mb=100.0)
