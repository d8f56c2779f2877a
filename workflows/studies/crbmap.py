"""Cramér–Rao maps over (d, h, E) from the GP surrogate, checked against real FD Jacobians.

    elastimap study crbmap [--data data/sweep512] [--out docs/figures]

Fits :class:`elastimap.identify.bounds.Surrogate` (one GP per output) to the sweep, takes central-difference
Jacobians of the surrogate on :func:`elastimap.identify.bounds.grid` (14 d x 5 depth fractions x 15 E),
computes Cramér–Rao relative standard deviations for each measurement set (noise: O1..O3 1 %
relative, image 1 % of its peak per pixel, force 0.1 % per reading) and writes
``identifiability_crb_<set>.png`` (fraction of the 5 depths at which each quantity is
identifiable within 10 %, i.e. CRB relative std <= 10 %, over (d, E)) and ``crb_grid.npz``
(the identifiability map read by :mod:`elastimap.identify.idmap` and used by inference).

It also computes the real-FD CRB at the points of :mod:`elastimap.workflows.studies.fd_check` (14 cached solves,
about a minute when not cached) and, when ``--fd-grid`` exists (``python -m elastimap.workflows.studies.fdgrid``,
40 more points), at those too, and unless ``--no-fd-scale`` makes the map *conservative*: each
set's bound of each output is multiplied by the 90th percentile over all FD points of the ratio
real-FD / surrogate, never by less than 1, so the map is at least as pessimistic as the real FD
bound at nine points in ten.  The unscaled surrogate bounds are kept in the file as
``<set>_surrogate``; ``python -m elastimap.workflows.studies.mapcheck`` compares the map with the FD grid.

``--surrogate-from MAP`` skips the sweep and the GP fits: the raw surrogate bounds are read from
the ``<set>_surrogate`` entries of an earlier map file made by this study on the same grid (e.g. the
shipped map), and the surrogate's bound at an FD point is that grid interpolated there as inference
interpolates a map (:meth:`elastimap.identify.idmap.IdentifiabilityMap.bound`) instead of the GP
evaluated there.  Use it to re-scale a map with new finite differences when the sweep is not at
hand; the new file records where its surrogate came from.

``--install`` also writes the map to the file inference reads when no map is given,
:data:`elastimap.identify.idmap.DEFAULT_MAP` (``identify/maps/default.npz`` in the repository),
through :func:`install_map`: the new file is read back as an
:class:`~elastimap.identify.idmap.IdentifiabilityMap` first and then swapped in atomically.  That
file is the shipped map; regenerate it this way, never by hand.
"""

from __future__ import annotations

import os
import shutil
import tempfile

import click
import numpy as np

from elastimap.cli_util import run
from elastimap.dataset.schema import THICKNESS
from elastimap.errors import UserError

SETS = ("features", "image", "image+force", "two-depths")


FD_SCALE_QUANTILE = 90.0


def fd_interpolate(
    theta_fd: np.ndarray, r_fd: np.ndarray, theta: np.ndarray, thickness: float = THICKNESS
) -> np.ndarray:
    """Bound ``r`` (n, 3) at ``theta`` from FD bounds at scattered points: linear in (d, u, ln E) of ln r
    (``u`` the depth fraction of :func:`elastimap.identify.bounds.grid`), nearest FD point outside their hull."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

    from elastimap.solver.params import depth_range

    def coords(th):
        lo, hi = np.array([depth_range(d, thickness) for d in th[:, 0]]).T
        return np.column_stack([th[:, 0] / 13.0, (th[:, 1] - lo) / (hi - lo), np.log(th[:, 2]) / np.log(19.0)])

    ok = np.isfinite(r_fd).all(axis=1)
    X, Y = coords(theta_fd[ok]), np.log(r_fd[ok])
    Xq = coords(theta)
    out = LinearNDInterpolator(X, Y)(Xq)
    miss = ~np.isfinite(out).all(axis=1)
    out[miss] = NearestNDInterpolator(X, Y)(Xq[miss])
    return np.exp(out)


def fd_grid_geometry(path: str) -> str:
    """How the FD grid file's solves were meshed (``morph`` or ``remesh``; older files: ``remesh``)."""
    z = np.load(path, allow_pickle=False)
    return str(z["geometry"]) if "geometry" in z.files else "remesh"


