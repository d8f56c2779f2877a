"""Hertz verification: a rigid sphere pressed into an elastic block with the contact code.

A rigid sphere of radius R moves down by δ onto the top face z = H of an
elastic block (quarter model, symmetry planes x = 0 and y = 0, bottom fixed).
Top-face nodes obey the unilateral condition u_z ≤ g0(r) − δ with the
initial gap g0(r) = r²/(2R) (the paraboloid of Hertz theory), solved with the same primal–dual active
set (:func:`elastimap.solver.interface.active_set`) and patch-force criterion as the probe
interface, closed nodes being prescribed on the sphere.

Hertz (elastic half-space, rigid sphere):

    F = 4/3 · E* · √R · δ^{3/2},   a = √(R δ),   E* = E / (1 − ν²)

in mN for E in kPa and lengths in mm.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from . import _boot  # noqa: F401

# isort: split

import numpy as np
import scipy.sparse as sp
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from dolfinx.fem import petsc as fpetsc
from mpi4py import MPI
from petsc4py import PETSc

from .interface import active_set
from .materials import epsilon, sigma


@dataclass
class HertzResult:
    force: float
    force_hertz: float
    radius: float
    radius_hertz: float
    ndofs: int
    iterations: int
    seconds: float

    @property
    def force_error(self) -> float:
        return self.force / self.force_hertz - 1

    @property
    def radius_error(self) -> float:
        return self.radius / self.radius_hertz - 1


def _block_mesh(L: float, H: float, a: float, h_fine: float, h_max: float, grading: float):
    import gmsh

    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("hertz")
        gmsh.model.occ.addBox(0, 0, 0, L, L, H)
        gmsh.model.occ.synchronize()
        zone = 1.3 * a

        def size(dim, tag, x, y, z, lc):
            r = math.hypot(x, y)
            dist = math.hypot(max(r - zone, 0.0), H - z)
            return min(h_fine + grading * dist, h_max)

        gmsh.model.mesh.setSizeCallback(size)
        for k in ("Mesh.MeshSizeExtendFromBoundary", "Mesh.MeshSizeFromPoints", "Mesh.MeshSizeFromCurvature"):
            gmsh.option.setNumber(k, 0)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        x = coords.reshape(-1, 3)
        index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
        index[tags.astype(np.int64)] = np.arange(tags.size)
        et, _, en = gmsh.model.mesh.getElements(3)
        cells = index[en[list(et).index(4)].astype(np.int64)].reshape(-1, 4)
    finally:
        gmsh.finalize()
    import basix.ufl

    coord_el = ufl.Mesh(basix.ufl.element("Lagrange", "tetrahedron", 1, shape=(3,)))
    return dmesh.create_mesh(MPI.COMM_SELF, cells, coord_el, x)


def hertz(
    R: float = 20.0, delta: float = 0.2, E: float = 10.0, nu: float = 0.3, *, level: str = "verify"
) -> HertzResult:
    """Press a rigid sphere into a block and compare force and contact radius with Hertz.

    Sphere radius ``R`` mm, indentation ``delta`` mm, block modulus ``E`` kPa and Poisson ratio
    ``nu``; the quarter block is L = H = 40 a (a = √(R δ)), its top meshed at 0.12 a (``level``
    "test") or 0.055 a ("verify") near the contact, growing by 0.4 per mm up to 6 a.  The measured
    force (mN) is the top face's total reaction, the measured radius (mm) midway between the
    outermost closed node and the next open one."""
    t0 = time.perf_counter()
    a_h, F_h = _hertz_theory(R, delta, E, nu)
    L = H = 40 * a_h
    h_fine = {"test": 0.12, "verify": 0.055}[level] * a_h
    msh = _block_mesh(L, H, a_h, h_fine, h_max=6.0 * a_h, grading=0.4)
    c = _SphereContact(msh, E, nu, R, delta, L, H, a_h)
    active0 = c.g0 - delta < 0
    uu, active, its = active_set(c.solve_with, c.patch_force, c.gap, active0, gap_tol=1e-9 * delta, max_iter=50)
    F, radius = c.force_and_radius(uu, active)
    c.destroy()
    return HertzResult(
        force=F,
        force_hertz=F_h,
        radius=radius,
        radius_hertz=a_h,
        ndofs=c.n,
        iterations=its,
        seconds=time.perf_counter() - t0,
    )


def _hertz_theory(R: float, delta: float, E: float, nu: float) -> tuple[float, float]:
    """Hertz's contact radius a (mm) and force F (mN) for a rigid sphere of radius ``R`` mm pressed
    ``delta`` mm into an elastic half-space of modulus ``E`` kPa, Poisson ratio ``nu``::

        a = √(R δ),   F = 4/3 · E* · √R · δ^{3/2},   E* = E / (1 − ν²)"""
    a_h = math.sqrt(R * delta)
    Estar = E / (1 - nu**2)
    F_h = 4.0 / 3.0 * Estar * math.sqrt(R) * delta**1.5
    return a_h, F_h


class _SphereContact:
    """The quarter block's P2 elasticity (``A``, modulus E kPa) and the sphere's unilateral
    contact on its top face z = H: the candidate top nodes (r < 2 a) with their initial gap
    g0(r) = r²/(2R) (mm), the fixed dofs (bottom, symmetry planes), the top nodes' patch
    incidence ``S`` and one MUMPS LU solver; :func:`~elastimap.solver.interface.active_set`
    calls :meth:`solve_with`, :meth:`patch_force` and :meth:`gap`."""

    def __init__(self, msh, E: float, nu: float, R: float, delta: float, L: float, H: float, a_h: float):
        self.delta = delta
        V = fem.functionspace(msh, ("Lagrange", 2, (3,)))
        u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
        a = fem.form(ufl.inner(sigma(u, fem.Constant(msh, E), fem.Constant(msh, nu)), epsilon(v)) * ufl.dx)
        self.A = fpetsc.assemble_matrix(a)
        self.A.assemble()
        X = V.tabulate_dof_coordinates()
        self.n = 3 * X.shape[0]
        tol = 1e-8 * L
        x, y, z = X[:, 0], X[:, 1], X[:, 2]
        top = np.flatnonzero(np.abs(z - H) < tol)
        r_top = np.hypot(x[top], y[top])
        cand = r_top < 2.0 * a_h  # nodes that may touch
        self.top, self.r_top = top[cand], r_top[cand]
        self.g0 = self.r_top**2 / (2 * R)  # paraboloid, as in Hertz theory
        self.fixed_base = np.zeros(self.n, dtype=bool)
        self.fixed_base[3 * np.flatnonzero(np.abs(z) < tol)[:, None] + np.arange(3)] = True
        self.fixed_base[3 * np.flatnonzero(np.abs(x) < tol)] = True
        self.fixed_base[3 * np.flatnonzero(np.abs(y) < tol) + 1] = True
        self.S = _patch_incidence(msh, u, v, self.top, H, a_h, tol)
        self.ksp = PETSc.KSP().create(MPI.COMM_SELF)
        self.ksp.setType("preonly")
        self.ksp.getPC().setType("lu")
        self.ksp.getPC().setFactorSolverType("mumps")

    def solve_with(self, active) -> np.ndarray:
        """The displacement (mm) with the ``active`` top nodes on the sphere, u_z = g0 − δ, and
        the fixed dofs at zero: K = PᵀAP on the free dofs, K u_free = −Pᵀ A u_D."""
        n, top = self.n, self.top
        fixed = self.fixed_base.copy()
        uD = np.zeros(n)
        idx = 3 * top[active] + 2
        fixed[idx] = True
        uD[idx] = self.g0[active] - self.delta
        free = np.flatnonzero(~fixed)
        P = sp.csr_matrix((np.ones(len(free)), (free, np.arange(len(free)))), shape=(n, len(free)))
        Pm = PETSc.Mat().createAIJ(
            size=P.shape,
            csr=(P.indptr.astype(PETSc.IntType), P.indices.astype(PETSc.IntType), P.data),
            comm=MPI.COMM_SELF,
        )
        Pm.assemble()
        K = self.A.ptap(Pm)
        rhs = -(P.T @ (_mult(self.A, uD)))
        self.ksp.reset()
        self.ksp.setOperators(K)
        ub = K.createVecRight()
        self.ksp.solve(PETSc.Vec().createWithArray(rhs, comm=MPI.COMM_SELF), ub)
        uu = P @ ub.getArray() + uD
        K.destroy(), Pm.destroy()
        return uu

    def patch_force(self, uu) -> np.ndarray:
        """Each top node's patch force S · (−(A u)_z) (mN; positive = pressed)."""
        return self.S @ (-_mult(self.A, uu)[3 * self.top + 2])

    def gap(self, uu) -> np.ndarray:
        """Each top node's gap to the sphere, (g0 − δ) − u_z (mm)."""
        return (self.g0 - self.delta) - uu[3 * self.top + 2]

    def force_and_radius(self, uu, active) -> tuple[float, float]:
        """The full sphere's force F = −4 Σ (A u)_z over the top nodes (mN; four quarters) and the
        contact radius (mm) midway between the outermost closed node and the next open one."""
        r = _mult(self.A, uu)
        F = -4.0 * float(np.sum(r[3 * self.top + 2]))
        r_in = self.r_top[active].max()
        r_out = self.r_top[~active & (self.r_top > r_in)].min()
        return F, 0.5 * (r_in + r_out)

    def destroy(self) -> None:
        """Free the PETSc solver and matrix."""
        self.ksp.destroy(), self.A.destroy()


