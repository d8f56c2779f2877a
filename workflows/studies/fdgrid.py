"""Real finite-difference Jacobians on a coarse (d, depth fraction, E) grid (cached solves).

    elastimap study fdgrid [--mesh default] [--geometry morph] [--out data/identify/fdgrid.npz]

7 forward solves per grid point (centre and central differences in d, h, ln E with
:data:`elastimap.workflows.solves.FD_STEP`), on the morphed map with the reference mesh pinned at the
point (``--geometry morph``, no remeshing jitter) or remeshed per solve (``remesh``); every solve is cached by :mod:`elastimap.workflows.solves`, so an
interrupted run resumes.  The result file holds the grid, the Jacobians and the geometry;
``python -m elastimap.workflows.studies.crbmap --fd-grid FILE`` scales the identifiability map with
their Cramér–Rao bounds and ``python -m elastimap.workflows.studies.mapcheck --fdgrid FILE`` checks
the map against them (docs/identifiability.md).
"""

from __future__ import annotations

import os
import sys
import time

import click
import numpy as np

from elastimap.cli_util import CONTEXT_SETTINGS, geometry_option, mesh_option, run
from elastimap.dataset.schema import THICKNESS

FD_D = (4.0, 7.0, 10.0, 13.0)
FD_U = (0.25, 0.75)
FD_E = (12.0, 25.0, 50.0, 100.0, 190.0)


def fd_grid_points(ds=FD_D, us=FD_U, Es=FD_E, thickness: float = THICKNESS) -> np.ndarray:
    from elastimap.solver.params import depth_range

    pts = []
    for d in ds:
        lo, hi = depth_range(d, thickness)
        lo2, hi2 = lo + 0.5, hi - 0.5  # room for the +-0.5 mm depth step
        for u in us:
            for E in Es:
                pts.append((d, lo2 + u * (hi2 - lo2), E, u))
    return np.array(pts)


def compute(out: str, mesh: str = "default", progress: bool = True, geometry: str = "morph") -> dict:
    from elastimap.workflows.solves import fd_jacobian_solves

    pts = fd_grid_points()
    res = {"theta": pts[:, :3], "u": pts[:, 3], "image": [], "lnF": [], "dF": [], "image0": [], "lnF0": [], "dF0": []}
    t0 = time.perf_counter()
    for i, p in enumerate(pts):
        J = fd_jacobian_solves(p[:3], mesh=mesh, geometry=geometry)
        for k in ("image", "lnF", "dF", "image0", "lnF0", "dF0"):
            res[k].append(J[k])
        if progress:
            click.echo(
                f"[{i + 1}/{len(pts)}] d={p[0]:g} h={p[1]:.2f} E={p[2]:g}  {time.perf_counter() - t0:.0f} s", err=True
            )
        res["background"] = J["background"]
    out_d = {k: np.asarray(v) for k, v in res.items()}
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    np.savez(out, **out_d, mesh=np.array(mesh), geometry=np.array(geometry))
    return out_d


@click.command(context_settings=CONTEXT_SETTINGS)
@mesh_option()
@geometry_option(
    default="morph",
    help="morph: the smooth morphed map, reference pinned per point; remesh: gmsh per solve.",
)
@click.option(
    "--out", default="data/identify/fdgrid.npz", show_default=True, help="The Jacobians file to write (.npz)."
)
def main(mesh, geometry, out):
    """Finite-difference Jacobians from real solves on the coarse study grid."""
    compute(out, mesh, geometry=geometry)
    click.echo(f"wrote {out}")


if __name__ == "__main__":
    run(main, sys.argv[1:], prog_name="elastimap study fdgrid")
