r"""The probe–tissue interface Γ (the footprint): node pairs, surface mass matrix, contact laws.

The mesh carries coincident node pairs on Γ (t_i on the tissue, p_i on the probe),
so the interface conditions are imposed exactly on the discrete pairs, with no
penalty parameter.  With the normal gap $g_i = u_z(p_i) - u_z(t_i)$ (mm):

* ``tied`` (default), frictionless and closed: $g_i = 0$; tangential components
  independent (zero shear traction).  Valid while the contact pressure stays
  compressive, checked after every solve (:meth:`Interface.diagnostics`).
* ``contact``, frictionless unilateral contact (Signorini) at the pairs:

  $$ g_i \ge 0, \qquad p_i \ge 0, \qquad p_i \, g_i = 0, $$

  solved by the primal–dual active set of :func:`active_set` (one solve per iteration).
* ``bonded``: all three components tied (a glued probe; wrong for the sensor, offered
  for comparison).

The tied components are eliminated by :mod:`elastimap.solver.reduction`; this module
measures the interface.
"""

from __future__ import annotations

from . import _boot  # noqa: F401  (must precede dolfinx)

# isort: split

from typing import TYPE_CHECKING

import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from mpi4py import MPI
from petsc4py import PETSc

from .errors import SolverError
from .space import Space, petsc_matrix

if TYPE_CHECKING:
    import scipy.sparse as sp


