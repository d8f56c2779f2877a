r"""The discrete setting: the two-body mesh, the displacement space and its named node sets.

The mesh (:mod:`elastimap.solver.geometry`) holds two disconnected bodies, the tissue
(tissue, skin, inclusion cells) and the probe (PDMS layers), whose footprint nodes
coincide pairwise.  The displacement u (mm) lives in the vector Lagrange space

$$
V_h = \{ u \in C^0(\Omega)^3 : u|_K \in P_k(K)^3 \ \forall K \}, \qquad k = 1, 2,
$$

with P2 by default (P1 locks at ν = 0.49).  One block of V_h (three flat dofs
3i, 3i+1, 3i+2) is one node i.  Coordinates: x, y in the tissue surface, z up, chest
wall at z = 0, tissue surface Γ_s at z = T, probe top at z = T + H.

Everything here depends on the mesh geometry only (no material, no loading).  A mesh
morphed by :mod:`elastimap.solver.morph` keeps its topology and moves no node of these
sets off its plane (the probe, the chest wall and the tissue surface do not move, the
symmetry-plane nodes slide in their plane), so the node sets of the reference mesh stay
valid and only ``X`` is recomputed.
"""

from __future__ import annotations

from . import _boot  # noqa: F401  (must precede dolfinx)

# isort: split

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from mpi4py import MPI
from petsc4py import PETSc

from .geometry import PROBE_LAYER0, RawMesh
from .params import SolveParams


class Space:
    """Mesh, cell markers, the P_k displacement space and the node sets of the boundary conditions.

    Attributes (node indices are blocks of ``V``):

    * ``mesh``, ``markers`` (per local cell), ``V``, ``X`` (node coordinates, mm),
      ``ncells``, ``nblocks``, ``ndofs`` = 3 · nblocks;
    * ``probe_cell`` (bool per cell), ``probe_cells`` (their indices), ``is_probe`` (bool per node);
    * ``top`` (probe nodes on z = T + H), ``bottom`` (tissue nodes on z = 0), ``sym_x``, ``sym_y``
      (nodes on the planes x = 0, y = 0; empty for the full model);
    * ``T``, ``H``, ``P`` (tissue thickness, probe height, probe side, mm) and ``tol``
      (coordinate tolerance, mm).
    """

    def __init__(self, raw: RawMesh, p: SolveParams):
        coord_el = ufl.Mesh(basix.ufl.element("Lagrange", "tetrahedron", 1, shape=(3,)))
        self.mesh = dmesh.create_mesh(MPI.COMM_SELF, raw.cells, coord_el, raw.x)
        msh = self.mesh
        self.markers = raw.markers[msh.topology.original_cell_index].astype(np.int32)
        self.ncells = msh.topology.index_map(3).size_local
        self.V = fem.functionspace(msh, ("Lagrange", p.disc.degree, (3,)))
        self.X = self.V.tabulate_dof_coordinates()
        self.nblocks = self.X.shape[0]
        self.ndofs = 3 * self.nblocks

        self.probe_cell = self.markers >= PROBE_LAYER0
        self.probe_cells = np.flatnonzero(self.probe_cell).astype(np.int32)
        self.is_probe = np.zeros(self.nblocks, dtype=bool)
        self.is_probe[self.V.dofmap.list[self.probe_cell].ravel()] = True

        self.T, self.H, self.P = p.tissue.thickness, p.probe.height, p.probe.size
        self.tol = 1e-6 * max(self.T, self.P)
        x, y, z = self.X[:, 0], self.X[:, 1], self.X[:, 2]
        tol = self.tol
        self.top = np.flatnonzero(self.is_probe & (np.abs(z - (self.T + self.H)) < tol))
        self.bottom = np.flatnonzero(~self.is_probe & (np.abs(z) < tol))
        quarter = p.disc.symmetry == "quarter"
        self.sym_x = np.flatnonzero(np.abs(x) < tol) if quarter else np.empty(0, int)
        self.sym_y = np.flatnonzero(np.abs(y) < tol) if quarter else np.empty(0, int)

    def on_footprint(self, xx: np.ndarray) -> np.ndarray:
        """True for points (columns of ``xx`` or rows of ``X``.T) on Γ: z = T, |x|, |y| ≤ P/2."""
        T, P, tol = self.T, self.P, self.tol
        return (np.abs(xx[2] - T) < tol) & (np.abs(xx[0]) <= P / 2 + tol) & (np.abs(xx[1]) <= P / 2 + tol)


def petsc_matrix(a: fem.Form) -> tuple:
    """The matrix of the bilinear form ``a`` as DOLFINx's own CSR matrix and a PETSc AIJ matrix on
    the same value array (no copy; PETSc's ``seqaij`` layout, the rows' columns sorted, block size
    and local-to-global map as ``dolfinx.fem.petsc.create_matrix`` gives them), both zero: assemble
    with ``fem.assemble_matrix(values, a)``, then ``A.assemble()``.  DOLFINx assembles into its CSR
    matrix by array offsets, about a quarter less CPU than through PETSc's MatSetValues (0.10 against
    0.13-0.15 s for the stiffness on the `default` mesh; docs/forward-model.md, 'Shared presses'),
    and a linear solve never imports ``dolfinx.fem.petsc`` (0.03 s of a `solve` process: its import
    builds a CFFI parser); everything else (PᵀAP, products, A += s A₁) runs on the PETSc matrix.
    Keep ``values`` alive as long as ``A``."""
    from dolfinx import la

    values = fem.create_matrix(a, block_mode=la.BlockMode.expanded)
    n = len(values.indptr) - 1  # one process: no ghost rows
    bs = a.function_spaces[0].dofmap.index_map_bs
    indptr = values.indptr.astype(PETSc.IntType)
    A = PETSc.Mat().createAIJWithArrays((n, n), (indptr, values.indices, values.data), comm=MPI.COMM_SELF)
    A.setBlockSizes(bs, bs)
    lgmap = PETSc.LGMap().create(np.arange(n // bs, dtype=PETSc.IntType), bsize=bs, comm=MPI.COMM_SELF)
    A.setLGMap(lgmap, lgmap)
    return values, A