def install_map(src: str, dest: str | None = None) -> str:
    """Copy the map file ``src`` to ``dest`` (default: the shipped map inference reads) after checking
    that it loads as an identifiability map; the destination is replaced atomically."""
    from elastimap.identify.idmap import DEFAULT_MAP, IdentifiabilityMap

    dest = dest or DEFAULT_MAP
    IdentifiabilityMap.load(src)
    folder = os.path.dirname(os.path.abspath(dest))
    fd, tmp = tempfile.mkstemp(suffix=".npz", dir=folder)
    os.close(fd)
    try:
        shutil.copyfile(src, tmp)
        IdentifiabilityMap.load(tmp)
        os.replace(tmp, dest)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return dest


def check_install_target(dest: str | None = None) -> str:
    """The install destination, checked before any work: its folder must exist and be writable."""
    from elastimap.identify.idmap import DEFAULT_MAP

    dest = dest or DEFAULT_MAP
    folder = os.path.dirname(os.path.abspath(dest))
    if not (os.path.isdir(folder) and os.access(folder, os.W_OK)):
        raise UserError(
            "--install",
            f"cannot write the shipped map {dest} (folder missing or read-only; "
            "use an editable install of the repository)",
        )
    return dest


def stored_surrogate(path: str):
    """The raw surrogate bounds of an earlier map file of this study: ``(map, where they came from)``.

    ``map`` is an :class:`~elastimap.identify.idmap.IdentifiabilityMap` holding the file's
    ``<set>_surrogate`` entries (every set of :data:`SETS`), on the grid of
    :func:`elastimap.identify.bounds.grid`; ``map.bound(theta, set)`` interpolates them."""
    from elastimap.identify.bounds import grid
    from elastimap.identify.idmap import IdentifiabilityMap

    if not os.path.isfile(path):
        raise UserError("--surrogate-from", f"{path}: no such map file")
    base = IdentifiabilityMap.load(path)
    z = np.load(path, allow_pickle=False)
    missing = [s for s in SETS if f"{s}_surrogate" not in z.files]
    if missing:
        raise UserError(
            "--surrogate-from", f"{path} keeps no raw surrogate bounds for {', '.join(missing)} (not made by crbmap)"
        )
    _T, (ds, us, Es) = grid()
    if not all(a.shape == b.shape and np.allclose(a, b) for a, b in ((base.d, ds), (base.u, us), (base.E, Es))):
        raise UserError("--surrogate-from", f"{path} is on another (d, u, E) grid than this study's")
    shape = (ds.size, us.size, Es.size, 3)
    rel = {s: np.asarray(z[f"{s}_surrogate"], float).reshape(shape) for s in SETS}
    if "surrogate_source" in z.files:
        origin = str(z["surrogate_source"])
    else:  # files written before the surrogate's origin was kept on its own: the head of the source
        origin = base.source.split(", scaled per output")[0].split(";")[0]
    return IdentifiabilityMap(base.d, base.u, base.E, rel, base.thickness, origin), origin


def _surrogate(data_path: str, k: int, surrogate_from: str | None, T: np.ndarray, noise):
    """The raw surrogate bounds on the grid ``T`` (``{set: (n, 3)}``), a function giving them at
    other points, and where they came from: a GP surrogate fitted to the sweep ``data_path``, or
    the ``<set>_surrogate`` entries of the map file ``surrogate_from`` interpolated."""
    from elastimap.identify.bounds import Surrogate, crb_relstd, fisher

    if surrogate_from:
        smap, sur_src = stored_surrogate(surrogate_from)
        R0 = {s: smap.relstd[s].reshape(-1, 3) for s in SETS}

        def sur_bounds(th: np.ndarray) -> dict:
            return {s: smap.bound(th, s)[0] for s in SETS}

        sur_src = f"{sur_src} (raw bounds read from {surrogate_from}, interpolated at the FD points)"
        click.echo(f"surrogate: {sur_src}")
        return R0, sur_bounds, sur_src
    from elastimap.identify.measure import load

    data = load(data_path)
    sur = Surrogate.fit(data, k=k, progress=True)
    F = fisher(sur.jacobians(T), noise)
    R0 = {s: crb_relstd(F[s], T) for s in SETS}

    def sur_bounds(th: np.ndarray) -> dict:
        Fs = fisher(sur.jacobians(th), noise)
        return {s: crb_relstd(Fs[s], th) for s in SETS}

    return R0, sur_bounds, f"GP surrogate (k={k}) of {data_path} ({data.n} rows)"