class Interface:
    """Node pairs on Γ, the tissue-side surface mass matrix M_Γ and the patch incidence.

    ``pair_probe[i]`` and ``pair_tissue[i]`` are the probe and tissue nodes of pair i,
    ordered by (y, x).
    """

    def __init__(self, space: Space):
        X, tol = space.X, space.tol
        on_gamma = space.on_footprint(X.T)
        gp = np.flatnonzero(on_gamma & space.is_probe)
        gt = np.flatnonzero(on_gamma & ~space.is_probe)
        if len(gp) != len(gt) or len(gp) == 0:
            raise SolverError(f"interface node pairing failed ({len(gp)} probe vs {len(gt)} tissue nodes)")
        kp = np.lexsort(np.round(X[gp, :2] / tol).T[::-1])
        kt = np.lexsort(np.round(X[gt, :2] / tol).T[::-1])
        gp, gt = gp[kp], gt[kt]
        if np.max(np.abs(X[gp] - X[gt])) > 10 * tol:
            raise SolverError("interface node pairs do not coincide")
        self.pair_probe, self.pair_tissue = gp, gt
        self.npairs = len(gt)
        # M_Γ as CSR arrays (indptr, indices, values) over the pairs; held by numpy and PETSc, not
        # scipy, so that a linear solve needs no scipy (0.13 s of a `solve` process's imports)
        self.M_csr = self._surface_mass(space)
        indptr, indices, values = self.M_csr
        # patch incidence: S_ij = 1 when interface nodes i and j share a facet (the pattern of M_Γ)
        nz = values != 0
        self._patch = (np.repeat(np.arange(self.npairs), np.diff(indptr))[nz], indices[nz])
        self._mass_ksp = None  # M_Γ's factorisation (``contact_pressure``), made on first use

    @property
    def M_gamma(self) -> sp.csr_matrix:
        """M_Γ as a scipy CSR matrix (:class:`Friction`)."""
        import scipy.sparse as sp

        indptr, indices, values = self.M_csr
        return sp.csr_matrix((values, indices, indptr), shape=(self.npairs, self.npairs))

    def _surface_mass(self, space: Space) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r"""Consistent surface mass matrix of the tissue side of Γ at the pairs (mm²):

        $$ (M_\Gamma)_{ij} = \int_{\Gamma} \phi_i \, \phi_j \, {\rm d}s , $$

        φ_i the scalar P_k basis function of tissue node t_i (assembled as the z-z block
        of ∫_Γ u_z v_z ds over the tissue-side facets).
        """
        msh, fdim = space.mesh, 2
        msh.topology.create_connectivity(fdim, 3)
        facets = dmesh.locate_entities_boundary(msh, fdim, space.on_footprint)
        f2c = msh.topology.connectivity(fdim, 3)
        tissue_facets = np.array([f for f in facets if not space.probe_cell[f2c.links(f)[0]]], dtype=np.int32)
        # the integration entities (cell, local facet) given directly, as DOLFINx derives them from
        # facet tags, without the tags' check against the exterior facets (np.intersect1d, whose
        # np.unique imports numpy.ma: 0.02 s of a `solve` process; docs/forward-model.md, 'Speed'):
        # Γ's facets are on the boundary of both bodies
        msh.topology.create_connectivity(3, fdim)
        entities = fem.compute_integration_domains(
            fem.IntegralType.exterior_facet, msh.topology, np.sort(tissue_facets)
        )
        ds = ufl.Measure("ds", domain=msh, subdomain_data=[(1, entities)])
        u, v = ufl.TrialFunction(space.V), ufl.TestFunction(space.V)
        m = fem.form(u[2] * v[2] * ds(1))
        values, M = petsc_matrix(m)
        fem.assemble_matrix(values, m)
        M.assemble()
        rows = PETSc.IS().createGeneral((3 * self.pair_tissue + 2).astype(PETSc.IntType), comm=MPI.COMM_SELF)
        Mp = M.createSubMatrix(rows, rows)  # M[idx][:, idx] in the pairs' order, columns ascending
        indptr, indices, values = (a.copy() for a in Mp.getValuesCSR())
        for obj in (Mp, rows, M):
            obj.destroy()
        return indptr, indices, values

    # ------------------------------------------------------------------ measures of a solution
    def gap(self, u: np.ndarray) -> np.ndarray:
        r"""Normal gap $g_i = u_z(p_i) - u_z(t_i)$ at the pairs (mm, ≥ 0 = no penetration)."""
        return u[3 * self.pair_probe + 2] - u[3 * self.pair_tissue + 2]

    def contact_pressure(self, reaction: np.ndarray) -> np.ndarray:
        r"""Normal contact pressure p (kPa, compressive > 0) at the tissue nodes of the pairs,
        recovered from the nodal reaction r = A u (mN) by

        $$ M_\Gamma \, p = -r_\Gamma . $$
        """
        if self._mass_ksp is None:
            indptr, indices, values = self.M_csr
            M = PETSc.Mat().createAIJ(
                size=(self.npairs, self.npairs),
                csr=(indptr.astype(PETSc.IntType), indices.astype(PETSc.IntType), values),
                comm=MPI.COMM_SELF,
            )
            M.assemble()
            ksp = PETSc.KSP().create(MPI.COMM_SELF)
            ksp.setType("preonly")
            ksp.getPC().setType("lu")  # PETSc's own sparse LU: M_Γ is small (a few hundred pairs)
            ksp.setOperators(M)
            M.destroy()  # the KSP holds it
            self._mass_ksp = ksp
        b = PETSc.Vec().createWithArray(-reaction[3 * self.pair_tissue + 2], comm=MPI.COMM_SELF)
        p = b.duplicate()
        self._mass_ksp.solve(b, p)
        out = p.getArray().copy()
        b.destroy()
        p.destroy()
        return out

    def patch_force(self, reaction: np.ndarray) -> np.ndarray:
        r"""Compressive normal force (mN) on each pair's patch of facets,

        $$ f_i = -\sum_{j \in {\rm patch}(i)} r_{z}(t_j) . $$

        The patch sum of nodal forces is a positive-weighted average of the pressure
        around the node, so its sign is robust to the oscillation of the recovered
        pressure next to the flat-punch edge singularity.  It is the tension criterion
        of the active set and of the tied-interface check.
        """
        rows, cols = self._patch
        return np.bincount(rows, weights=-reaction[3 * self.pair_tissue + 2][cols], minlength=self.npairs)

    def diagnostics(self, u: np.ndarray, reaction: np.ndarray, active: np.ndarray) -> dict[str, float]:
        """Pressure range (kPa), tensile patch fraction, open pairs, smallest gap (mm)."""
        pf = self.patch_force(reaction)
        pres = self.contact_pressure(reaction)
        pc = pres[active] if active.any() else np.zeros(1)
        return {
            "pressure_mean_kPa": float(np.mean(pc)),
            "pressure_min_kPa": float(np.min(pres)),
            "pressure_max_kPa": float(np.max(pres)),
            # patches whose net normal force is tensile (> 1e-6 of the mean patch force)
            "tension_patch_fraction": float(np.mean(pf < -1e-6 * max(float(np.mean(np.abs(pf))), 1e-300))),
            "open_pair_fraction": float(np.mean(~active)),
            "gap_min_mm": float(np.min(self.gap(u))),
        }

    def destroy(self) -> None:
        if self._mass_ksp is not None:
            self._mass_ksp.destroy()
            self._mass_ksp = None


