"""Check the identifiability map against Cramér–Rao bounds from REAL finite differences on a grid.

    elastimap study fdgrid                      # 40 points x 7 cached solves (~20 min, resumable)
    elastimap study mapcheck [--fdgrid data/identify/fdgrid.npz] [--map default]

At every point of the FD grid (:mod:`elastimap.workflows.studies.fdgrid`: d 4/7/10/13 mm, two depth fractions,
E 12/25/50/100/190 kPa) the bound from the real FD Jacobian (same noise as the map) is compared
with the map's bound interpolated there, as inference evaluates it.  Printed per measurement set
and output: median and range of map / FD, the fraction of points where the map is at least as
pessimistic as FD ("conservative"), agreement of the 10 % identifiability call, and the
dangerous disagreements: the map calls the output identifiable where FD says it is not.
"""

from __future__ import annotations

import os
import sys

import click
import numpy as np

from elastimap.cli_util import run
from elastimap.errors import UserError

SETS = ("features", "image", "two-depths")


def fd_bounds(path: str) -> tuple[np.ndarray, dict]:
    """``theta`` (n, 3) and ``{set: (n, 3)}`` CRB relative std from an fdgrid file."""
    from elastimap.identify.bounds import fd_relstd

    from .fd_check import NOISE

    if not os.path.isfile(path):
        raise UserError("--fdgrid", f"{path}: no such file (make it with python -m elastimap.workflows.studies.fdgrid)")
    z = np.load(path, allow_pickle=False)
    return z["theta"], fd_relstd({k: z[k] for k in ("image", "image0", "lnF", "dF")}, z["theta"], NOISE)


def compare(map_r: np.ndarray, fd_r: np.ndarray, threshold: float = 0.10) -> dict:
    """Per output: ratio statistics and identifiability-call agreement of ``map_r`` vs ``fd_r`` (n, 3)."""
    ratio = map_r / fd_r
    m_ok, f_ok = map_r <= threshold, fd_r <= threshold
    out = {}
    for j, q in enumerate(("d", "h", "E")):
        out[q] = {
            "median": float(np.median(ratio[:, j])),
            "min": float(ratio[:, j].min()),
            "max": float(ratio[:, j].max()),
            "conservative": float(100 * (ratio[:, j] >= 1).mean()),
            "agree": float(100 * (m_ok[:, j] == f_ok[:, j]).mean()),
            "false_identifiable": int((m_ok[:, j] & ~f_ok[:, j]).sum()),
            "fd_identifiable": int(f_ok[:, j].sum()),
            "n": int(ratio.shape[0]),
        }
    return out


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--fdgrid",
    default="data/identify/fdgrid.npz",
    show_default=True,
    help="Output of elastimap.workflows.studies.fdgrid.",
)
@click.option("--map", "map_path", default="default", show_default=True, help="Map file or 'default' (shipped).")
@click.option(
    "--crb-limit",
    "threshold",
    default=0.10,
    show_default=True,
    type=float,
    help="Cramér–Rao relative std limit of the identifiability call.",
)
def main(fdgrid, map_path, threshold):
    """Compare the identifiability map with real-FD Cramér–Rao bounds on the FD grid."""
    from elastimap.identify.idmap import IdentifiabilityMap

    theta, fd = fd_bounds(fdgrid)
    idm = IdentifiabilityMap.load(None if map_path == "default" else map_path)
    click.echo(f"{theta.shape[0]} FD points; map: {idm.source}")
    click.echo(
        "| set | output | map/FD median [min, max] | map >= FD (%) | same 10 % call (%) "
        "| FD identifiable | map says identifiable, FD not |"
    )
    click.echo("|---|---|---|---|---|---|---|")
    for s in SETS:
        if s not in idm.relstd:
            continue
        r, _ = idm.bound(theta, s)
        ok = np.isfinite(r).all(axis=1) & np.isfinite(fd[s]).all(axis=1)
        if not ok.all():  # e.g. O3 = 0 (nothing above the threshold) makes ln O3 and its FD undefined
            click.echo(f"({s}: {int((~ok).sum())} point(s) without a finite FD bound left out)")
        for q, c in compare(r[ok], fd[s][ok], threshold).items():
            click.echo(
                f"| {s} | {q} | {c['median']:.3g} [{c['min']:.3g}, {c['max']:.3g}] | {c['conservative']:.0f} "
                f"| {c['agree']:.0f} | {c['fd_identifiable']}/{c['n']} | {c['false_identifiable']} |"
            )
    return 0


if __name__ == "__main__":
    run(main, sys.argv[1:], prog_name="elastimap study mapcheck")
