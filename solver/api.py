"""``solve(params) -> SolveResult``: geometry → mesh → two solves → elasticity image → features.

One sample is two solves on the same mesh: with the inclusion (modulus E) and
a reference with the inclusion's modulus set to the tissue's.  The raw image
w(x, y) = u_z + δ of the probe bottom is dominated by the flat-punch edge
singularity at the probe rim, so the features are taken from the difference
image w_E − w_ref (see :mod:`elastimap.solver.image`).
"""

from __future__ import annotations

from . import _threads  # noqa: F401  (before numpy: one solve, one core)

# isort: split

import gc
import sys
import time

from .params import SolveParams, SolveResult
from .sample import run_sample, sample_tag

#: how a sample's two presses share their work (:class:`~elastimap.solver.fem.Model`):
#: ``shared`` -- the reference press is factorised, the inclusion press is the difference of the two
#: by CG on those factors, assembled and reduced by the inclusion's cells only; ``separate`` -- each
#: press assembles, reduces and factorises for itself (the path before; the baseline ``sweep bench
#: --compare`` times against)
PRESSES = ("shared", "separate")


def solve(params: SolveParams, presses: str | None = None) -> SolveResult:
    """Run one sample.  Raises :class:`elastimap.errors.UserError` for bad input and
    :class:`solver.SolverError` (message carries d, h, E) when the solve fails.  ``presses``: one
    of ``PRESSES``; None: ``$ELASTIMAP_PRESSES`` (``shared`` when unset;
    :func:`elastimap.solver.fem.default_presses`, which also sets a morphed or batched model's)."""
    if presses is not None and presses not in PRESSES:
        from elastimap.errors import UserError

        raise UserError("presses", f"must be one of {', '.join(PRESSES)} (got {presses!r})")
    return _solve(params, presses=presses)


def solve_with_fields(params: SolveParams, vtx_path: str) -> SolveResult:
    """As :func:`solve`, and write both displacement fields (``u`` with the inclusion,
    ``u_ref`` of the reference solve, mm) to an ADIOS2 ``.bp`` folder for ParaView."""
    return _solve(params, vtx_path)


def _import_the_stack() -> None:
    """Import the physics (:mod:`.fem`, :mod:`.geometry`: DOLFINx, UFL, FFCx, PETSc, gmsh) the first
    time a process solves, with Python's cyclic garbage collector paused, then move every object
    made so far to the collector's permanent generation (:func:`gc.freeze`): the modules, classes
    and UFL objects of the imports (about 60 000) live as long as the process, and no later pass of
    the collector (one walks them all, as does the interpreter's at exit) needs to visit them again.
    About 0.05 s of CPU of a `solve` process (docs/forward-model.md, 'Speed').  Garbage made after
    this is collected as before; a process that imported :mod:`.fem` itself is left alone."""
    if "elastimap.solver.fem" in sys.modules:
        return
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        from . import fem, geometry  # noqa: F401
    finally:
        gc.freeze()
        if was_enabled:
            gc.enable()


def _solve(params: SolveParams, vtx_path: str | None = None, presses: str | None = None) -> SolveResult:
    _import_the_stack()
    from .errors import SolverError
    from .fem import Model, default_presses
    from .geometry import MeshError, build_mesh

    p = params.validate()
    if presses is None:
        default_presses()  # a bad $ELASTIMAP_PRESSES is refused before any work
    if p.disc.geometry == "morph":
        if vtx_path:
            from elastimap.errors import UserError

            raise UserError("geometry", "writing the fields needs geometry='remesh'")
        from .morph import shared_forward

        inc = p.inclusion
        return shared_forward(p).solve(inc.d, inc.h, inc.E)
    t0 = time.perf_counter()
    try:
        raw = build_mesh(p)
        model = Model(raw, p)
        model.single_factors = True  # a remeshed sample: single-precision factors (fem.PRESS_RTOL_SINGLE)
        if presses is not None:
            model.share_presses = presses == "shared"
    except (MeshError, SolverError) as exc:
        raise SolverError(f"mesh/setup failed for {sample_tag(p)}: {exc}") from exc
    try:
        return run_sample(model, p, t0, {"mesh": raw.seconds}, vtx_path=vtx_path)[0]
    finally:
        model.destroy()


def warmup(params: SolveParams | None = None) -> float:
    """Compile the DOLFINx forms once (into the JIT cache) with a tiny solve; returns seconds.

    Call it in a sweep driver before fanning out to workers.
    """
    from .params import Discretisation

    t0 = time.perf_counter()
    p = params or SolveParams()
    p = p.replace(disc=Discretisation(mesh="tiny", degree=p.disc.degree, interface="tied", symmetry="quarter"))
    p = p.with_inclusion(offset_x=0.0, offset_y=0.0)
    solve(p)
    return time.perf_counter() - t0
