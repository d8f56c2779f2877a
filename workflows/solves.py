"""Stored forward solves for the studies (finite-difference Jacobians, level bias, the frames
benchmark's worlds).

Each solve is kept once in the solve store (:class:`elastimap.dataset.store.SolveStore`) in the
folder ``cache``, keyed by the solve parameters, so reruns of the studies and of the tests cost
nothing.  :func:`fd_jacobian_solves` takes central-difference Jacobians from such solves, to check
the bounds of :mod:`elastimap.identify.bounds`.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable

import numpy as np

from elastimap.dataset.store import SolveStore, solver_label
from elastimap.solver.params import SolveParams

DEFAULT_CACHE = "data/identify/solves"
_STORES: dict = {}


def params_of(
    d: float,
    h: float,
    E: float,
    mesh: str,
    delta: float,
    nonlinearity: float,
    geometry: str = "remesh",
    sizing: str = "fixed",
):
    p = SolveParams().with_inclusion(d=float(d), h=float(h), E=float(E))
    return p.replace(
        disc=dataclasses.replace(p.disc, mesh=mesh, geometry=geometry, sizing=sizing),
        loading=dataclasses.replace(p.loading, delta=float(delta)),
        tissue=dataclasses.replace(p.tissue, nonlinearity=float(nonlinearity)),
    )


def _store(cache: str, solver: str):
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
    p = params_of(d, h, E, mesh, delta, nonlinearity, geometry, sizing)
    if reference is not None:
        if geometry != "morph":
            raise ValueError("reference= pins a morphed mesh: it needs geometry='morph'")
        if solver is None:
            solver = PinnedMorph(*reference)
    store = _store(cache, solver_label(solver))
    res = store.get(p, need_raw=True)
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


# d mm, h mm, ln E: large enough to beat remeshing noise; on the morphed map the 0.5 mm step's
# truncation error in dO2 is 0.3-0.6 % (docs/forward-model.md, derivative smoothness)
FD_STEP = np.array([0.5, 0.5, 0.1])


def fd_jacobian_solves(theta, mesh: str = "default", cache: str | None = None, geometry: str = "morph") -> dict:
    """Jacobians from 7 real (cached) forward solves, central differences with :data:`FD_STEP`.

    ``geometry="morph"`` (default) takes all 7 on the smooth morphed map, the reference mesh
    pinned at the centre's (:func:`elastimap.workflows.solves.morph_reference`), so the
    differences carry no remeshing jitter; ``"remesh"`` meshes each solve anew (the older maps).
    """
    d, h, E = (float(v) for v in theta)
    kw = {"mesh": mesh, "cache": cache or DEFAULT_CACHE, "geometry": geometry}
    if geometry == "morph":
        kw["reference"] = morph_reference(d, h)
    base = cached_solve(d, h, E, **kw)
    J = {"image": np.zeros((base["image"].size, 3)), "lnF": np.zeros((3, 3)), "dF": np.zeros(3)}
    for j in range(3):
        r = []
        for s in (+1, -1):
            p = np.array([d, h, np.log(E)])
            p[j] += s * FD_STEP[j]
            r.append(cached_solve(p[0], p[1], float(np.exp(p[2])), **kw))
        J["image"][:, j] = (r[0]["image"].ravel() - r[1]["image"].ravel()) / (2 * FD_STEP[j])
        J["lnF"][:, j] = (np.log(r[0]["O"]) - np.log(r[1]["O"])) / (2 * FD_STEP[j])
        f0 = r[0]["force"] - r[0]["force_ref"]
        f1 = r[1]["force"] - r[1]["force_ref"]
        J["dF"][j] = (f0 - f1) / (2 * FD_STEP[j])
    J["image0"] = base["image"].ravel()
    J["lnF0"] = np.log(base["O"])
    J["dF0"] = float(base["force"] - base["force_ref"])
    J["background"] = base["image_raw"] - base["image"]
    return J