def _patch_incidence(msh, u, v, top: np.ndarray, H: float, a_h: float, tol: float):
    """The patch incidence of the ``top`` nodes (which share a facet of the top face near the
    contact, r < 2.2 a), the nonzero pattern of the surface mass matrix ∫ u_z v_z ds there."""
    fdim = 2
    msh.topology.create_connectivity(fdim, 3)
    facets = dmesh.locate_entities_boundary(
        msh, fdim, lambda xx: (np.abs(xx[2] - H) < tol) & (np.hypot(xx[0], xx[1]) < 2.2 * a_h)
    )
    ft = dmesh.meshtags(msh, fdim, np.sort(facets), np.ones(len(facets), dtype=np.int32))
    ds = ufl.Measure("ds", domain=msh, subdomain_data=ft)
    M = fpetsc.assemble_matrix(fem.form(u[2] * v[2] * ds(1)))
    M.assemble()
    Mi, Mj, Mv = M.getValuesCSR()
    Mz = sp.csr_matrix((Mv, Mj, Mi), shape=M.getSize())[3 * top + 2][:, 3 * top + 2]
    return (abs(Mz) > 0).astype(float).tocsr()


def _mult(A, x: np.ndarray) -> np.ndarray:
    y = A.createVecLeft()
    A.mult(PETSc.Vec().createWithArray(np.ascontiguousarray(x), comm=MPI.COMM_SELF), y)
    out = y.getArray().copy()
    y.destroy()
    return out
