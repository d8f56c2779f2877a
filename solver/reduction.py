r"""Constraints by elimination: u = P ū + u_D, the reduced system PᵀAP ū = −PᵀA u_D, MUMPS LU.

Dirichlet conditions (mm): u = 0 on a rigid chest wall z = 0 (a compliant one,
``Tissue.wall_compliance`` > 0, is a spring term of a(u, v) instead: :mod:`elastimap.solver.fem`); u = (0, 0, −δ) (a tilted plate:
(0, 0, −(δ + θ x)), ``Loading.tilt`` θ in rad) on the
probe top (bonded to the rigid plate, which moves down by δ); u·n = 0 on the
symmetry planes x = 0, y = 0 of the quarter model.  The interface ties the
normal component of every active pair (all three components for ``bonded``):
a tied tissue value copies its probe partner.

All of them are imposed by elimination.  With the free unknowns ū, the prescribed
values u_D and the 0/1 matrix P that copies each free unknown to the flat dofs it
stands for,

$$
u = P \bar u + u_D, \qquad
P^{T} (A + S) P \, \bar u = -P^{T} (A + S) \, u_D ,
$$

A the stiffness matrix of a(u, v) (mN/mm) and S the optional friction spring
(:class:`elastimap.solver.interface.Friction`).  The reduced matrix keeps A's symmetry
and is factorised with MUMPS (:class:`LU`; Cholesky for this SPD matrix); a variant of the same
problem on the same mesh (other moduli or ν) is solved by conjugate gradients on the factors of
the last one (:class:`Recycled`).  The nodal reaction is r = A u (mN).
"""

from __future__ import annotations

from . import _boot  # noqa: F401  (must precede dolfinx)

# isort: split

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .errors import SolverError
from .interface import Interface
from .space import Space

if TYPE_CHECKING:
    import scipy.sparse as sp


@dataclass
class Solution:
    u: np.ndarray  # all nodal values (mm), flat (3 per node)
    reaction: np.ndarray  # internal nodal force r (mN), flat: A u (linear) or R(u) (finite strain)
    iterations: int  # linear solves (or active-set iterations) that produced it


