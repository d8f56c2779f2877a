"""Finite-difference Jacobians on the morphed map: the stencil pins its centre's reference mesh.

At d = 6.5 mm the +0.5 mm step crosses the d-bin edge (6.73 mm) of the morphed map; pinned, the
0.5 mm central difference agrees with a 0.1 mm one, unpinned it jumps with the mesh (tiny mesh,
real FEM, about 20 s).
"""

import numpy as np

from elastimap.workflows.solves import cached_solve, fd_jacobian_solves, morph_reference

D, H, E = 6.5, 7.0, 50.0


def _dlnO_dd(step, **kw):
    a, b = (cached_solve(D + s * step, H, E, mesh="tiny", geometry="morph", **kw)["O"] for s in (1, -1))
    return (np.log(a) - np.log(b)) / (2 * step)


def test_fd_stencil_pins_the_reference_across_a_bin_edge(tmp_path):
    ref = morph_reference(D, H)
    assert morph_reference(D + 0.5, H) != ref  # the stencil crosses a bin edge
    J = fd_jacobian_solves((D, H, E), mesh="tiny", cache=str(tmp_path))
    fine = _dlnO_dd(0.1, cache=str(tmp_path), reference=ref)
    pinned_miss = np.abs(J["lnF"][:2, 0] / fine[:2] - 1)  # O1, O2
    assert np.all(pinned_miss < 0.01), pinned_miss
    unpinned = _dlnO_dd(0.5, cache=str(tmp_path))  # each side on its own bin's mesh
    assert np.max(np.abs(unpinned[:2] / fine[:2] - 1)) > 3 * np.max(pinned_miss)
    assert np.all(np.isfinite(J["image"])) and J["image"].shape[1] == 3
