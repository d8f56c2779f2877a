r"""The image sampler: the probe-bottom deflection on the pixel grid.

The raw elasticity image is the deflection of the probe bottom relative to the plate,

$$ w(x_{ij}, y_{ij}) = u_z(x_{ij}, y_{ij}, T) + \delta \qquad {\rm (mm)}, $$

how much the probe is compressed at pixel centre (x_ij, y_ij) of the footprint
(pixel side ``ImageSpec.pixel``; the quarter model samples the quadrant x, y > 0 and
:func:`elastimap.solver.image.mirror_quarter` completes it).  u is evaluated in the
probe cells, so the sample is the probe's side of Γ.
"""

from __future__ import annotations

from . import _boot  # noqa: F401  (must precede dolfinx)

# isort: split

import numpy as np
from dolfinx import fem, geometry, graph

from .errors import SolverError
from .image import pixel_centres
from .params import SolveParams
from .space import Space


class ImageSampler:
    """Pixel centres on the probe bottom (``points``), the probe cell holding each (``cells``)
    and the grid ``shape`` (rows = y ascending, columns = x ascending)."""

    def __init__(self, space: Space, p: SolveParams):
        c = pixel_centres(space.P, p.image.pixel)
        if p.disc.symmetry == "quarter":
            c = c[c > 0]
        gx, gy = np.meshgrid(c, c)  # rows = y, cols = x
        pts = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, space.T)])
        msh = space.mesh
        tree = geometry.bb_tree(msh, 3, entities=space.probe_cells)
        cand = near_candidates(msh, geometry.compute_collisions_points(tree, pts), pts)
        cells = geometry.compute_colliding_cells(msh, cand, pts)
        found = np.diff(cells.offsets) > 0
        owner = np.full(len(pts), -1, dtype=np.int32)
        owner[found] = cells.array[cells.offsets[:-1][found]]  # the first colliding cell of each point
        if np.any(owner < 0):
            raise SolverError("image pixels fall outside the probe mesh")
        self.V = space.V
        self.points, self.cells, self.shape = pts, owner, gx.shape

    def deflection(self, u: np.ndarray, delta: float) -> np.ndarray:
        """w = u_z + δ (mm) at the pixel centres, as a ``shape`` grid."""
        uf = fem.Function(self.V)
        uf.x.array[: len(u)] = u
        vals = uf.eval(self.points, self.cells)[:, 2]
        return vals.reshape(self.shape) + delta


def near_candidates(msh, cand: graph.AdjacencyList, pts: np.ndarray, margin: float = 1e-3) -> graph.AdjacencyList:
    """``cand`` (the cells whose bounding box holds each point, DOLFINx's
    ``compute_collisions_points``) without the cells certainly farther than ``margin`` (mm) from
    their point, in the same order.

    A point x lies at least max_i(−s_i) from a tetrahedron, s_i its signed distance to the plane of
    face i (positive inside), so a cell with some s_i < −margin is farther than margin and fails
    DOLFINx's exact test (``compute_colliding_cells``, a distance of about 1e-6 at most): the
    colliding cells of the pruned list are those of the whole one, in the same order.  On the
    probe bottom most candidates merely share the plane z = T; the exact test (GJK, 4 µs a pair)
    then runs on about a fifth of them (0.016 → 0.004 s on `default`; docs/forward-model.md, 'Speed')."""
    cells = cand.array
    point = np.repeat(np.arange(len(pts)), np.diff(cand.offsets))
    v = msh.geometry.x[msh.geometry.dofmaps[0][cells]]  # (pairs, 4 vertices, 3)
    x = pts[point]
    far = np.zeros(len(cells), dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore"):  # a degenerate face: NaN, the cell is kept
        for i in range(4):
            q0, q1, q2 = (v[:, j] for j in range(4) if j != i)
            n = np.cross(q1 - q0, q2 - q0)
            n *= np.sign(np.einsum("ij,ij->i", v[:, i] - q0, n))[:, None]  # towards vertex i: inward
            s = np.einsum("ij,ij->i", x - q0, n) / np.linalg.norm(n, axis=1)
            far |= s < -margin
    keep = ~far
    offsets = np.zeros(len(pts) + 1, dtype=np.int32)
    np.cumsum(np.bincount(point[keep], minlength=len(pts)), out=offsets[1:])
    return graph.adjacencylist(np.ascontiguousarray(cells[keep], dtype=np.int32), offsets)
