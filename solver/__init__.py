"""Forward model: parametric geometry, DOLFINx contact solve, elasticity image.

``from solver import solve, warmup, SolveParams`` — DOLFINx is imported only
when a solve runs, so ``elastimap.solver.params`` and ``elastimap.solver.image`` stay light.
"""

from .params import (Discretisation, ImageSpec, Inclusion, Loading, Probe, SolveParams, SolveResult,
                     Tissue, depth_range)

__all__ = ["solve", "warmup", "SolverError", "SolveParams", "SolveResult", "Inclusion", "Tissue", "Probe",
           "Loading", "Discretisation", "ImageSpec", "depth_range"]


def __getattr__(name):
    if name in ("solve", "warmup"):
        from . import api
        return getattr(api, name)
    if name == "SolverError":
        from .fem import SolverError
        return SolverError
    raise AttributeError(name)
