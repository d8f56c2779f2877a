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
from dolfinx import fem, geometry

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
        cand = geometry.compute_collisions_points(tree, pts)
        cells = geometry.compute_colliding_cells(msh, cand, pts)
        owner = np.array([cells.links(i)[0] if len(cells.links(i)) else -1 for i in range(len(pts))], dtype=np.int32)
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