class Friction:
    r"""Interface friction switch (``Discretisation.friction_kt`` = k_t, kPa/mm).

    A tangential spring between the paired nodes of the tied/contact interface,

    $$
    s(u, v) = k_t \int_\Gamma (u_{p,t} - u_{t,t}) \cdot (v_{p,t} - v_{t,t}) \, {\rm d}s,
    \qquad t = x, y,
    $$

    discretised with M_Γ over the active pairs:

    $$ S = k_t \sum_{c = x, y} B_c^{T} M_\Gamma B_c, \qquad (B_c u)_i = u_c(p_i) - u_c(t_i) $$

    (k_t M_Γ is in kPa·mm = mN/mm like A).  The reduced operator becomes
    K = PᵀAP + PᵀSP.  k_t = 0 is the frictionless interface; k_t → ∞ ties the
    tangential components (the ``bonded`` limit).  The natural scale is the tissue's
    E_t / T = 0.25 kPa/mm.
    """

    def __init__(self, interface: Interface, kt: float, ndofs: int):
        self.interface, self.kt, self.ndofs = interface, float(kt), ndofs
        self._key = None
        self._cached = None

    def matrix(self, active: np.ndarray) -> sp.csr_matrix:
        """S over the active pairs (mN/mm, all flat dofs; scipy)."""
        import scipy.sparse as sp

        itf, n = self.interface, self.ndofs
        m = itf.npairs
        D = sp.diags(active.astype(float))
        Mact = (D @ itf.M_gamma @ D).tocsr()
        S = sp.csr_matrix((n, n))
        for comp in (0, 1):
            B = sp.csr_matrix(
                (
                    np.r_[np.ones(m), -np.ones(m)],
                    (np.r_[np.arange(m), np.arange(m)], np.r_[3 * itf.pair_probe + comp, 3 * itf.pair_tissue + comp]),
                ),
                shape=(m, n),
            )
            S = S + B.T @ Mact @ B
        return (self.kt * S).tocsr()

    def matrices(self, active: np.ndarray, Psp: sp.csr_matrix) -> tuple[sp.csr_matrix, PETSc.Mat]:
        """(S, PᵀSP as PETSc) for this active set, cached by the set."""
        key = active.tobytes()
        if self._key != key:
            S = self.matrix(active)
            Sr = (Psp.T @ S @ Psp).tocsr()
            Sr.sort_indices()
            if self._cached is not None:
                self._cached[1].destroy()
            Sm = PETSc.Mat().createAIJ(
                size=Sr.shape,
                csr=(Sr.indptr.astype(PETSc.IntType), Sr.indices.astype(PETSc.IntType), Sr.data),
                comm=MPI.COMM_SELF,
            )
            Sm.assemble()
            self._cached = (S, Sm)
            self._key = key
        return self._cached

    def destroy(self) -> None:
        if self._cached is not None:
            self._cached[1].destroy()
            self._cached = None


def active_set(
    solve_with, patch_force, gap, active0: np.ndarray, *, gap_tol: float, force_tol: float = 1e-6, max_iter: int = 30
):
    r"""Primal–dual active-set iteration for frictionless unilateral contact at node pairs.

    ``solve_with(active)`` solves with the ``active`` nodes closed (normal
    displacement tied or prescribed); ``patch_force(sol)`` is the compressive
    normal force on each node's facet patch (mN); ``gap(sol)`` the normal gap
    (mm, negative = penetration).  The next active set is

    $$
    \mathcal{A}^{k+1} = \{ i \in \mathcal{A}^k : f_i > -\epsilon_f \bar f \}
                 \cup \{ i \notin \mathcal{A}^k : g_i < -\epsilon_g \},
    $$

    a closed node opening when its patch force is tensile (below ``-force_tol`` times
    the mean |patch force| $\bar f$), an open node closing when it penetrates by more
    than ``gap_tol``.  Stops when the set no longer changes (a cycle closes the union
    of the cycling sets); returns (solution, active set, iterations).
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
