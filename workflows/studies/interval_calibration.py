"""The scales of the fit's calibrated 95 % intervals (:mod:`elastimap.identify.intervals`) from the
records of camera-frame benchmark folders, and the coverage they give, seed by seed.

    python -m elastimap.workflows.studies.interval_calibration runs/fb27 runs/fb28Ec ... runs/fb41E \\
        [--check runs/fb42E] [--loso] [--install | --out FILE]

Each FOLDER is a ``workflows/frames_benchmark.py`` output (SYNTHETIC lesions; its fits in
``fits-morph-coarse-corr-fine-drift``, the calibrated configuration
:data:`~elastimap.identify.intervals.CALIBRATED_FOR`).  Per lesion with a signal and per parameter q
the score is ``|x̂_q − x_q| / sd_q`` in the fit's coordinate (d mm, h mm, e = ln c(E) of
:class:`~elastimap.identify.coords.FitCoords`) with the fit's Gauss–Newton sd (records before
2026-11-27 hold it as ``sd``/``crb_rel``, later ones as ``fit_relstd_gauss``).  Prints the scales per
stratum of the estimate (far from or near the slab's base, :func:`~elastimap.identify.intervals.near_base`)
and class of the relative sd (:func:`~elastimap.identify.intervals.calibrate`), then the coverage of the Gauss–Newton and of the calibrated interval inside and
outside the shipped identifiability map's region (``frames`` set, 10 %, at the truth; the
benchmark's own split) and near the base: of the calibration folders themselves (in-sample: says
only that the scales do what they were set to), with ``--loso`` of each folder with the scales of the others (leave one
seed out: an honest estimate of held-out coverage), and of the ``--check`` folders (never used for
the scales).  ``--install`` writes the scales, with their provenance (date, commit, folders, seeds,
lesions per cell, method), to the file inference reads (``identify/maps/intervals.json``,
:data:`~elastimap.identify.intervals.INTERVALS_FILE`; atomically, and only after every folder was
read); ``--out FILE`` writes the same file elsewhere.  Nothing edits the scales in code.
"""

from __future__ import annotations

import datetime
import glob
import json
import os

import click
import numpy as np

from elastimap.cli_util import run
from elastimap.errors import UserError
from elastimap.identify.coords import FitCoords
from elastimap.identify.intervals import (
    CALIBRATED_FOR,
    INTERVALS_FILE,
    NEAR_BASE_MM,
    PARAMS,
    Z95,
    calibrate,
    near_base,
    scales_for,
    write_scales,
)
from elastimap.outputs import check_out_file
from elastimap.provenance import code_version

FITS = "fits-morph-coarse-corr-fine-drift"


def read_folder(folder: str) -> dict:
    """Arrays of one benchmark folder's lesions with a signal: ``truth`` (n, 3) in (d, h, E),
    ``x_true``/``x_fit`` (n, 3) in the fit's coordinates (d, h, e), ``sd`` (n, 3) the Gauss–Newton sd in
    those coordinates, ``relstd`` (n, 3) the Gauss–Newton relative sds (d, h; ln E), ``theta_fit``
    (n, 3) the estimate (d, h, E), ``seeds`` the lesion designs' seeds (None where a record has none)."""
    paths = sorted(glob.glob(os.path.join(folder, FITS, "lesion-*.json")))
    if not paths:
        raise UserError("FOLDER", f"{folder} holds no {FITS}/lesion-*.json")
    X = FitCoords()
    rows, seeds = [], set()
    for path in paths:
        with open(path) as fh:
            r = json.load(fh)
        if "no_signal" in r["network"]["flags"] or r.get("fit_message", "") == "":
            continue
        seeds.add((r.get("design") or {}).get("seed"))
        f = r["fit"]
        th = np.array([f["d"], f["h"], f["E"]])
        rel = r.get("fit_relstd_gauss") or [f["d_crb_rel"], f["h_crb_rel"], f["E_crb_rel"]]
        rel = np.asarray(rel, dtype=float)
        # ∂ ln E / ∂e at the estimate turns the sd of ln E into that of e (the E row of FitCoords.dtheta)
        g_e = abs(X.dtheta(X.x(th))[2, 2])
        sd = np.array([rel[0] * th[0], rel[1] * th[1], rel[2] / g_e])
        t = np.asarray(r["truth"], dtype=float)
        xt, xf = X.x(t), X.x(th)
        rows.append((t, np.array([t[0], t[1], xt[2]]), np.array([th[0], th[1], xf[2]]), sd, rel, th))
    cols = list(zip(*rows))
    out = {k: np.array(v) for k, v in zip(("truth", "x_true", "x_fit", "sd", "relstd", "theta_fit"), cols)}
    out["seeds"] = sorted(seeds, key=lambda v: (v is None, v))
    return out


def scores(data: dict) -> np.ndarray:
    """(n, 3) ``|x̂ − x| / sd`` per lesion and parameter."""
    return np.abs(data["x_fit"] - data["x_true"]) / data["sd"]


def scales_of(datas: list[dict]) -> tuple[dict, dict]:
    """The scales and cell sizes per parameter (stratum × class) from the pooled lesions of ``datas``."""
    rel = np.concatenate([d["relstd"] for d in datas])
    sc = np.concatenate([scores(d) for d in datas])
    nb = near_base(np.concatenate([d["theta_fit"] for d in datas]))
    out, sizes = {}, {}
    for j, q in enumerate(PARAMS):
        k, n = calibrate(rel[:, j], sc[:, j], nb)
        out[q] = tuple(tuple(round(float(v), 3) for v in row) for row in k)
        sizes[q] = tuple(tuple(int(v) for v in row) for row in n)
    return out, sizes


