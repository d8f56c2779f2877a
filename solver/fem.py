"""Linear-elastic finite-element model of the probe pressing the tissue (DOLFINx 0.11).

Bodies Ω = Ω_tissue ∪ Ω_inclusion ∪ Ω_skin (one tissue body) and Ω_probe (three
PDMS layers) are linear, isotropic and bonded internally.  For the
displacement u (mm) with test function v:

    a(u, v) = ∫_Ω σ(u) : ε(v) dx,     ε(u) = ½(∇u + ∇uᵀ),
    σ(u)   = 2 μ ε(u) + λ tr ε(u) I,  μ = E / (2(1+ν)),  λ = E ν / ((1+ν)(1−2ν))

with E in kPa, so σ is in kPa and nodal forces in kPa·mm² = mN.  P2
(quadratic) tetrahedra are used by default because P1 locks at ν = 0.49.

Boundary conditions: u = 0 on the chest wall z = 0; u = (0, 0, −δ) on the
probe top (bonded to the rigid plate); u·n = 0 on the symmetry planes of the
quarter model; the tissue surface outside the probe is traction-free.

Probe–tissue interface Γ (the footprint).  The mesh carries coincident node
pairs (t_i on the tissue, p_i on the probe) on Γ, so the conditions are
imposed exactly on the discrete pairs, with no penalty parameter:

* ``tied``    (default) frictionless, closed: u_z(t_i) = u_z(p_i); tangential
  components independent (zero shear traction).  Valid while the contact
  pressure stays compressive; this is checked after every solve.
* ``contact`` frictionless unilateral contact: u_z(t_i) ≤ u_z(p_i) with
  contact pressure p_i ≥ 0 and p_i·gap_i = 0, solved by a primal–dual active
  set iteration (each iteration is one linear solve).
* ``bonded``  all three components tied (a glued probe; wrong for the sensor,
  offered for comparison).

Constraints are applied by elimination: u = P ū + u_D, where P maps the free
unknowns ū to all nodal values (a tied tissue value copies its probe
partner) and u_D carries the prescribed values.  The reduced system
Pᵀ A P ū = −Pᵀ A u_D is factorised with MUMPS.  The contact pressure p on Γ
is recovered from the nodal reaction r = A u by the consistent surface mass
matrix, M_Γ p = −r_Γ.

Effect switches (both off by default; the default path is unchanged):

* **Interface friction** ``Discretisation.friction_kt`` = k_t (kPa/mm): a
  tangential spring between the paired nodes of the tied/contact interface,

      s(u, v) = k_t ∫_Γ (u_p,t − u_t,t) · (v_p,t − v_t,t) ds,   t = x, y,

  discretised with the tissue-side consistent surface mass matrix M_Γ
  (mm²) of the pairs: S = k_t Σ_{c=x,y} B_cᵀ M_Γ B_c with B_c u = u_p,c − u_t,c
  (only pairs in the active set).  k_t M_Γ is in kPa·mm = mN/mm like A.  The
  reduced operator becomes K = Pᵀ A P + Pᵀ S P.  k_t = 0 is the frictionless
  interface; k_t → ∞ ties the tangential components (the ``bonded`` limit).
  The natural scale is the tissue's E_t / T = 0.25 kPa/mm.
* **Tissue nonlinearity** ``Tissue.nonlinearity`` = β ∈ [0, 1]: the tissue,
  skin and inclusion get the stored energy (kPa)

      ψ = (1 − β) ψ_lin + β ψ_NH,
      ψ_lin = μ ε:ε + ½ λ (tr ε)²,
      ψ_NH  = ½ μ (I_C − 3) − μ ln J + ½ λ (ln J)²   (compressible neo-Hookean),
      F = I + ∇u,  C = Fᵀ F,  I_C = tr C,  J = det F,

  with the same μ, λ as the linear model, so that ψ_NH → ψ_lin for small
  strain; β = 1 is the plain neo-Hookean solid.  The probe PDMS stays linear
  (it is 10–60 times stiffer than the tissue, so its strains are small).  The
  residual R(u; v) = ∫ ∂ψ/∂F : ∇v dx and its Jacobian are UFL derivatives;
  Newton runs on the reduced system, P̄ᵀ J P̄ Δū = −Pᵀ R(P ū + u_D), started
  from the linear solution, with backtracking when a step inverts an element
  (J ≤ 0) or raises the residual.  The interface pairs are the coincident
  nodes of the reference configuration (small tangential sliding assumed).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from . import _boot  # noqa: F401  (must precede dolfinx)

import numpy as np
import scipy.sparse as sp
import ufl
from dolfinx import fem, geometry, mesh as dmesh
from dolfinx.fem import petsc as fpetsc
from mpi4py import MPI
from petsc4py import PETSc

from .geometry import INCLUSION, PROBE_LAYER0, SKIN, TISSUE, RawMesh
from .params import SolveParams


_DEBUG = bool(__import__("os").environ.get("ELASTIMAP_NEWTON_DEBUG"))


class SolverError(RuntimeError):
    """A solve failed (no convergence, singular system, bad mesh); carries the parameters."""


def epsilon(u):
    """Small-strain tensor ε(u) = ½(∇u + ∇uᵀ) (dimensionless)."""
    return ufl.sym(ufl.grad(u))


def sigma(u, E, nu):
    """Linear isotropic stress σ = 2μ ε + λ tr(ε) I (kPa) for E in kPa."""
    mu = E / (2 * (1 + nu))
    lmbda = E * nu / ((1 + nu) * (1 - 2 * nu))
    return 2 * mu * epsilon(u) + lmbda * ufl.tr(epsilon(u)) * ufl.Identity(len(u))


def psi_linear(u, E, nu):
    """Linear-elastic stored energy ψ_lin = μ ε:ε + ½ λ (tr ε)² (kPa)."""
    mu = E / (2 * (1 + nu))
    lmbda = E * nu / ((1 + nu) * (1 - 2 * nu))
    eps = epsilon(u)
    return mu * ufl.inner(eps, eps) + 0.5 * lmbda * ufl.tr(eps) ** 2


def psi_neo_hookean(u, E, nu):
    """Compressible neo-Hookean stored energy ψ_NH = ½ μ (I_C − 3) − μ ln J + ½ λ (ln J)² (kPa).

    F = I + ∇u, I_C = tr(FᵀF), J = det F; the same Lamé constants as :func:`sigma`,
    so its linearisation at u = 0 is the linear model."""
    mu = E / (2 * (1 + nu))
    lmbda = E * nu / ((1 + nu) * (1 - 2 * nu))
    F = ufl.Identity(len(u)) + ufl.grad(u)
    Ic = ufl.tr(F.T * F)
    lnJ = ufl.ln(ufl.det(F))
    return 0.5 * mu * (Ic - 3) - mu * lnJ + 0.5 * lmbda * lnJ ** 2


@dataclass
class LinearSolution:
    u: np.ndarray          # all nodal values, flat (3 per node)
    reaction: np.ndarray   # r = A u (mN), flat
    iterations: int


def active_set(solve_with, patch_force, gap, active0: np.ndarray, *, gap_tol: float,
               force_tol: float = 1e-6, max_iter: int = 30):
    """Primal–dual active-set iteration for frictionless unilateral contact at node pairs.

    ``solve_with(active)`` solves with the ``active`` nodes closed (normal
    displacement tied or prescribed); ``patch_force(sol)`` is the compressive
    normal force on each node's facet patch (mN); ``gap(sol)`` the normal gap
    (mm, negative = penetration).  A closed node opens when its patch force
    is tensile (below ``-force_tol`` times the mean |patch force|), an open
    node closes when it penetrates by more than ``gap_tol``.  Stops when the
    set no longer changes (a cycle closes the union of the cycling sets); returns
    (solution, active set, iterations).
    """
    active = active0.copy()
    seen = {active.tobytes()}
    for its in range(1, max_iter + 1):
        sol = solve_with(active)
        pf = patch_force(sol)
        fscale = max(float(np.mean(np.abs(pf))), 1e-300)
        g = gap(sol)
        new = (active & (pf > -force_tol * fscale)) | (~active & (g < -gap_tol))
        if np.array_equal(new, active):
            return sol, active, its
        if new.tobytes() in seen:
            # a cycle (a node chattering at the contact edge within tolerance):
            # close the union, which admits no penetration, and stop
            active = active | new
            return solve_with(active), active, its + 1
        seen.add(new.tobytes())
        active = new
    raise SolverError(f"contact active set did not settle in {max_iter} iterations")


class Model:
    """One mesh, its function space, operators and constraint bookkeeping.

    Built once per sample and reused by the inclusion solve and the reference
    solve (same mesh, same sparsity, same symbolic factorisation when the
    interface set does not change).
    """

    def __init__(self, raw: RawMesh, p: SolveParams):
        t0 = time.perf_counter()
        self.p = p
        comm = MPI.COMM_SELF
        coord_el = ufl.Mesh(__import__("basix").ufl.element("Lagrange", "tetrahedron", 1, shape=(3,)))
        self.mesh = dmesh.create_mesh(comm, raw.cells, coord_el, raw.x)
        msh = self.mesh
        tdim = 3
        self.markers = raw.markers[msh.topology.original_cell_index].astype(np.int32)
        ncells = msh.topology.index_map(tdim).size_local
        self.ncells = ncells
        V = fem.functionspace(msh, ("Lagrange", p.disc.degree, (3,)))
        self.V = V
        Q = fem.functionspace(msh, ("DG", 0))
        self.E = fem.Function(Q, name="E")
        self.nu = fem.Function(Q, name="nu")
        self._set_materials(p.inclusion.E)
        u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
        self.a = fem.form(ufl.inner(sigma(u, self.E, self.nu), epsilon(v)) * ufl.dx)

        # ---- dof classification (block = node of the P2 space) ----------------
        X = V.tabulate_dof_coordinates()
        nb = X.shape[0]
        self.nblocks = nb
        self.X = X
        cell_dofs = V.dofmap.list
        probe_cell = self.markers >= PROBE_LAYER0
        self.probe_cells = np.flatnonzero(probe_cell).astype(np.int32)
        is_probe = np.zeros(nb, dtype=bool)
        is_probe[np.unique(cell_dofs[probe_cell])] = True
        self.is_probe = is_probe
        T, H, P = p.tissue.thickness, p.probe.height, p.probe.size
        tol = 1e-6 * max(T, P)
        x, y, z = X[:, 0], X[:, 1], X[:, 2]
        self.top = np.flatnonzero(is_probe & (np.abs(z - (T + H)) < tol))
        self.bottom = np.flatnonzero(~is_probe & (np.abs(z) < tol))
        self.sym_x = np.flatnonzero(np.abs(x) < tol) if p.disc.symmetry == "quarter" else np.empty(0, int)
        self.sym_y = np.flatnonzero(np.abs(y) < tol) if p.disc.symmetry == "quarter" else np.empty(0, int)
        on_gamma = (np.abs(z - T) < tol) & (np.abs(x) <= P / 2 + tol) & (np.abs(y) <= P / 2 + tol)
        gp = np.flatnonzero(on_gamma & is_probe)
        gt = np.flatnonzero(on_gamma & ~is_probe)
        if len(gp) != len(gt) or len(gp) == 0:
            raise SolverError(f"interface node pairing failed ({len(gp)} probe vs {len(gt)} tissue nodes)")
        kp = np.lexsort(np.round(X[gp, :2] / tol).T[::-1])
        kt = np.lexsort(np.round(X[gt, :2] / tol).T[::-1])
        gp, gt = gp[kp], gt[kt]
        if np.max(np.abs(X[gp] - X[gt])) > 10 * tol:
            raise SolverError("interface node pairs do not coincide")
        self.pair_probe, self.pair_tissue = gp, gt

        # ---- consistent surface mass matrix on the tissue side of Γ ----------
        fdim = 2
        msh.topology.create_connectivity(fdim, tdim)
        facets = dmesh.locate_entities_boundary(
            msh, fdim, lambda xx: (np.abs(xx[2] - T) < tol) & (np.abs(xx[0]) <= P / 2 + tol) & (np.abs(xx[1]) <= P / 2 + tol))
        f2c = msh.topology.connectivity(fdim, tdim)
        tissue_facets = np.array([f for f in facets if not probe_cell[f2c.links(f)[0]]], dtype=np.int32)
        ft = dmesh.meshtags(msh, fdim, np.sort(tissue_facets), np.ones(len(tissue_facets), dtype=np.int32))
        ds = ufl.Measure("ds", domain=msh, subdomain_data=ft)
        m_form = fem.form(u[2] * v[2] * ds(1))
        M = fpetsc.assemble_matrix(m_form)
        M.assemble()
        Mi, Mj, Mv = M.getValuesCSR()
        Mfull = sp.csr_matrix((Mv, Mj, Mi), shape=M.getSize())
        M.destroy()
        idx = 3 * gt + 2
        self.M_gamma = sp.csc_matrix(Mfull[idx][:, idx])
        # patch incidence: S_ij = 1 when interface nodes i and j share a facet
        self.S_patch = (abs(self.M_gamma) > 0).astype(float).tocsr()

        # ---- image sampling points on the probe bottom ------------------------
        from .image import pixel_centres
        c = pixel_centres(P, p.image.pixel)
        if p.disc.symmetry == "quarter":
            c = c[c > 0]
        gx, gy = np.meshgrid(c, c)   # rows = y, cols = x
        pts = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, T)])
        tree = geometry.bb_tree(msh, tdim, entities=self.probe_cells)
        cand = geometry.compute_collisions_points(tree, pts)
        cells = geometry.compute_colliding_cells(msh, cand, pts)
        owner = np.array([cells.links(i)[0] if len(cells.links(i)) else -1 for i in range(len(pts))], dtype=np.int32)
        if np.any(owner < 0):
            raise SolverError("image pixels fall outside the probe mesh")
        self.img_pts, self.img_cells, self.img_shape = pts, owner, gx.shape

        self.A = fpetsc.create_matrix(self.a)
        self.kt = float(p.disc.friction_kt) if p.disc.interface != "bonded" else 0.0
        self._S_key = None
        self._S_red = None
        self.beta = None
        if p.tissue.nonlinearity > 0:
            # β per cell: the tissue bodies blend towards neo-Hookean, the probe stays linear
            self.beta = fem.Function(Q, name="beta")
            b = np.where(probe_cell, 0.0, float(p.tissue.nonlinearity))
            self.beta.x.array[: len(b)] = b
            self.u_fun = fem.Function(V, name="u")
            psi = ((1 - self.beta) * psi_linear(self.u_fun, self.E, self.nu)
                   + self.beta * psi_neo_hookean(self.u_fun, self.E, self.nu))
            # quadrature of degree 2(k-1): exact for the linear part (∇u of P_k is P_{k-1}), like a(u, v)
            dxq = ufl.dx(metadata={"quadrature_degree": max(2 * (p.disc.degree - 1), 1)})
            R = ufl.derivative(psi * dxq, self.u_fun, v)
            self.R_form = fem.form(R)
            self.J_form = fem.form(ufl.derivative(R, self.u_fun, u))
            self.Jmat = fpetsc.create_matrix(self.J_form)
            self._KJ = None
            self._KJ_key = None
        self.ndofs = 3 * nb
        self._ksp = None
        self._K = None
        self._P = None
        self._P_key = None
        self.timings = {"setup": time.perf_counter() - t0}

    # ------------------------------------------------------------------------
    def _set_materials(self, E_inclusion: float) -> None:
        p = self.p
        E = np.empty(len(self.markers))
        nu = np.empty(len(self.markers))
        E[self.markers == TISSUE], nu[self.markers == TISSUE] = p.tissue.E, p.tissue.nu
        E[self.markers == SKIN], nu[self.markers == SKIN] = p.tissue.skin_E, p.tissue.nu
        E[self.markers == INCLUSION], nu[self.markers == INCLUSION] = E_inclusion, p.inclusion.nu
        for i, (_th, El) in enumerate(p.probe.layers):
            sel = self.markers == PROBE_LAYER0 + i
            E[sel], nu[sel] = El, p.probe.nu
        self.E.x.array[: len(E)] = E
        self.nu.x.array[: len(nu)] = nu

    def _tick(self, key: str, t0: float) -> float:
        t = time.perf_counter()
        self.timings[key] = self.timings.get(key, 0.0) + t - t0
        return t

    def _constraints(self, delta: float, active: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Column of every flat dof in ū (−1 for prescribed) and the prescribed values u_D."""
        n = 3 * self.nblocks
        fixed = np.zeros(n, dtype=bool)
        uD = np.zeros(n)
        for comp in range(3):
            fixed[3 * self.bottom + comp] = True
            fixed[3 * self.top + comp] = True
        uD[3 * self.top + 2] = -delta
        fixed[3 * self.sym_x + 0] = True
        fixed[3 * self.sym_y + 1] = True
        master = np.arange(n)
        comps = (0, 1, 2) if self.p.disc.interface == "bonded" else (2,)
        for comp in comps:
            s = 3 * self.pair_tissue[active] + comp
            m = 3 * self.pair_probe[active] + comp
            fixed[s] |= fixed[m]
            master[s[~fixed[s]]] = m[~fixed[s]]
        free = ~fixed & (master == np.arange(n))
        col = np.full(n, -1, dtype=np.int64)
        col[free] = np.arange(np.count_nonzero(free))
        slave = ~fixed & ~free
        col[slave] = col[master[slave]]
        return col, uD, fixed

    def _reduction(self, delta: float, active: np.ndarray):
        """(P as PETSc, P as scipy CSR, u_D, new_pattern) for this active set, cached by the set."""
        key = active.tobytes()
        col, uD, fixed = self._constraints(delta, active)
        if self._P_key == key:
            return self._P, self._Psp, uD, False
        n = len(col)
        rows = np.flatnonzero(col >= 0)
        nfree = int(col.max()) + 1
        Pcsr = sp.csr_matrix((np.ones(len(rows)), (rows, col[rows])), shape=(n, nfree))
        if self._P is not None:
            self._P.destroy()
        self._P = PETSc.Mat().createAIJ(size=(n, nfree), csr=(Pcsr.indptr.astype(PETSc.IntType),
                                                              Pcsr.indices.astype(PETSc.IntType), Pcsr.data),
                                        comm=MPI.COMM_SELF)
        self._P.assemble()
        self._Psp = Pcsr
        self._P_key = key
        return self._P, Pcsr, uD, True

    def friction_matrix(self, active: np.ndarray) -> sp.csr_matrix:
        """S = k_t Σ_{c=x,y} B_cᵀ M_Γ B_c over the active pairs (mN/mm, full flat dofs; scipy)."""
        n = 3 * self.nblocks
        m = len(self.pair_tissue)
        D = sp.diags(active.astype(float))
        Mact = (D @ self.M_gamma @ D).tocsr()
        S = sp.csr_matrix((n, n))
        for comp in (0, 1):
            B = sp.csr_matrix((np.r_[np.ones(m), -np.ones(m)],
                               (np.r_[np.arange(m), np.arange(m)],
                                np.r_[3 * self.pair_probe + comp, 3 * self.pair_tissue + comp])), shape=(m, n))
            S = S + B.T @ Mact @ B
        return (self.kt * S).tocsr()

    def _friction_reduced(self, active: np.ndarray, Psp: sp.csr_matrix) -> tuple[sp.csr_matrix, PETSc.Mat]:
        key = active.tobytes()
        if self._S_key != key:
            S = self.friction_matrix(active)
            Sr = (Psp.T @ S @ Psp).tocsr()
            Sr.sort_indices()
            if self._S_red is not None:
                self._S_red[1].destroy()
            Sm = PETSc.Mat().createAIJ(size=Sr.shape, csr=(Sr.indptr.astype(PETSc.IntType),
                                                            Sr.indices.astype(PETSc.IntType), Sr.data),
                                       comm=MPI.COMM_SELF)
            Sm.assemble()
            self._S_red = (S, Sm)
            self._S_key = key
        return self._S_red

    def _factor_solve(self, K: PETSc.Mat, f: PETSc.Vec, new_pattern: bool, which: str = "_ksp") -> PETSc.Vec:
        ksp = getattr(self, which, None)
        if ksp is None:
            ksp = PETSc.KSP().create(MPI.COMM_SELF)
            ksp.setType("preonly")
            pc = ksp.getPC()
            pc.setType("lu")
            pc.setFactorSolverType("mumps")
            ksp.setOptionsPrefix(f"elastimap_{id(self)}{which}_")
            opts = PETSc.Options()
            opts[f"elastimap_{id(self)}{which}_mat_mumps_icntl_14"] = 80  # workspace margin (%)
            ksp.setFromOptions()
            setattr(self, which, ksp)
        if new_pattern:
            ksp.reset()  # new constraint set: new symbolic factorisation
        ksp.setOperators(K)  # same pattern as last time: numeric refactorisation only
        ksp.setFromOptions()
        ubar = K.createVecRight()
        ksp.solve(f, ubar)
        reason = ksp.getConvergedReason()
        if reason < 0:
            ubar.destroy()
            raise SolverError(f"linear solve failed (PETSc reason {reason})")
        return ubar

    def solve_linear(self, E_inclusion: float, delta: float, active: np.ndarray | None = None) -> LinearSolution:
        """One linear solve with the pairs in ``active`` tied (all pairs when None)."""
        t = time.perf_counter()
        if active is None:
            active = np.ones(len(self.pair_tissue), dtype=bool)
        self._set_materials(E_inclusion)
        self.A.zeroEntries()
        fpetsc.assemble_matrix(self.A, self.a)
        self.A.assemble()
        t = self._tick("assemble", t)

        Pm, Psp, uD, new_pattern = self._reduction(delta, active)
        if new_pattern or self.kt > 0:
            # with friction K gets the extra Pᵀ S P pattern, so it is rebuilt from PᵀAP each time
            if self._K is not None:
                self._K.destroy()
            self._K = self.A.ptap(Pm)
            new_pattern = True
        else:
            self.A.ptap(Pm, result=self._K)
        K = self._K
        vD = PETSc.Vec().createWithArray(uD, comm=MPI.COMM_SELF)
        AuD = self.A.createVecLeft()
        self.A.mult(vD, AuD)
        f = K.createVecRight()
        Pm.multTranspose(AuD, f)
        if self.kt > 0:
            S, Sm = self._friction_reduced(active, Psp)
            K.axpy(1.0, Sm, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
            f.getArray()[:] += Psp.T @ (S @ uD)
        f.scale(-1.0)
        t = self._tick("ptap", t)

        ubar = self._factor_solve(K, f, new_pattern)
        t = self._tick("factor_solve", t)

        u_vec = AuD.duplicate()
        Pm.mult(ubar, u_vec)
        u = u_vec.getArray().copy() + uD
        r_vec = AuD.duplicate()
        self.A.mult(PETSc.Vec().createWithArray(u, comm=MPI.COMM_SELF), r_vec)
        r = r_vec.getArray().copy()
        for vec in (vD, AuD, f, ubar, u_vec, r_vec):
            vec.destroy()
        if not np.all(np.isfinite(u)):
            raise SolverError("the solve produced non-finite displacements")
        self._tick("post", t)
        return LinearSolution(u=u, reaction=r, iterations=1)

    def _residual(self, u: np.ndarray) -> np.ndarray:
        """Internal nodal force R(u) (mN, full flat dofs), without the friction spring."""
        self.u_fun.x.array[: len(u)] = u
        return fem.assemble_vector(self.R_form).array[: len(u)].copy()

    def solve_nonlinear(self, E_inclusion: float, delta: float, active: np.ndarray | None = None,
                        rtol: float = 1e-9, max_iter: int = 30) -> LinearSolution:
        """Newton on the reduced system for the finite-strain tissue (``Tissue.nonlinearity`` > 0).

        Predictor: the linear solution; each step solves P̄ᵀ(J + S)P̄ Δū = −Pᵀ(R + S u) and
        halves the step while it makes a non-finite residual (an inverted element) or raises
        ‖Pᵀ(R + S u)‖.  Converged when the reduced residual falls below ``rtol`` times the
        norm of the internal force of the predictor.  ``iterations`` counts the linear solves."""
        if active is None:
            active = np.ones(len(self.pair_tissue), dtype=bool)
        lin = self.solve_linear(E_inclusion, delta, active)
        t = time.perf_counter()
        Pm, Psp, uD, _ = self._reduction(delta, active)
        S = self._friction_reduced(active, Psp)[0] if self.kt > 0 else None
        u = lin.u.copy()

        def reduced_res(uu):
            r = self._residual(uu)
            g = Psp.T @ (r + (S @ uu if S is not None else 0.0))
            return r, g

        r, g = reduced_res(u)
        scale = max(float(np.linalg.norm(Psp.T @ np.abs(lin.reaction))), 1e-300)
        gnorm = float(np.linalg.norm(g))
        its = 1
        t = self._tick("newton", t)
        for _ in range(max_iter):
            if gnorm <= rtol * scale:
                break
            self.Jmat.zeroEntries()
            fpetsc.assemble_matrix(self.Jmat, self.J_form)
            self.Jmat.assemble()
            key = active.tobytes()
            if self._KJ is None or self._KJ_key != key or self.kt > 0:
                if self._KJ is not None:
                    self._KJ.destroy()
                self._KJ = self.Jmat.ptap(Pm)
                new_pattern = True
            else:
                self.Jmat.ptap(Pm, result=self._KJ)
                new_pattern = False
            self._KJ_key = key
            if self.kt > 0:
                self._KJ.axpy(1.0, self._friction_reduced(active, Psp)[1],
                              structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
            f = self._KJ.createVecRight()
            f.getArray()[:] = -g
            dub = self._factor_solve(self._KJ, f, new_pattern, "_ksp_nl")
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
                raise SolverError("Newton line search failed (finite-strain tissue)")
            u, r, g, gnorm = u_try, r_try, g_try, gn_try
            if _DEBUG:
                print(f"newton {its}: step {step:g} |g|/scale {gnorm / scale:.3e}")
            t = self._tick("newton", t)
        else:
            raise SolverError(f"Newton did not converge in {max_iter} iterations "
                              f"(residual {gnorm:.3g}, scale {scale:.3g})")
        if not np.all(np.isfinite(u)):
            raise SolverError("the Newton solve produced non-finite displacements")
        return LinearSolution(u=u, reaction=r, iterations=its)

    def _solve_once(self, E_inclusion: float, delta: float, active: np.ndarray | None = None) -> LinearSolution:
        if self.beta is not None:
            return self.solve_nonlinear(E_inclusion, delta, active)
        return self.solve_linear(E_inclusion, delta, active)

    # ------------------------------------------------------------------------
    def contact_pressure(self, sol: LinearSolution) -> np.ndarray:
        """Normal contact pressure (kPa, compressive > 0) at the tissue-side interface nodes."""
        from scipy.sparse.linalg import spsolve

        r = sol.reaction[3 * self.pair_tissue + 2]
        return -spsolve(self.M_gamma, r)

    def patch_force(self, sol: LinearSolution) -> np.ndarray:
        """Compressive normal force (mN) on each interface node's patch of facets.

        The patch sum of nodal forces is a positive-weighted average of the
        pressure around the node, so its sign is robust to the oscillation of
        the recovered pressure next to the flat-punch edge singularity.  It is
        the tension criterion of the active set and of the tied-interface check.
        """
        return self.S_patch @ (-sol.reaction[3 * self.pair_tissue + 2])

    def gap(self, sol: LinearSolution) -> np.ndarray:
        """Normal gap u_z(probe) − u_z(tissue) at the interface pairs (mm, ≥ 0 = no penetration)."""
        return sol.u[3 * self.pair_probe + 2] - sol.u[3 * self.pair_tissue + 2]

    def plate_force(self, sol: LinearSolution) -> float:
        """Total force (mN) the plate applies on the probe, compressive positive, full probe."""
        f = -float(np.sum(sol.reaction[3 * self.top + 2]))
        return 4 * f if self.p.disc.symmetry == "quarter" else f

    def probe_bottom_w(self, sol: LinearSolution, delta: float) -> np.ndarray:
        """Deflection of the probe bottom relative to the plate, u_z + δ (mm), on the pixel grid."""
        t = time.perf_counter()
        uf = fem.Function(self.V)
        uf.x.array[: len(sol.u)] = sol.u
        vals = uf.eval(self.img_pts, self.img_cells)[:, 2]
        self._tick("image", t)
        return vals.reshape(self.img_shape) + delta

    def solve(self, E_inclusion: float, delta: float, max_iter: int = 30) -> tuple[LinearSolution, dict]:
        """Solve with the configured interface; returns the solution and interface diagnostics."""
        npairs = len(self.pair_tissue)
        if self.p.disc.interface == "contact":
            sol, active, its = active_set(
                lambda act: self._solve_once(E_inclusion, delta, act), self.patch_force, self.gap,
                np.ones(npairs, dtype=bool), gap_tol=1e-9 * delta, max_iter=max_iter)
        else:
            active = np.ones(npairs, dtype=bool)
            sol = self._solve_once(E_inclusion, delta, active)
            its = sol.iterations
        pf = self.patch_force(sol)
        sol.iterations = its
        pres = self.contact_pressure(sol)
        pc = pres[active] if active.any() else np.zeros(1)
        diag = {
            "pressure_mean_kPa": float(np.mean(pc)),
            "pressure_min_kPa": float(np.min(pres)),
            "pressure_max_kPa": float(np.max(pres)),
            # patches whose net normal force is tensile (> 1e-6 of the mean patch force)
            "tension_patch_fraction": float(np.mean(pf < -1e-6 * max(float(np.mean(np.abs(pf))), 1e-300))),
            "open_pair_fraction": float(np.mean(~active)),
            "gap_min_mm": float(np.min(self.gap(sol))),
        }
        return sol, diag

    def destroy(self) -> None:
        for name in ("_ksp", "_ksp_nl", "_K", "_KJ", "_P", "A", "Jmat"):
            obj = getattr(self, name, None)
            if obj is not None:
                obj.destroy()
            setattr(self, name, None)
        if self._S_red is not None:
            self._S_red[1].destroy()
            self._S_red = None
