"""Cramér–Rao maps over (d, h, E) from the GP surrogate, checked against real FD Jacobians.

    python -m identify.crbmap [--data data/sweep512] [--out docs/figures]

Fits :class:`identify.local.Surrogate` (one GP per output) to the sweep, takes central-difference
Jacobians of the surrogate on :func:`identify.local.grid` (14 d x 5 depth fractions x 15 E),
computes Cramér–Rao relative standard deviations for each measurement set (noise: O1..O3 1 %
relative, image 1 % of its peak per pixel, force 0.1 % per reading) and writes
``identifiability_crb_<set>.png`` (fraction of the 5 depths at which each quantity is
identifiable within 10 %, i.e. CRB relative std <= 10 %, over (d, E)) and ``crb_grid.npz``
(the identifiability map read by :mod:`identify.region` and used by inference).

It also computes the real-FD CRB at the points of :mod:`identify.fd_check` (14 cached solves,
about a minute when not cached) and, unless ``--no-fd-scale``, makes the map *conservative*: each
set's bound of each output is multiplied by the largest real-FD / surrogate ratio seen at those
points, never by less than 1 (the surrogate was up to ~10x optimistic for the three features).
The unscaled surrogate bounds are kept in the file as ``<set>_surrogate``.
"""

from __future__ import annotations

import os

import click
import numpy as np

from elastimap.cli_util import run

SETS = ("features", "image", "image+force", "two-depths")


def fd_crb(points, noise) -> dict:
    """Real-FD CRB relative std ``{set: (len(points), 3)}`` (cached solves, default mesh)."""
    from .local import crb_relstd, fd_jacobian_solves, fisher, stack

    out = {s: [] for s in SETS}
    for th in points:
        J = fd_jacobian_solves(th)
        Js = stack([J])
        Js["dF"] = J["dF"][None]
        F = fisher(Js, noise)
        for s in SETS:
            out[s].append(crb_relstd(F[s], np.array([th]))[0])
    return {s: np.array(v) for s, v in out.items()}


def compute(data_path: str, out: str, k: int = 16, fd_scale: bool = True):
    from .fd_check import POINTS
    from .local import NoiseSpec, Surrogate, crb_relstd, fisher, grid
    from .measure import load

    data = load(data_path)
    sur = Surrogate.fit(data, k=k, progress=True)
    T, (ds, us, Es) = grid()
    noise = NoiseSpec(feature=0.01, image=0.01, force=0.001)
    F = fisher(sur.jacobians(T), noise)
    R0 = {s: crb_relstd(F[s], T) for s in SETS}
    P = np.array(POINTS)
    Fp = fisher(sur.jacobians(P), noise)
    Rp = {s: crb_relstd(Fp[s], P) for s in SETS}
    for s in SETS:
        for th, rr in zip(POINTS, Rp[s] * 100):
            click.echo(f"surrogate d={th[0]:g} h={th[1]:g} E={th[2]:g}  {s:12s} CRB rel std %: "
                       f"d {rr[0]:.3g}  h {rr[1]:.3g}  E {rr[2]:.3g}")
    scale = {s: np.ones(3) for s in SETS}
    if fd_scale:
        fd = fd_crb(POINTS, noise)
        for s in SETS:
            for th, rr in zip(POINTS, fd[s] * 100):
                click.echo(f"real FD   d={th[0]:g} h={th[1]:g} E={th[2]:g}  {s:12s} CRB rel std %: "
                           f"d {rr[0]:.3g}  h {rr[1]:.3g}  E {rr[2]:.3g}")
            scale[s] = np.maximum(1.0, (fd[s] / Rp[s]).max(axis=0))
            click.echo(f"conservative scale {s:12s}: d x{scale[s][0]:.3g}  h x{scale[s][1]:.3g}  E x{scale[s][2]:.3g}")
    R = {s: R0[s] * scale[s] for s in SETS}
    os.makedirs(out, exist_ok=True)
    src = (f"GP surrogate (k={k}) of {data_path} ({data.n} rows)"
           + (", scaled per output by max(1, real-FD / surrogate) at (8, 8, 30) and (8, 8, 120)" if fd_scale else "")
           + "; Cramér–Rao relative std, noise 1 % features, 1 % of the image peak per pixel, 0.1 % force; "
             "python -m identify.crbmap")
    np.savez(os.path.join(out, "crb_grid.npz"), theta=T, d=ds, u=us, E=Es, thickness=20.0, source=src,
             **{s: R[s] for s in SETS}, **{f"{s}_surrogate": R0[s] for s in SETS},
             **{f"scale_{s}": scale[s] for s in SETS})
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
        fig.suptitle(f"{s}: surrogate Cramér–Rao{' (FD-scaled)' if fd_scale else ''}, noise 1 % (features / image), "
                     f"0.1 % force")
        fig.savefig(os.path.join(out, f"identifiability_crb_{s.replace('+', '_')}.png"), dpi=90)
        plt.close(fig)
        frac, frac0 = (R[s] <= 0.10).mean(axis=0) * 100, (R0[s] <= 0.10).mean(axis=0) * 100
        click.echo(f"{s:12s} grid fraction identifiable within 10 %: d {frac[0]:.0f} %  h {frac[1]:.0f} %  "
                   f"E {frac[2]:.0f} %   (unscaled surrogate: d {frac0[0]:.0f} %  h {frac0[1]:.0f} %  E {frac0[2]:.0f} %)")
    return R


@click.command()
@click.option("--data", "data_path", default="data/sweep512", show_default=True, help="Sweep with images.")
@click.option("--out", default="docs/figures", show_default=True, help="Directory for the PNG maps and crb_grid.npz.")
@click.option("--no-fd-scale", is_flag=True, help="Keep the raw surrogate bounds (no real-FD correction, no solves).")
def main(data_path, out, no_fd_scale):
    """Cramér–Rao identifiability maps (issue 7, local evidence) and the map inference uses."""
    compute(data_path, out, fd_scale=not no_fd_scale)


if __name__ == "__main__":
    import sys

    run(main, sys.argv[1:], prog_name="python -m identify.crbmap")
