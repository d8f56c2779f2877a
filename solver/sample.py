"""One sample on a built model: the inclusion press and the reference press, the difference
image and its features (``run_sample``), and what names a sample in messages (``sample_tag``).

Shared by :mod:`elastimap.solver.api` (``solve``: a gmsh mesh per sample),
:mod:`elastimap.solver.batch` (material variants on one mesh) and :mod:`elastimap.solver.morph`
(reference meshes moved to (d, h)).
"""

from __future__ import annotations

import resource
import time

import numpy as np

from .params import SolveParams, SolveResult


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def solve_at(model, E_inc: float, p: SolveParams):
    """Solve for one inclusion modulus under the loading of ``p``; returns (sol, diag, delta, force)."""
    from .errors import SolverError

    ld = p.loading
    delta = ld.delta
    sol, diag = model.solve(E_inc, delta)
    force = model.plate_force(sol)
    if ld.force is None:
        return sol, diag, delta, force
    from elastimap.errors import UserError

    from .params import delta_limit

    limit = delta_limit(p)

    def too_far(d: float) -> UserError:
        return UserError(
            "force",
            f"{ld.force:g} mN needs a plate travel of about {d:.3g} mm; at most "
            f"{limit:g} mm is allowed (the same limit as --delta)",
        )

    if not (np.isfinite(force) and force > 0):
        raise SolverError(f"force control: the plate force at delta = {delta:g} mm is {force:g} mN")
    if not p.nonlinear:
        # linear problem: displacements and force scale with δ
        s = ld.force / force
        if delta * s > limit:
            raise too_far(delta * s)
        sol.u *= s
        sol.reaction *= s
        for k in ("pressure_mean_kPa", "pressure_min_kPa", "pressure_max_kPa", "gap_min_mm"):
            diag[k] *= s
        return sol, diag, delta * s, ld.force
    its = sol.iterations
    for _ in range(20):  # secant on δ for the (mildly) nonlinear contact / finite-strain problem
        if abs(force - ld.force) <= 1e-6 * ld.force:
            break
        delta = delta * ld.force / force
        if delta > limit:
            raise too_far(delta)
        sol, diag = model.solve(E_inc, delta)
        its += sol.iterations
        force = model.plate_force(sol)
    else:
        raise SolverError(f"force control did not converge (target {ld.force:g} mN, got {force:g} mN)")
    sol.iterations = its
    return sol, diag, delta, force


def sample_tag(p: SolveParams) -> str:
    inc = p.inclusion
    return f"(d={inc.d:g} mm, h={inc.h:g} mm, E={inc.E:g} kPa)"


def write_vtx(model, path: str, fields: dict) -> None:
    from dolfinx import fem
    from dolfinx.io import VTXWriter

    funcs = []
    for name, u in fields.items():
        f = fem.Function(model.V, name=name)
        f.x.array[: len(u)] = u
        funcs.append(f)
    with VTXWriter(model.mesh.comm, path, funcs, engine="BP4") as w:
        w.write(0.0)


def run_sample(
    model, p: SolveParams, t0: float, extra_timings: dict, *, vtx_path: str | None = None, reference=None
) -> tuple[SolveResult, tuple]:
    """The two solves of one sample on a built ``model`` whose mesh has the geometry of ``p``.

    ``reference``: the (sol_ref, diag_ref, delta_ref, force_ref, w_ref) of the reference solve when
    the caller already has it (it does not depend on the inclusion's modulus).  Returns the
    result and that reference tuple, so a caller can keep it for the next modulus.
    """
    from .errors import SolverError
    from .image import features, mirror_quarter

    tag = sample_tag(p)
    model.timings = {"setup": model.timings.get("setup", 0.0)}
    try:
        # the reference press first: the inclusion press then starts from its solution and solves
        # the difference of the two on its factors (:meth:`~elastimap.solver.fem.Model.solve_linear`);
        # a model that does not share them (``share_presses``) runs the inclusion press first, as before
        first = getattr(model, "share_presses", True) or reference is not None
        if not first:
            sol, diag, delta, force = solve_at(model, p.inclusion.E, p)
        if reference is None:
            sol_ref, diag_ref, delta_ref, force_ref = solve_at(model, p.tissue.E, p)
            w_ref = model.probe_bottom_w(sol_ref, delta_ref)
            reference = (sol_ref, diag_ref, delta_ref, force_ref, w_ref)
        sol_ref, diag_ref, delta_ref, force_ref, w_ref = reference
        if first:
            sol, diag, delta, force = solve_at(model, p.inclusion.E, p)
        w = model.probe_bottom_w(sol, delta)
        if vtx_path:
            write_vtx(model, vtx_path, {"u": sol.u, "u_ref": sol_ref.u})
    except SolverError as exc:
        raise SolverError(f"solve failed for {tag}: {exc}") from exc
    if p.disc.symmetry == "quarter":
        w, w_ref = mirror_quarter(w), mirror_quarter(w_ref)
    if p.disc.interface == "tied" and diag["tension_patch_fraction"] > 0:
        import warnings

        warnings.warn(
            f"tied interface carries tension on {100 * diag['tension_patch_fraction']:.2g} % of the "
            f"footprint patches for {tag}: the probe would lift off there; use interface='contact'",
            RuntimeWarning,
            stacklevel=2,
        )
    diff = w - w_ref
    O1, O2, O3 = features(diff, p.image.pixel, p.image.threshold, p.image.supersample)
    timings = dict(model.timings)
    timings.update(extra_timings)
    seconds = time.perf_counter() - t0
    res = SolveResult(
        params=p,
        O1=O1,
        O2=O2,
        O3=O3,
        force=force,
        force_ref=force_ref,
        delta=delta,
        image=diff.astype(np.float32),
        image_raw=w.astype(np.float32),
        pixel=p.image.pixel,
        ndofs=model.ndofs,
        ncells=model.ncells,
        newton_iterations=sol.iterations + sol_ref.iterations,
        seconds=seconds,
        timings={k: round(v, 4) for k, v in timings.items()},
        peak_memory_mb=_peak_mb(),
        interface={**diag, "reference_tension_patch_fraction": diag_ref["tension_patch_fraction"]},
    )
    return res, reference
