"""Cramér–Rao bounds from REAL finite-difference Jacobians at two points (7 cached solves each).

    elastimap study fd_check

Noise: O1, O2, O3 1 % relative each; image 1 % of its peak per pixel (iid); plate force 0.1 % per
reading.  "two-depths" is 2 x the image Fisher matrix: the forward model is linear, so the image
at a second indentation depth is the first image scaled (checked on cached solves, see
docs/identifiability.md) and only averages noise.  ``--geometry morph`` (default) takes the
differences on the morphed map with its reference pinned at the point; ``remesh`` as the first maps did.  Solves are cached in data/identify/solves
(about 3 s each on the default mesh when absent).
"""

import click
import numpy as np

from elastimap.cli_util import CONTEXT_SETTINGS, geometry_option, run
from elastimap.identify.bounds import NoiseSpec, fd_relstd, stack
from elastimap.workflows.solves import fd_jacobian_solves

POINTS = ((8.0, 8.0, 30.0), (8.0, 8.0, 120.0))
NOISE = NoiseSpec(feature=0.01, image=0.01, force=0.001)


def fd_crb(points=POINTS, noise: NoiseSpec = NOISE, geometry: str = "morph") -> dict:
    """Real-FD CRB relative std ``{set: (len(points), 3)}`` (cached solves, default mesh)."""
    J = stack([fd_jacobian_solves(th, geometry=geometry) for th in points])
    return fd_relstd(J, np.array(points, dtype=float), noise)


@click.command(context_settings=CONTEXT_SETTINGS)
@geometry_option(
    default="morph",
    help="morph: the smooth morphed map, reference pinned per point; remesh: gmsh per solve.",
)
def main(geometry):
    """Print the real-FD Cramér–Rao relative std of d, h, E at the two check points."""
    R = fd_crb(geometry=geometry)
    for i, th in enumerate(POINTS):
        for k in ("features", "image", "image+force", "two-depths"):
            r = R[k][i] * 100
            click.echo(
                f"d={th[0]:g} h={th[1]:g} E={th[2]:g}  {k:12s} CRB rel std %: d {r[0]:.3g}  h {r[1]:.3g}  E {r[2]:.3g}"
            )


if __name__ == "__main__":
    run(main, prog_name="elastimap study fd_check")