def _echo_bounds(label: str, points, R: dict) -> None:
    """One line per set and point: the Cramér–Rao relative std of d, h, E in %."""
    for s in SETS:
        for th, rr in zip(points, R[s] * 100):
            click.echo(
                f"{label} d={th[0]:g} h={th[1]:g} E={th[2]:g}  {s:12s} CRB rel std %: "
                f"d {rr[0]:.3g}  h {rr[1]:.3g}  E {rr[2]:.3g}"
            )


def _fd_scales(Rp: dict, sur_bounds, noise, fd_grid: str | None) -> dict:
    """Real-FD bounds at fd_check's points (and at the ``fd_grid`` points when that file exists)
    and, per set and output, the conservative scale max(1, q90 of real-FD / surrogate) over them.
    Returns ``scale``, ``npts``, ``fd`` (at fd_check's points) and, with a grid, ``grid``
    (its points, its FD bounds) and ``geometry`` (the grid's)."""
    from .fd_check import POINTS, fd_crb

    fd = fd_crb(POINTS, noise)
    _echo_bounds("real FD  ", POINTS, fd)
    ratios = {s: [fd[s] / Rp[s]] for s in SETS}
    out = {"fd": fd, "npts": len(POINTS), "grid": None, "geometry": None}
    if fd_grid and os.path.isfile(fd_grid):
        from .mapcheck import fd_bounds

        tg, fdg = fd_bounds(fd_grid)
        Rg = sur_bounds(tg)
        for s in SETS:
            ratios[s].append(fdg[s] / Rg[s])
        out.update(npts=out["npts"] + tg.shape[0], grid=(tg, fdg), geometry=fd_grid_geometry(fd_grid))
        click.echo(f"FD grid {fd_grid} ({out['geometry']}): {tg.shape[0]} more points")
    out["scale"] = {}
    for s in SETS:
        q = np.concatenate(ratios[s])
        q = q[np.isfinite(q).all(axis=1)]
        out["scale"][s] = sc = np.maximum(1.0, np.percentile(q, FD_SCALE_QUANTILE, axis=0))
        click.echo(
            f"conservative scale {s:12s}: d x{sc[0]:.3g}  h x{sc[1]:.3g}  E x{sc[2]:.3g}"
            f"  ({FD_SCALE_QUANTILE:g}th percentile of FD / surrogate over {len(q)} points)"
        )
    return out


def _source(sur_src: str, fd: dict | None, command: str) -> str:
    """The map's ``source`` line: the surrogate, the FD scaling (``fd``: :func:`_fd_scales`'s
    answer, None without), the noise model and the command."""
    src = sur_src
    if fd is not None:
        geoms = {"morph"} | ({fd["geometry"]} if fd["grid"] else set())  # fd_check's points: the morphed map
        fd_how = f"real-FD ({' + '.join(sorted(geoms))} geometry)"
        src += (
            f", scaled per output by max(1, {FD_SCALE_QUANTILE:g}th percentile of {fd_how} / surrogate over "
            f"{fd['npts']} FD points)"
        )
        if fd["grid"]:
            src += "; features entry: real-FD bound interpolated from those points"
    return (
        src + "; Cramér–Rao relative std, noise 1 % features, 1 % of the image peak per pixel, 0.1 % force; " + command
    )