def coverage(data: dict, table: dict | None) -> dict:
    """Coverage inside/outside the map's region, and of the estimates near the base
    (:func:`~elastimap.identify.intervals.near_base`), per parameter of ``x̂ ± 1.96 k sd`` (``table``:
    the scales, None: the Gauss–Newton interval, k = 1): (held, n) for each of the three.  The truth lies in the box, so clipping the
    interval to the box does not change whether it holds it."""
    from elastimap.workflows.benchmarks.frames import identifiable_at  # the benchmark's region rule

    reg = identifiable_at(data["truth"])
    k = (
        np.ones_like(data["sd"])
        if table is None
        else np.array([scales_for(r, t, table) for r, t in zip(data["relstd"], data["theta_fit"])])
    )
    held = scores(data) <= Z95 * k
    nb = near_base(data["theta_fit"])
    out = {}
    for j, q in enumerate(PARAMS):
        i_in, i_out = reg[:, j], ~reg[:, j]
        out[q] = (held[i_in, j].sum(), i_in.sum(), held[i_out, j].sum(), i_out.sum(), held[nb, j].sum(), nb.sum())
    return out


def _row(name: str, cov: dict) -> str:
    def pct(a, n):
        return f"{100 * a / n:5.1f} % ({n:3d})" if n else "    —        "

    cells = [f"{q} in {pct(*cov[q][:2])} out {pct(*cov[q][2:4])} near {pct(*cov[q][4:])}" for q in ("d", "h", "E")]
    return f"{name:<28s} " + " | ".join(cells)


def _sum(covs: list[dict]) -> dict:
    return {q: tuple(int(sum(c[q][i] for c in covs)) for i in range(6)) for q in covs[0]}


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("folders", nargs=-1, required=True)
@click.option("--check", "checks", multiple=True, help="A folder scored with the scales, never used for them.")
@click.option("--loso", is_flag=True, help="Also score each folder with the scales of the others.")
@click.option(
    "--install",
    is_flag=True,
    help="Write the scales, with their provenance, to the file inference reads (identify/maps/intervals.json).",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the scales, with their provenance, to this JSON file (the format --install writes).",
)
def main(folders, checks, loso, install, out):
    """Interval scales from benchmark FOLDERS (SYNTHETIC lesions) and the coverage they give."""
    if install and out:
        raise UserError("--out", "give --install or --out, not both")
    if out:
        check_out_file(out, "--out")
    datas = {f: read_folder(f) for f in folders}
    table, sizes = scales_of(list(datas.values()))
    click.echo(f"SYNTHETIC calibration: {sum(len(d['truth']) for d in datas.values())} lesions of {len(datas)} folders")
    click.echo(
        "class edges of the relative sd: (0, 0.03], (0.03, 0.1], (0.1, 0.3], > 0.3; rows: far from the base, "
        f"near it (the estimated inclusion's bottom within {NEAR_BASE_MM:g} mm of the base)"
    )
    for q in table:
        click.echo(f"  {q}: scales {table[q]}  lesions per cell {sizes[q]}")
    click.echo("\ncoverage, Gauss–Newton then calibrated (in-sample for the calibration folders):")
    for f, d in datas.items():
        click.echo(_row(f"{f} gauss", coverage(d, None)))
        click.echo(_row(f"{f} calibrated", coverage(d, table)))
    if loso and len(datas) > 1:
        click.echo("\nleave one folder out (its coverage with the scales of the others):")
        covs, covs0 = [], []
        for f, d in datas.items():
            t, _ = scales_of([v for g, v in datas.items() if g != f])
            covs.append(coverage(d, t))
            covs0.append(coverage(d, None))
            click.echo(_row(f"{f} held out", covs[-1]))
        click.echo(_row("all, Gauss–Newton", _sum(covs0)))
        click.echo(_row("all, held out", _sum(covs)))
    for f in checks:
        d = read_folder(f)
        click.echo(f"\ncheck folder {f} (not used for the scales):")
        click.echo(_row("  gauss", coverage(d, None)))
        click.echo(_row("  calibrated", coverage(d, table)))
    if install or out:
        dest = INTERVALS_FILE if install else out
        write_scales(dest, table, CALIBRATED_FOR, provenance(datas, sizes))
        click.echo(f"\nwrote {dest}")


def provenance(datas: dict, sizes: dict) -> dict:
    """What the scales were made from and how: date, code version, folders, seeds, lesions (in all
    and per parameter's cell, stratum × class), the records' fits and the method."""
    return {
        "command": "python -m elastimap.workflows.studies.interval_calibration " + " ".join(datas),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "git_commit": code_version(),
        "folders": list(datas),
        "fits": FITS,
        "seeds": sorted({s for d in datas.values() for s in d["seeds"] if s is not None}),
        "lesions": int(sum(len(d["truth"]) for d in datas.values())),
        "lesions_per_cell": {q: [list(row) for row in sizes[q]] for q in sizes},
        "method": "Mondrian split-conformal prediction per parameter, stratum (near_base) and class of the fit's "
        "relative sd: k = the ceil((n + 1) level)-th smallest of |x_fit - x_true| / sd_gauss, divided by "
        "1.959964 (elastimap.identify.intervals.calibrate); SYNTHETIC benchmark lesions",
    }


if __name__ == "__main__":
    run(main, prog_name="python -m elastimap.workflows.studies.interval_calibration")