class Reduction:
    """The map u = P ū + u_D for a loading δ and a set of closed interface pairs.

    P depends on the active set only (u_D on δ too); it is rebuilt, and the reduced
    pattern with it, when the set changes.
    """

    def __init__(self, space: Space, interface: Interface, tied_components: tuple[int, ...], rigid_wall: bool = True):
        self.space, self.interface, self.tied = space, interface, tied_components
        self.rigid_wall = rigid_wall  # u = 0 on the chest wall (False: the wall is a spring term of A)
        self.tilt = 0.0  # rad: a tilted plate, u_z = -(δ + tilt · x) on the probe top
        self._P = None
        self._Psp = None  # P as scipy CSR, made on first use (``P_csr``)
        self._csr = None  # P's CSR arrays (indptr, indices, data, shape)
        self._col = None  # P's column of every row (−1: prescribed), as ``constraints`` gives it
        self._key = None
        self._K = None
        self.ptap_via: str | None = "rap"  # PᵀAP's algorithm (:func:`ptap`)

    def constraints(self, delta: float, active: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Column of every flat dof in ū (−1 for prescribed), the prescribed values u_D and the prescribed mask."""
        s = self.space
        n = s.ndofs
        fixed = np.zeros(n, dtype=bool)
        uD = np.zeros(n)
        for comp in range(3):
            if self.rigid_wall:
                fixed[3 * s.bottom + comp] = True
            fixed[3 * s.top + comp] = True
        uD[3 * s.top + 2] = -(delta + self.tilt * s.X[s.top, 0]) if self.tilt else -delta
        fixed[3 * s.sym_x + 0] = True
        fixed[3 * s.sym_y + 1] = True
        master = np.arange(n)
        for comp in self.tied:
            sl = 3 * self.interface.pair_tissue[active] + comp
            m = 3 * self.interface.pair_probe[active] + comp
            fixed[sl] |= fixed[m]
            master[sl[~fixed[sl]]] = m[~fixed[sl]]
        free = ~fixed & (master == np.arange(n))
        col = np.full(n, -1, dtype=np.int64)
        col[free] = np.arange(np.count_nonzero(free))
        slave = ~fixed & ~free
        col[slave] = col[master[slave]]
        return col, uD, fixed

    def operator(self, delta: float, active: np.ndarray) -> tuple[PETSc.Mat, np.ndarray, bool]:
        """(P as PETSc, u_D, new_pattern) for this active set, cached by the set (P as scipy:
        :attr:`P_csr`)."""
        key = active.tobytes()
        col, uD, _fixed = self.constraints(delta, active)
        if self._key == key:
            return self._P, uD, False
        # one entry (1) per row that is not prescribed, in column col[row]: CSR by numpy, so that
        # the linear solve needs no scipy (0.13 s of a `solve` process's imports)
        n = len(col)
        kept = col >= 0
        nfree = int(col.max()) + 1
        indptr = np.concatenate(([0], np.cumsum(kept))).astype(PETSc.IntType)
        indices = col[kept].astype(PETSc.IntType)
        data = np.ones(len(indices))
        if self._P is not None:
            self._P.destroy()
        self._P = PETSc.Mat().createAIJ(size=(n, nfree), csr=(indptr, indices, data), comm=MPI.COMM_SELF)
        self._P.assemble()
        self._csr = (indptr, indices, data, (n, nfree))
        self._col = col
        self._Psp = None
        self._key = key
        return self._P, uD, True

    @property
    def P_csr(self) -> sp.csr_matrix:
        """P of the last :meth:`operator` call as a scipy CSR matrix (friction, Newton, a morphed
        tangent), made on first use."""
        if self._Psp is None:
            import scipy.sparse as sp

            indptr, indices, data, shape = self._csr
            self._Psp = sp.csr_matrix((data, indices, indptr), shape=shape)
        return self._Psp

    def reduce(
        self,
        A: PETSc.Mat,
        Pm: PETSc.Mat,
        uD: np.ndarray,
        new_pattern: bool,
        friction: tuple[sp.csr_matrix, PETSc.Mat] | None = None,
    ) -> tuple[PETSc.Mat, PETSc.Vec, bool]:
        r"""The reduced system $K = P^{T} (A + S) P$, $f = -P^{T} (A + S) u_D$ and whether K has a new pattern.

        K is kept between calls: with an unchanged active set and no friction only its
        values are recomputed (so the LU reuses its symbolic factorisation).
        """
        if new_pattern or friction is not None:
            # with friction K gets the extra Pᵀ S P pattern, so it is rebuilt from PᵀAP each time
            if self._K is not None:
                self._K.destroy()
            self._K = ptap(A, Pm, self.ptap_via)
            new_pattern = True
        else:
            A.ptap(Pm, result=self._K)
        K = self._K
        if friction is not None:
            K.axpy(1.0, friction[1], structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        return K, self.rhs(A, Pm, uD, friction), new_pattern

    def increment(self, A: PETSc.Mat, Pm: PETSc.Mat, uD: np.ndarray, dK: PETSc.Mat, scale: float):
        r"""The reduced system after A changed by ``scale`` · ΔA on the same pattern and active set:
        $K \leftarrow K + s \, P^{T} \Delta A P$ with ``dK`` = PᵀΔAP (its pattern within K's), and
        $f = -P^{T} A u_D$ of the new A.  Returns (K, f); K is the one :meth:`reduce` made last."""
        if scale != 0.0:
            self._K.axpy(scale, dK, structure=PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
        return self._K, self.rhs(A, Pm, uD, None)

    def restrict(self, A: PETSc.Mat, Pm: PETSc.Mat) -> PETSc.Mat:
        r"""PᵀAP (a new matrix) of a matrix A with few rows, e.g. A₁ of the inclusion's cells, whose
        rows and columns with entries are each either prescribed or P's only row of their column
        (no tied pair): then $(P^T A P)_{cd} = A_{r(c) r(d)}$, r(c) that row, one product by 1.0 per
        entry, so PᵀAP is A's entries moved to the reduced numbering (MatCreateSubMatrix): the
        matrix :func:`ptap` gives, without forming Pᵀ and the products over all of P (0.011 against
        0.002 s for A₁ on `default`; docs/forward-model.md, 'Speed').  Any other A, or a P other
        than the last :meth:`operator`'s: :func:`ptap`."""
        col = self._col
        if Pm is not self._P or col is None:
            return ptap(A, Pm)
        indptr, indices, _values = A.getValuesCSR()
        used = np.zeros(len(col), dtype=bool)
        used[np.diff(indptr) > 0] = True
        used[indices] = True
        kept = np.flatnonzero(col >= 0)
        rows_per_column = np.bincount(col[kept], minlength=self._csr[3][1])
        c = col[used]
        if np.any(rows_per_column[c[c >= 0]] != 1):
            return ptap(A, Pm)
        rep = np.empty(self._csr[3][1], dtype=PETSc.IntType)
        rep[col[kept]] = kept  # a row of each column: the only one where A has entries
        index = PETSc.IS().createGeneral(rep, comm=MPI.COMM_SELF)
        try:
            return A.createSubMatrix(index, index)
        finally:
            index.destroy()

    def rhs(self, A: PETSc.Mat, Pm: PETSc.Mat, uD: np.ndarray, friction=None) -> PETSc.Vec:
        """f = −Pᵀ(A + S) u_D (mN)."""
        vD = PETSc.Vec().createWithArray(uD, comm=MPI.COMM_SELF)
        AuD = A.createVecLeft()
        A.mult(vD, AuD)
        f = Pm.createVecRight()
        Pm.multTranspose(AuD, f)
        if friction is not None:
            f.getArray()[:] += self.P_csr.T @ (friction[0] @ uD)
        f.scale(-1.0)
        vD.destroy()
        AuD.destroy()
        return f

    def expand(self, Pm: PETSc.Mat, ubar: PETSc.Vec, uD: np.ndarray) -> np.ndarray:
        """All nodal values u = P ū + u_D (flat numpy array)."""
        u_vec = Pm.createVecLeft()
        Pm.mult(ubar, u_vec)
        u = u_vec.getArray().copy() + uD
        u_vec.destroy()
        return u

    def destroy(self) -> None:
        for obj in (self._P, self._K):
            if obj is not None:
                obj.destroy()
        self._P = self._K = None


def ptap(A: PETSc.Mat, P: PETSc.Mat, via: str | None = "rap") -> PETSc.Mat:
    """PᵀAP (a new matrix), by default by PETSc's ``rap`` product (Pᵀ formed, then Pᵀ·A·P): for
    this 0/1 reduction about 2.5× faster than PETSc's default algorithm (``via=None``; 0.07
    against 0.19 s of CPU on the `default` quarter model, 2.1 M entries; docs/forward-model.md,
    'Shared presses'), the same matrix."""
    if via is None:
        return A.ptap(P)
    opts = PETSc.Options()
    opts["matptap_via"] = via  # read when the product is set up
    try:
        return A.ptap(P)
    finally:
        opts.delValue("matptap_via")


def mumps_ksp(prefix: str, ksp_type: str, factor: str, workspace: bool = True) -> PETSc.KSP:
    """A serial KSP of ``ksp_type`` whose preconditioner is MUMPS's ``factor`` ("lu" or
    "cholesky") factorisation, with a 80 % workspace margin (ICNTL(14); ``workspace=False``: the
    caller sets it, with :func:`mumps_workspace`, before its first factorisation)."""
    ksp = PETSc.KSP().create(MPI.COMM_SELF)
    ksp.setType(ksp_type)
    pc = ksp.getPC()
    pc.setType(factor)
    pc.setFactorSolverType("mumps")
    ksp.setOptionsPrefix(prefix)
    if workspace:
        mumps_workspace(prefix)
    ksp.setFromOptions()
    return ksp


def mumps_workspace(prefix: str) -> None:
    """MUMPS's 80 % workspace margin (ICNTL(14)) for the solver of ``prefix``, read at its next
    symbolic factorisation.  Set only where a factorisation follows: PETSc prints every option
    left unread at exit, on stdout (where a ``--json`` answer goes)."""
    PETSc.Options()[f"{prefix}mat_mumps_icntl_14"] = 80


class LU:
    """Direct solve K x = f with MUMPS; the symbolic factorisation is kept while K's pattern is.

    ``symmetry``: "spd" -- K symmetric positive definite (the linear stiffness with the rigid
    modes constrained): Cholesky L Lᵀ, no pivoting (MUMPS SYM=1); "symmetric" -- symmetric,
    possibly indefinite (a Newton tangent away from equilibrium): L D Lᵀ with pivoting (SYM=2);
    "general" -- LU.  The symmetric factorisations read the upper triangle only and take about
    a quarter less time than LU on the coarse quarter model (same displacements to round-off)."""

    def __init__(self, name: str = "lu", symmetry: str = "general"):
        if symmetry not in ("spd", "symmetric", "general"):
            raise ValueError(f"symmetry must be spd, symmetric or general, not {symmetry!r}")
        self.symmetry = symmetry
        self.ksp = mumps_ksp(f"elastimap_{id(self)}_{name}_", "preonly", "lu" if symmetry == "general" else "cholesky")

    def solve(self, K: PETSc.Mat, f: PETSc.Vec, new_pattern: bool) -> PETSc.Vec:
        ksp = self.ksp
        if self.symmetry != "general":
            K.setOption(PETSc.Mat.Option.SYMMETRIC, True)
            if self.symmetry == "spd":
                K.setOption(PETSc.Mat.Option.SPD, True)
        if new_pattern:
            ksp.reset()  # new constraint set: new symbolic factorisation
        ksp.setOperators(K)  # same pattern as last time: numeric refactorisation only
        ksp.setFromOptions()
        x = K.createVecRight()
        ksp.solve(f, x)
        reason = ksp.getConvergedReason()
        if reason < 0:
            x.destroy()
            raise SolverError(f"linear solve failed (PETSc reason {reason})")
        return x

    def resolve(self, f: PETSc.Vec) -> PETSc.Vec:
        """Solve with the factorisation of the last :meth:`solve` (its matrix unchanged since)."""
        x = self.ksp.getOperators()[0].createVecRight()
        self.ksp.solve(f, x)
        if self.ksp.getConvergedReason() < 0:
            x.destroy()
            raise SolverError(f"linear solve failed (PETSc reason {self.ksp.getConvergedReason()})")
        return x

    def destroy(self) -> None:
        if self.ksp is not None:
            self.ksp.destroy()
            self.ksp = None


#: :class:`Recycled` factorises a matrix of at least this many unknowns by MUMPS's block low-rank
#: Cholesky with this dropping tolerance (a `fine` sample's solves: 41 % less time; CG on the factors
#: keeps every solve at its tolerance).  The `default` level (about 27 000-33 000) stays below it:
#: there exact factors cost 7 % less factorisation-and-solve CPU (the block low-rank analysis and the
#: reference press's CG step outweigh the cheaper numeric factorisation; docs/forward-model.md,
#: 'Shared presses')
BLR_MIN_UNKNOWNS = 40_000
BLR_TOLERANCE = 1e-8
#: :class:`Recycled` factorises a matrix of at least this many unknowns and below ``BLR_MIN_UNKNOWNS``
#: (the `default` quarter model) in **single precision** (MUMPS's ``smumps``, PETSc's
#: ``-pc_precision single``): the numeric factorisation and every back-substitution in float32, CG in
#: double on those factors to the solver's tolerance.  On five `default` samples the reference press
#: (factorise, then CG to 1e-12: 3 iterations) and the inclusion press (the same 9-18 iterations, each
#: cheaper) took 0.60-0.84 instead of 0.90-1.30 s of CPU (mean 0.73 against 1.14 s; docs/forward-model.md,
#: 'Shared presses'); a factorisation that fails in single precision is redone in double
SINGLE_MIN_UNKNOWNS = 25_000
#: MUMPS's fill-reducing ordering (ICNTL(7)) of single-precision factors: PORD (4) instead of the
#: automatic choice (METIS here): on five other `default` samples than the five above, the reference
#: and inclusion presses' factorisation and solves took 0.60-0.76 instead of 0.72-0.90 s of CPU (mean
#: 0.67 against 0.77 s, the same CG iterations); with double factors PORD was no faster than METIS
SINGLE_ORDERING = 4
#: :class:`Recycled`'s relative tolerance of CG (preconditioned residual) unless told otherwise
CG_RTOL = 1e-12


class Recycled:
    r"""K x = f by conjugate gradients preconditioned with the Cholesky factors of a nearby
    matrix K₀: the last one this solver factorised, a variant of the same problem (another
    modulus of a probe layer or of the background, another ν) on the same mesh and constraints.

    The factorisation is most of a solve's time; an iteration costs one back-substitution and
    one product with K.  With M = K₀ the error falls per iteration by (√κ − 1)/(√κ + 1),
    κ = cond(K₀⁻¹K): when the parts' stiffnesses (the elastic moduli of a region) change by the
    factors s_i, the eigenvalues of K₀⁻¹K lie within [min s_i, max s_i] (the ratio of the
    Rayleigh quotients is a mean of the s_i weighted by the parts' energies), so
    κ ≤ max s_i / min s_i: a 40 % change of one layer's modulus, κ ≤ 1.4, needs about 10 iterations for the
    relative tolerance ``rtol`` = 1e-12 (Saad 2003, §6.11, §9.2).  When CG has not converged in
    ``max_it`` iterations, or the constraints (``key``: the active set) changed, K is
    factorised afresh (K₀ := K) and solved with its own factors.  ``refactor_after``: when the
    solve before a :meth:`resolve` (a tangent's back-solves) needed more than that many CG
    iterations, K is factorised first, so that each back-solve costs one back-substitution instead
    of as many iterations (and the solves after start from K's factors); plain solves never
    refactorise early; None: only when CG fails.  K must be symmetric
    positive definite (the linear stiffness with the rigid modes constrained).

    Block low-rank factors (``blr_min``, ``blr_tol``): a matrix of at least ``blr_min`` unknowns
    is factorised by MUMPS's block low-rank Cholesky (ICNTL(35) = 2: the off-diagonal blocks of
    the fronts compressed to rank-revealing products, dropping tolerance CNTL(7) = ``blr_tol``;
    Amestoy et al., SIAM J. Sci. Comput. 37 (2015) A1451).  Such factors are not exact, so a
    solve with K's own factors is then CG preconditioned by them to ``rtol`` as well (two
    iterations on the `fine` level, measured), not one back-substitution: every solve meets
    ``rtol`` as before.  Measured on the quarter model (docs/forward-model.md): a `fine` sample's
    two factorisations and solves (66 851 unknowns) 14.0 → 8.3 s; `coarse` (18 191) would be slower
    (0.84 → 0.93 s) and a `default` sample's factorisation and solves 7 % slower, so both stay below the
    size.  None: exact factors always.

    Single-precision factors (``single_min``): a matrix of at least ``single_min`` unknowns that is
    not factorised block low-rank is factorised in float32 (MUMPS ``smumps``); CG in double on those
    factors meets ``rtol`` as with block low-rank factors (about three iterations on the `default`
    level).  Should MUMPS fail in single precision (a pivot lost to rounding) or CG not converge on
    K's own single-precision factors, this solver factorises in double from then on.  None: double
    always.

    Another solver's factors (:meth:`borrow`): a solve of another kind on the same mesh and
    constraints (the inclusion press on the reference press's factors) by CG, without
    factorising (``fem.Model._borrow`` decides when)."""

    def __init__(
        self,
        name: str = "recycled",
        rtol: float = CG_RTOL,
        max_it: int = 30,
        refactor_after: int | None = None,
        blr_min: int | None = BLR_MIN_UNKNOWNS,
        blr_tol: float = BLR_TOLERANCE,
        single_min: int | None = SINGLE_MIN_UNKNOWNS,
    ):
        self.prefix = f"elastimap_{id(self)}_{name}_"
        # no option before the first factorisation: a solver that only borrows (the inclusion press
        # of a shared sample) leaves none unread
        self.ksp = mumps_ksp(self.prefix, "cg", "cholesky", workspace=False)
        self.ksp.setTolerances(rtol=rtol, atol=0.0, max_it=max_it)
        self.blr_min, self.blr_tol = blr_min, float(blr_tol)
        self.blr = False  # whether the factors of K₀ are block low-rank (approximate)
        self.single_min = single_min
        self.single = False  # whether the factors of K₀ are single precision (approximate)
        self.K0: PETSc.Mat | None = None  # the factorised matrix
        self.key: bytes | None = None
        self.tag = None  # what the caller said of K₀ when it was factorised (``solve(tag=)``)
        self.refactor_after = refactor_after
        self.last = (0, None)  # (CG iterations, tag) of the last solve
        self.factorisations = 0
        self.iterations = 0  # CG iterations with another matrix's factors
        self.borrowed = 0  # solves by another solver's factors (:meth:`borrow`)
        self._borrowed_K = None  # (K, key) of the last solve when it was borrowed (for ``resolve``)

    def _factorise(self, K: PETSc.Mat, key: bytes, tag) -> None:
        if self.K0 is not None and key == self.key and self.K0.getSize() == K.getSize():
            K.copy(self.K0, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        else:
            if self.K0 is not None:
                self.K0.destroy()
            self.ksp.reset()  # new constraint set: new symbolic factorisation
            self.K0 = K.duplicate(copy=True)
            n = K.getSize()[0]
            self.blr = self.blr_min is not None and n >= self.blr_min
            self.single = not self.blr and self.single_min is not None and n >= self.single_min
            opts = PETSc.Options()
            mumps_workspace(self.prefix)
            opts[f"{self.prefix}mat_mumps_icntl_35"] = 2 if self.blr else 0  # read at the symbolic factorisation
            opts[f"{self.prefix}mat_mumps_cntl_7"] = self.blr_tol if self.blr else 0.0
            opts[f"{self.prefix}pc_precision"] = "single" if self.single else "double"
            opts[f"{self.prefix}mat_mumps_icntl_7"] = SINGLE_ORDERING if self.single else 7  # 7: MUMPS's choice
        self.K0.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        self.K0.setOption(PETSc.Mat.Option.SPD, True)
        self.key, self.tag = key, tag
        self.factorisations += 1

    def solve(self, K: PETSc.Mat, f: PETSc.Vec, key: bytes, fresh: bool = False, tag=None) -> PETSc.Vec:
        """x = K⁻¹ f; ``fresh``: factorise K without trying the old factors (the caller knows
        it far from K₀, e.g. an inclusion modulus changed several-fold, from ``self.tag``);
        ``tag``: kept as ``self.tag`` when K is factorised."""
        K.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        K.setOption(PETSc.Mat.Option.SPD, True)
        self._borrowed_K = None
        x = K.createVecRight()
        same = not fresh and self.K0 is not None and key == self.key and self.K0.getSize() == K.getSize()
        equal = same and K.equal(self.K0)  # the same matrix again: its factors solve it exactly
        if same and not equal:
            self.ksp.setOperators(K, self.K0)  # K₀ unchanged: its factors are reused
            self.ksp.solve(f, x)
            if self.ksp.getConvergedReason() > 0:
                self.last = (self.ksp.getIterationNumber(), tag)
                self.iterations += self.last[0]
                return x
        self.last = (0, tag)
        if not equal:  # new constraints, far from K₀, or CG did not converge: K's own factors
            self._factorise(K, key, tag)
        reason = self._own_solve(K, f, x)
        if reason <= 0 and self.single:  # float32 factors failed or too poor: double from now on
            self.single_min = None
            self.K0.destroy()
            self.K0 = None
            self._factorise(K, key, tag)
            reason = self._own_solve(K, f, x)
        if reason <= 0:
            x.destroy()
            raise SolverError(f"linear solve failed (PETSc reason {reason})")
        return x

    def _own_solve(self, K: PETSc.Mat, f: PETSc.Vec, x: PETSc.Vec) -> int:
        """x = K⁻¹ f on K's own factors (K₀ = K): one back-substitution when they are exact, else CG
        on them to rtol; returns PETSc's converged reason."""
        self.ksp.setOperators(K, self.K0)
        if not (self.blr or self.single):
            self.ksp.setType("preonly")  # its own exact factors: one back-substitution, as LU.solve
        self.ksp.solve(f, x)  # approximate factors: CG on them to rtol
        reason = self.ksp.getConvergedReason()
        self.ksp.setType("cg")
        return reason

    def borrow(
        self,
        donor: Recycled,
        K: PETSc.Mat,
        f: PETSc.Vec,
        key: bytes,
        max_it: int,
        tag=None,
        start: PETSc.Vec | None = None,
        rtol: float | None = None,
    ) -> PETSc.Vec | None:
        r"""x = K⁻¹ f by CG preconditioned with ``donor``'s factors (another solve kind on the same
        mesh and constraints, e.g. the reference press for the inclusion press: K and K₀ differ by
        the inclusion's modulus, κ ≤ the ratio of the moduli), so that this solver need not
        factorise K; None (nothing changed) when the donor has no factors for ``key`` or CG did not
        reach its tolerance in ``max_it`` iterations.  The donor's factors and operators are left as
        they were; a :meth:`resolve` after a borrowed solve factorises K first (K₀ := K).

        ``start`` x₀ (e.g. the reference press's solution for the inclusion press): CG solves for the
        correction, $K v = f - K x_0$, $x = x_0 + v$, to ``rtol`` (default this solver's) relative to
        that residual — a tolerance on the difference of the two presses, not on x."""
        if donor.K0 is None or donor.key != key or donor.K0.getSize() != K.getSize():
            return None
        K.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        K.setOption(PETSc.Mat.Option.SPD, True)
        ksp = donor.ksp
        before = ksp.getOperators()[0]
        rtol0, atol, dtol, it0 = ksp.getTolerances()
        b = f
        if start is not None:
            b = f.duplicate()
            K.mult(start, b)
            b.aypx(-1.0, f)  # f − K x₀
        x = K.createVecRight()
        ksp.setTolerances(rtol=rtol or self.ksp.getTolerances()[0], atol=0.0, max_it=int(max_it))
        ksp.setOperators(K, donor.K0)  # the donor's K₀ unchanged: its factors are reused
        try:
            ksp.solve(b, x)
            ok = ksp.getConvergedReason() > 0
            n = ksp.getIterationNumber()
        finally:
            ksp.setTolerances(rtol=rtol0, atol=atol, max_it=it0)
            ksp.setOperators(before, donor.K0)
            if b is not f:
                b.destroy()
        if not ok:
            x.destroy()
            return None
        if start is not None:
            x.axpy(1.0, start)
        self.last = (n, tag)
        self.iterations += n
        self.borrowed += 1
        self._borrowed_K = (K, key)
        return x

    def resolve(self, f: PETSc.Vec) -> PETSc.Vec:
        """Solve with the matrix of the last :meth:`solve` (its values unchanged since); factorised
        first when that solve needed more than ``refactor_after`` CG iterations (or was borrowed,
        :meth:`borrow`: this solver holds no factors near K)."""
        if self._borrowed_K is not None:
            K, key = self._borrowed_K
            self._borrowed_K = None
            self._factorise(K, key, self.last[1])
            self.last = (0, self.tag)
            return self.solve(K, f, key, tag=self.tag)
        K = self.ksp.getOperators()[0]
        n, tag = self.last
        if self.refactor_after is not None and n > self.refactor_after:
            self._factorise(K, self.key, tag)  # K₀ := K: this and the next back-solves are exact
            self.last = (0, tag)
        return self.solve(K, f, self.key, tag=self.tag)

    def destroy(self) -> None:
        for obj in (self.ksp, self.K0):
            if obj is not None:
                obj.destroy()
        self.ksp = self.K0 = None
        opts = PETSc.Options()
        for name in (
            "mat_mumps_icntl_14",
            "mat_mumps_icntl_35",
            "mat_mumps_cntl_7",
            "pc_precision",
            "mat_mumps_icntl_7",
        ):
            opts.delValue(f"{self.prefix}{name}")