def _plot(out: str, R: dict, R0: dict, axes, fd_scale: bool, use_grid: bool) -> None:
    """``identifiability_crb_<set>.png``: the fraction of the depths at which d, h, E have a CRB
    relative std <= 10 %, over (d, E); prints each set's identifiable fraction of the grid."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ds, us, Es = axes
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
        how = (
            "real-FD Cramér–Rao interpolated from the FD points"
            if s == "features" and use_grid
            else f"surrogate Cramér–Rao{' (FD-scaled)' if fd_scale else ''}"
        )
        fig.suptitle(f"{s}: {how}, noise 1 % (features / image), 0.1 % force")
        fig.savefig(os.path.join(out, f"identifiability_crb_{s.replace('+', '_')}.png"), dpi=90)
        plt.close(fig)
        frac, frac0 = (R[s] <= 0.10).mean(axis=0) * 100, (R0[s] <= 0.10).mean(axis=0) * 100
        click.echo(
            f"{s:12s} grid fraction identifiable within 10 %: d {frac[0]:.0f} %  h {frac[1]:.0f} %  "
            f"E {frac[2]:.0f} %   (unscaled surrogate: d {frac0[0]:.0f} %  h {frac0[1]:.0f} %  E {frac0[2]:.0f} %)"
        )


def compute(
    data_path: str,
    out: str,
    k: int = 16,
    fd_scale: bool = True,
    fd_grid: str | None = None,
    install: str | None = None,
    surrogate_from: str | None = None,
    command: str = "python -m elastimap.workflows.studies.crbmap",
):
    """Fit (or, with ``surrogate_from``, read), bound and plot (see the module docstring); with
    ``install`` (a path) the map is also written there by :func:`install_map`.  ``command`` is
    recorded in the map's ``source``.  Returns ``{set: (n_grid, 3)}`` relative std."""
    if install:
        check_install_target(install)
    from elastimap.identify.bounds import grid

    from .fd_check import NOISE as noise
    from .fd_check import POINTS

    T, (ds, us, Es) = grid()
    P = np.array(POINTS)
    R0, sur_bounds, sur_src = _surrogate(data_path, k, surrogate_from, T, noise)
    Rp = sur_bounds(P)
    _echo_bounds("surrogate", POINTS, Rp)
    fd = _fd_scales(Rp, sur_bounds, noise, fd_grid) if fd_scale else None
    R = {s: R0[s] * (fd["scale"][s] if fd else 1.0) for s in SETS}
    use_grid = fd is not None and fd["grid"] is not None
    if use_grid:
        # the surrogate of the three features disagrees with real FD by up to ~100x (O3 is a thresholded
        # area); no single scale fits, so the features entry is the real-FD bound itself, interpolated
        tg, fdg = fd["grid"]
        R["features"] = fd_interpolate(np.vstack([P, tg]), np.vstack([fd["fd"]["features"], fdg["features"]]), T)
        click.echo("features: map = real-FD bound interpolated from the FD points (linear in d, u, ln E of ln r)")
    os.makedirs(out, exist_ok=True)
    grid_file = os.path.join(out, "crb_grid.npz")
    scale = {s: fd["scale"][s] if fd else np.ones(3) for s in SETS}
    np.savez(
        grid_file,
        theta=T,
        d=ds,
        u=us,
        E=Es,
        thickness=THICKNESS,
        source=_source(sur_src, fd, command),
        surrogate_source=sur_src,
        **{s: R[s] for s in SETS},
        **{f"{s}_surrogate": R0[s] for s in SETS},
        **{f"scale_{s}": scale[s] for s in SETS},
    )
    _plot(out, R, R0, (ds, us, Es), fd_scale, use_grid)
    if install:
        click.echo(f"installed {grid_file} as the shipped map {install_map(grid_file, install)}")
    return R


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--data", "data_path", default="data/sweep512", show_default=True, help="Sweep with images.")
@click.option("--out", default="docs/figures", show_default=True, help="Directory for the PNG maps and crb_grid.npz.")
@click.option("--no-fd-scale", is_flag=True, help="Keep the raw surrogate bounds (no real-FD correction, no solves).")
@click.option(
    "--fd-grid",
    default="data/identify/fdgrid.npz",
    show_default=True,
    help="Real-FD Jacobians of python -m elastimap.workflows.studies.fdgrid, used for the scale when the file exists.",
)
@click.option(
    "--surrogate-from",
    default=None,
    help="Read the raw surrogate bounds from this earlier crbmap map file (e.g. identify/maps/default.npz) "
    "instead of fitting the GPs to --data (which is then not read).",
)
@click.option(
    "--install",
    is_flag=True,
    help="Also replace the shipped map inference reads (identify/maps/default.npz) with the new one.",
)
def main(data_path, out, no_fd_scale, fd_grid, surrogate_from, install):
    """Cramér–Rao identifiability maps (local evidence) and the map inference uses."""
    from elastimap.identify.idmap import DEFAULT_MAP

    cmd = ["elastimap study crbmap"]
    if surrogate_from:
        cmd.append(f"--surrogate-from {surrogate_from}")
    else:
        cmd.append(f"--data {data_path}")
    cmd.append("--no-fd-scale" if no_fd_scale else f"--fd-grid {fd_grid}")
    cmd.append(f"--out {out}" + (" --install" if install else ""))
    compute(
        data_path,
        out,
        fd_scale=not no_fd_scale,
        fd_grid=fd_grid,
        install=DEFAULT_MAP if install else None,
        surrogate_from=surrogate_from,
        command=" ".join(cmd),
    )


if __name__ == "__main__":
    import sys

    run(main, sys.argv[1:], prog_name="elastimap study crbmap")
