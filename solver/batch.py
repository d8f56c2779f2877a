"""``solve_batch(params_list)``: many samples, one mesh and one model per geometry.

A sample (:func:`elastimap.solver.api.solve`) spends part of its time on things that only the
geometry decides: the gmsh mesh, the DOLFINx mesh and space, the node sets, the interface pairs,
the image sampler, the compiled forms and the sparsity pattern.  Samples that differ only in
the **moduli** (tissue E, skin E, inclusion E, the probe layers' E), the **Poisson ratios** (ν of
tissue, inclusion, probe) and the **plate travel** (δ or force, the plate's tilt) share all of that.  The stiffness
form a(u, v) = ∫ σ(u) : ε(v) dx reads E and ν from cell-wise (DG0) functions, so a new
material only refills those functions before the next assembly
(:meth:`elastimap.solver.fem.Model.set_params`); the sparsity pattern, the reduction P and the
symbolic LU factorisation stay.

``solve_batch`` groups the parameters by :func:`geometry_key`, builds each group's mesh and
:class:`~elastimap.solver.fem.Model` once, and runs every variant of the group on it (both
solves of each variant: with the inclusion and the reference).  The numbers are those of
``solve`` (the same mesh; equal within the solves' tolerances: a variant's presses run by CG on
the factors of the one before, a single sample's inclusion press as the difference of its two
presses to 1e-6 of that difference, docs/forward-model.md "Shared presses"; tested to 1e-6).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence

from .params import SolveParams, SolveResult

#: the solve parameters a variant may change without a new mesh or model
MATERIAL_FIELDS = {
    "tissue": ("E", "nu", "skin_E"),
    "inclusion": ("E", "nu"),
    "probe": ("nu",),
    "loading": ("delta", "force", "tilt"),
}


def geometry_key(p: SolveParams) -> str:
    """What decides the mesh and the model: every parameter except moduli, ν and plate travel
    (the probe layers keep their thicknesses, lose their moduli)."""
    d = p.to_dict()
    for part, names in MATERIAL_FIELDS.items():
        for n in names:
            d[part].pop(n, None)
    d["probe"]["layers"] = [float(t) for t, _E in p.probe.layers]
    return json.dumps(d, sort_keys=True)


def inclusion_modulus_only(a: SolveParams, b: SolveParams) -> bool:
    """Whether ``b`` differs from ``a`` by the inclusion's modulus alone (then both have the same
    reference press: the inclusion's modulus set to the tissue's).  Never for a core/shell inclusion,
    whose core's share of a modulus change depends on E (``materials.core_weight``)."""
    return a.with_inclusion(E=b.inclusion.E) == b and a.inclusion.core == 0


def group_by_geometry(params_list: Sequence[SolveParams]) -> list[list[int]]:
    """Indices of ``params_list`` grouped by :func:`geometry_key` (first-seen order)."""
    groups: dict[str, list[int]] = {}
    for i, p in enumerate(params_list):
        groups.setdefault(geometry_key(p), []).append(i)
    return list(groups.values())


def solve_group(
    params_list: Sequence[SolveParams],
    on_result: Callable[[int, SolveResult | Exception], None] | None = None,
    errors: str = "raise",
    single_factors: bool = False,
) -> list[SolveResult | Exception]:
    """Every sample of one geometry (:func:`geometry_key` equal for all) on one mesh and model.

    The first result's ``seconds`` and ``timings`` carry the mesh and the model setup.
    ``errors="return"`` puts the :class:`~elastimap.solver.errors.SolverError` of a failed
    sample in its place instead of raising (a failed mesh fails every sample of the group).

    A sample that differs from the one before by the inclusion's modulus alone (a sweep's moduli
    of one mesh, ``sweep run --moduli-per-mesh``) keeps that sample's reference press, which does
    not depend on it, and its factors: its inclusion press is the difference of the two presses by
    CG on them, as the first sample's (docs/forward-model.md, 'Shared presses').
    ``single_factors``: the reference press may factorise in single precision as a single
    ``solve`` does (``fem.Model.single_factors``); batched variants of other moduli keep double."""
    from .api import solve
    from .errors import SolverError
    from .fem import Model
    from .geometry import MeshError, build_mesh
    from .sample import run_sample, sample_tag

    ps = [p.validate() for p in params_list]
    if len({geometry_key(p) for p in ps}) > 1:
        raise ValueError("solve_group: the samples do not share one geometry (use solve_batch)")
    out: list[SolveResult | Exception] = []

    def land(i, r):
        out.append(r)
        if on_result:
            on_result(i, r)

    if ps[0].disc.geometry != "remesh":  # a morphed mesh has its own reuse (solver.morph): sample by sample
        for i, p in enumerate(ps):
            try:
                land(i, solve(p))
            except SolverError as exc:
                if errors == "raise":
                    raise
                land(i, exc)
        return out
    t0 = time.perf_counter()
    try:
        raw = build_mesh(ps[0])
        model = Model(raw, ps[0])
    except (MeshError, SolverError) as exc:
        err = SolverError(f"mesh/setup failed for {sample_tag(ps[0])}: {exc}")
        if errors == "raise":
            raise err from exc
        for i in range(len(ps)):
            land(i, err)
        return out
    model.single_factors = single_factors
    reference = None  # the reference press of the sample before (run_sample's)
    try:
        for i, p in enumerate(ps):
            try:
                if reference is not None and inclusion_modulus_only(ps[i - 1], p):
                    model.set_inclusion_modulus(p)
                else:
                    model.set_params(p)
                    reference = None
                # the first variant carries the mesh and the model setup (its t0 is the group's)
                res, reference = run_sample(
                    model,
                    p,
                    t0 if i == 0 else time.perf_counter(),
                    {"mesh": raw.seconds} if i == 0 else {},
                    reference=reference,
                )
                if i > 0:
                    res.timings.pop("setup", None)
            except SolverError as exc:
                if errors == "raise":
                    raise
                res, reference = exc, None
            land(i, res)
    finally:
        model.destroy()
    return out


def solve_batch(
    params_list: Sequence[SolveParams],
    on_result: Callable[[int, SolveResult | Exception], None] | None = None,
    errors: str = "raise",
) -> list[SolveResult | Exception]:
    """Results of :func:`elastimap.solver.api.solve` for every sample of ``params_list`` (same
    order), one mesh and one model per geometry (:func:`group_by_geometry`).  ``on_result(i, r)``
    is called as each lands; ``errors`` as in :func:`solve_group`."""
    out: list[SolveResult | Exception | None] = [None] * len(params_list)
    for idx in group_by_geometry(params_list):

        def land(j, r, idx=idx):
            out[idx[j]] = r
            if on_result:
                on_result(idx[j], r)

        solve_group([params_list[i] for i in idx], land, errors)
    return out  # type: ignore[return-value]
