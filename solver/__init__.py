"""Forward model: parametric geometry, DOLFINx contact solve, elasticity image.

``from elastimap.solver import solve, warmup, SolveParams`` — DOLFINx is imported only
when a solve runs, so ``elastimap.solver.params``, ``elastimap.solver.image`` and
``elastimap.solver.errors`` stay light.
"""

from .errors import SolverError
from .params import Discretisation, ImageSpec, Inclusion, Loading, Probe, SolveParams, SolveResult, Tissue, depth_range

__all__ = [
    "solve",
    "warmup",
    "SolverError",
    "SolveParams",
    "SolveResult",
    "Inclusion",
    "Tissue",
    "Probe",
    "Loading",
    "Discretisation",
    "ImageSpec",
    "depth_range",
]


def __getattr__(name):
    if name in ("solve", "warmup"):
        from . import api

        return getattr(api, name)
    raise AttributeError(name)
