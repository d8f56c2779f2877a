"""Stored forward solves for the local study (finite-difference checks, indentation check).

Each solve is kept once in the solve store (:class:`elastimap.dataset.store.SolveStore`) in the
folder ``cache``, keyed by the solve parameters, so reruns of the study and of the tests cost
nothing.  Files of the older per-solve cache (``<cache>/<hash>.npz``) are still read.  Only this
module runs solves.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Callable

import numpy as np

DEFAULT_CACHE = "data/identify/solves"
_STORES: dict = {}


def _params(
    d: float,
    h: float,
    E: float,
    mesh: str,
    delta: float,
    nonlinearity: float,
    geometry: str = "remesh",
    sizing: str = "fixed",
):
    from elastimap.solver.params import SolveParams

    p = SolveParams().with_inclusion(d=float(d), h=float(h), E=float(E))
    return p.replace(
        disc=dataclasses.replace(p.disc, mesh=mesh, geometry=geometry, sizing=sizing),
        loading=dataclasses.replace(p.loading, delta=float(delta)),
        tissue=dataclasses.replace(p.tissue, nonlinearity=float(nonlinearity)),
    )


def _legacy_npz(cache: str, p) -> str:
    """Path of the solve in the per-solve npz cache this store replaced."""
    key = hashlib.sha256(json.dumps(p.to_dict(), sort_keys=True).encode()).hexdigest()[:20]
    return os.path.join(cache, key + ".npz")


def _store(cache: str, solver: str):
    from elastimap.dataset.store import SolveStore

    k = (os.path.abspath(cache), solver)
    if k not in _STORES:  # one per folder and process: its index is reused across calls
        _STORES[k] = SolveStore(cache, solver=solver)
    return _STORES[k]


class PinnedMorph:
    """The morphed forward map with its reference mesh pinned at (d₀, h₀) (mm), as a solve function.

    Central differences around a point must not cross from one reference mesh to another (the
    result jumps there by the discretisation error, :mod:`elastimap.solver.morph`), so a
    finite-difference stencil pins the reference of its centre.  ``solver_name`` names the
    reference: the solve store keeps these solves apart from the bins' own (same parameters,
    another mesh).
    """

    def __init__(self, d0: float, h0: float):
        from elastimap.solver.morph import Reference

        self.reference = Reference(float(d0), float(h0))
        self.solver_name = f"fem-morph@{float(d0):.9g},{float(h0):.9g}"

    def __call__(self, p):
        from elastimap.solver.morph import shared_forward

        inc = p.inclusion
        return shared_forward(p).solve(inc.d, inc.h, inc.E, reference=self.reference)


def morph_reference(d: float, h: float) -> tuple[float, float]:
    """(d₀, h₀) of the reference mesh that the morphed map uses at (d, h) unpinned."""
    from elastimap.solver.morph import reference_for

    r = reference_for(float(d), float(h))
    return r.d0, r.h0


def cached_solve(
    d: float,
    h: float,
    E: float,
    *,
    mesh: str = "default",
    delta: float = 3.0,
    nonlinearity: float = 0.0,
    cache: str = DEFAULT_CACHE,
    solver: Callable | None = None,
    geometry: str = "remesh",
    reference: tuple[float, float] | None = None,
    sizing: str = "fixed",
) -> dict:
    """One forward solve (tied interface, quarter model) -> dict of image, image_raw, features, force.

    ``solver``: the solve function (default the forward model; tests pass the SYNTHETIC stand-in,
    whose solves the store keeps apart).  ``geometry``: ``"remesh"`` (gmsh mesh at (d, h)) or
    ``"morph"`` (:mod:`elastimap.solver.morph`); with ``"morph"``, ``reference=(d0, h0)`` pins the
    reference mesh (:class:`PinnedMorph`).  ``sizing``: how the element size near the inclusion is
    chosen (``"fixed"`` or ``"by_d"``, :class:`elastimap.solver.params.Discretisation`).  Images come as stored (float32 values, as float64 arrays).
    """
    from elastimap.dataset.store import solver_label

    p = _params(d, h, E, mesh, delta, nonlinearity, geometry, sizing)
    if reference is not None:
        if geometry != "morph":
            raise ValueError("reference= pins a morphed mesh: it needs geometry='morph'")
        if solver is None:
            solver = PinnedMorph(*reference)
    store = _store(cache, solver_label(solver))
    res = store.get(p, need_raw=True)
    if res is None and solver is None and os.path.exists(_legacy_npz(cache, p)):
        z = np.load(_legacy_npz(cache, p))
        return {k: z[k] for k in z.files}
    if res is None:
        res = store.solve(p, solver, need_raw=True)
    return {
        "image": np.asarray(res.image, np.float64),
        "image_raw": np.asarray(res.image_raw, np.float64),
        "O": np.array([res.O1, res.O2, res.O3]),
        "force": np.array(res.force),
        "force_ref": np.array(res.force_ref),
        "theta": np.array([d, h, E]),
        "delta": np.array(res.delta),
        "seconds": np.array(res.seconds),
    }
