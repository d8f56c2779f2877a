r"""Newton's method on the reduced system, for the finite-strain tissue (``Tissue.nonlinearity`` > 0).

With the stored energy ψ(F) of :func:`elastimap.solver.materials.psi_blended`, the
internal virtual work and its Jacobian are UFL derivatives,

$$
R(u; v) = \int_\Omega \frac{\partial \psi}{\partial F} : \nabla v \, {\rm d}x, \qquad
J(u; \delta u, v) = D_u R(u; v)[\delta u] .
$$

The constraints stay eliminated, u = P ū + u_D (:mod:`elastimap.solver.reduction`),
and the friction spring S (if any) is linear, so each step solves

$$
P^{T} (J + S) P \, \Delta \bar u = -P^{T} \left( R(u) + S u \right),
\qquad u \leftarrow u + \alpha \, P \Delta \bar u ,
$$

started from the linear solution (or a warm start: the caller load-steps a cold solve,
:meth:`elastimap.solver.fem.Model.solve_nonlinear`), with α halved while the step makes a
non-finite residual (an inverted element, J = det F ≤ 0) or raises ‖Pᵀ(R + S u)‖.  A
factorised tangent is reused (modified Newton) while a full step with it cuts the residual by
``reuse_ratio``.  The
interface pairs are the coincident nodes of the reference configuration (small
tangential sliding assumed).
"""

from __future__ import annotations

from . import _boot  # noqa: F401  (must precede dolfinx)

# isort: split

import os
from typing import TYPE_CHECKING

import numpy as np
from dolfinx import fem
from petsc4py import PETSc

from .errors import SolverError
from .reduction import LU, Solution, ptap

if TYPE_CHECKING:
    import scipy.sparse as sp

_DEBUG = bool(os.environ.get("ELASTIMAP_NEWTON_DEBUG"))


class Newton:
    """Newton on the reduced system for the residual form ``R_form`` and Jacobian ``J_form``,
    both evaluated at the displacement function ``u_fun``."""

    def __init__(self, R_form, J_form, u_fun: fem.Function):
        self.R_form, self.J_form, self.u_fun = R_form, J_form, u_fun
        from dolfinx.fem import petsc as fpetsc  # only here: its import costs a linear solve 0.03 s

        self.Jmat = fpetsc.create_matrix(J_form)
        self._KJ = None
        self._KJ_key = None
        self.factorisations = 0  # tangent factorisations, all solves
        #: modified Newton: keep the factorised tangent while a full step cuts ‖g‖ by this factor
        #: (0.25: β = 1 on coarse, d/h/E = 8/7/50, 19 CPU s against 24 for plain Newton; 0.1 and
        #: 0.5 within 1.5 s of it)
        self.reuse_ratio = 0.25
        self.lu = LU("newton", "symmetric")  # the tangent of a stored energy: symmetric

    def residual(self, u: np.ndarray) -> np.ndarray:
        """Internal nodal force R(u) (mN, all flat dofs), without the friction spring."""
        self.u_fun.x.array[: len(u)] = u
        return fem.assemble_vector(self.R_form).array[: len(u)].copy()

    def _reduced_jacobian(self, Pm: PETSc.Mat, key: bytes, Sm: PETSc.Mat | None) -> tuple[PETSc.Mat, bool]:
        """Pᵀ(J + S)P at the current ``u_fun``, and whether its pattern is new."""
        from dolfinx.fem import petsc as fpetsc

        self.Jmat.zeroEntries()
        fpetsc.assemble_matrix(self.Jmat, self.J_form)
        self.Jmat.assemble()
        if self._KJ is None or self._KJ_key != key or Sm is not None:
            if self._KJ is not None:
                self._KJ.destroy()
            self._KJ = ptap(self.Jmat, Pm)
            new_pattern = True
        else:
            self.Jmat.ptap(Pm, result=self._KJ)
            new_pattern = False
        self._KJ_key = key
        if Sm is not None:
            self._KJ.axpy(1.0, Sm, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        return self._KJ, new_pattern

    def solve(
        self,
        predictor: Solution,
        Pm: PETSc.Mat,
        Psp: sp.csr_matrix,
        key: bytes,
        friction: tuple[sp.csr_matrix, PETSc.Mat] | None = None,
        rtol: float = 1e-9,
        max_iter: int = 30,
        start: np.ndarray | None = None,
    ) -> Solution:
        """Converge from the linear ``predictor`` (same P, same active set ``key``), or from
        ``start`` (a converged neighbour with the same prescribed values: a warm start).

        Converged when ‖Pᵀ(R + S u)‖ falls below ``rtol`` times the norm of the
        predictor's reduced |internal force|.  ``iterations`` counts the linear solves
        (the predictor's included).  A factorised tangent is reused (modified Newton, one
        back-substitution) while a full step with it cuts ‖g‖ by at least the factor
        ``self.reuse_ratio``; otherwise the next step factorises the tangent afresh (0: plain Newton)."""
        S, Sm = friction if friction is not None else (None, None)
        u = (predictor.u if start is None else start).copy()

        def reduced_res(uu):
            r = self.residual(uu)
            g = Psp.T @ (r + (S @ uu if S is not None else 0.0))
            return r, g

        r, g = reduced_res(u)
        scale = max(float(np.linalg.norm(Psp.T @ np.abs(predictor.reaction))), 1e-300)
        gnorm = float(np.linalg.norm(g))
        its = 1
        KJ, fresh = None, True
        for _ in range(max_iter):
            if gnorm <= rtol * scale:
                break
            reused = not (fresh or KJ is None)
            if not reused:
                KJ, new_pattern = self._reduced_jacobian(Pm, key, Sm)
                f = KJ.createVecRight()
                f.getArray()[:] = -g
                dub = self.lu.solve(KJ, f, new_pattern)
                self.factorisations += 1
            else:  # modified Newton: the last tangent's factors (back-substitution only)
                f = KJ.createVecRight()
                f.getArray()[:] = -g
                dub = self.lu.resolve(f)
            du = Psp @ dub.getArray().copy()
            f.destroy()
            dub.destroy()
            its += 1
            step = 1.0
            for _ls in range(12):
                u_try = u + step * du
                with np.errstate(all="ignore"):
                    r_try, g_try = reduced_res(u_try)
                gn_try = float(np.linalg.norm(g_try))
                if np.all(np.isfinite(r_try)) and gn_try < max(gnorm, 1e-12 * scale) * (1 + 1e-12) + 1e-300:
                    break
                step *= 0.5
            else:
                if reused:  # the stale tangent's direction: try again with a fresh one
                    fresh = True
                    continue
                raise SolverError("Newton line search failed (finite-strain tissue)")
            # keep the tangent while it still cuts the residual fast with full steps
            fresh = not (step == 1.0 and gn_try <= self.reuse_ratio * gnorm)
            u, r, g, gnorm = u_try, r_try, g_try, gn_try
            if _DEBUG:
                print(f"newton {its}: step {step:g} |g|/scale {gnorm / scale:.3e}")
        else:
            if gnorm > rtol * scale:  # (the last step may itself have converged)
                raise SolverError(
                    f"Newton did not converge in {max_iter} iterations (residual {gnorm:.3g}, scale {scale:.3g})"
                )
        if not np.all(np.isfinite(u)):
            raise SolverError("the Newton solve produced non-finite displacements")
        return Solution(u=u, reaction=r, iterations=its)

    def destroy(self) -> None:
        for obj in (self._KJ, self.Jmat):
            if obj is not None:
                obj.destroy()
        self._KJ = self.Jmat = None
        self.lu.destroy()
