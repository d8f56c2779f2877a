"""Score held-out inverse predictions inside and outside the locally identifiable region.

    elastimap study region_score --pred runs/image-inverse-loocv/pred-scg-loocv.npz [--set image]

For every row of the prediction file (written by ``elastimap study image_model``) the Cramér–Rao
bound of the identifiability map (:mod:`elastimap.identify.idmap`; default: the shipped map, the one
inference uses) is evaluated at the row's true (d, h, E) for the chosen measurement set.  A row is
*identifiable for output q* when the bound's relative standard deviation of q is at most
``--crb-limit`` (default 10 %).  Printed: the mean relative error of each output over all
held-out rows, over the identifiable rows and over the rest, with counts.

It then checks the *intervals inference would report*: for every row the estimate is the mean
held-out prediction over the repeats, its interval :meth:`elastimap.identify.idmap.IdentifiabilityMap.assess`
at that estimate (widened to the repeats' 10–90 % range, clipped to the data's range), and the
coverage is the fraction of rows whose true value lies inside, separately for the rows flagged
``non_identifiable`` at the estimate and the rest.
"""

from __future__ import annotations

import os

import click
import numpy as np

from elastimap.cli_util import run
from elastimap.errors import UserError
from elastimap.identify.idmap import SETS


def score(pred: np.ndarray, theta: np.ndarray, crb: np.ndarray, threshold: float = 0.10) -> dict:
    """MRE (%) per output over all rows, identifiable rows (``crb <= threshold``) and the rest.

    ``pred`` ``(R, n, 3)`` (NaN where not held out), ``theta`` ``(n, 3)``, ``crb`` ``(n, 3)``."""
    rel = np.abs(pred - theta[None]) / np.abs(theta[None]) * 100.0
    out = {}
    for j, name in enumerate(("d", "h", "E")):
        ok = crb[:, j] <= threshold
        for key, m in (("all", np.ones_like(ok)), ("identifiable", ok), ("rest", ~ok)):
            v = rel[:, m, j]
            v = v[np.isfinite(v)]
            out[(name, key)] = (float(v.mean()) if v.size else float("nan"), int(m.sum()))
    return out


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--pred", "pred_path", required=True, help="pred-<algo>-<validation>.npz from elastimap study image_model."
)
@click.option(
    "--map",
    "map_path",
    default="default",
    show_default=True,
    help="Identifiability map (crb_grid.npz of python -m elastimap.workflows.studies.crbmap) or 'default' (shipped).",
)
@click.option("--set", "mset", default="image", show_default=True, help="Measurement set: " + ", ".join(SETS) + ".")
@click.option("--crb-limit", "threshold", default=0.10, show_default=True, type=float, help="CRB relative std limit.")
def main(pred_path, map_path, mset, threshold):
    """MRE of held-out predictions inside / outside the identifiable region of the map."""
    from elastimap.identify.idmap import IdentifiabilityMap

    if mset not in SETS:
        raise UserError("--set", f"must be one of {', '.join(SETS)} (got {mset!r})")
    if not 0 < threshold < 10:
        raise UserError("--crb-limit", f"must be in (0, 10) (got {threshold:g})")
    if not os.path.isfile(pred_path):
        raise UserError("--pred", f"no such file: {pred_path}")
    try:
        z = np.load(pred_path, allow_pickle=False)
        pred, theta = z["pred"], z["theta"]
        shared = z["pred_shared_noise"] if "pred_shared_noise" in z.files else None
    except Exception as exc:
        raise UserError(
            "--pred", f"{pred_path}: not a prediction file of elastimap study image_model ({exc})"
        ) from None
    idm = IdentifiabilityMap.load(None if map_path == "default" else map_path)
    crb, _ = idm.bound(theta, mset)
    res = score(pred, theta, crb, threshold)
    click.echo(
        f"{pred_path}: {pred.shape[0]} repeat(s), {pred.shape[1]} rows; region: map CRB ({mset}) "
        f"rel std <= {100 * threshold:g} % ({idm.source})"
    )
    _print_scores(res)
    if shared is not None:
        click.echo("")
        click.echo(
            f"Ensemble estimate as inference reports it: ONE noisy image of each held-out row through all "
            f"{shared.shape[0]} networks, their mean:"
        )
        _print_scores(score(np.nanmean(shared, axis=0)[None], theta, crb, threshold))
    cov = coverage(pred if shared is None else shared, theta, idm, mset, threshold)
    click.echo("")
    click.echo(
        "Intervals as inference reports them (estimate = mean over repeats"
        + (", one shared noisy image" if shared is not None else ", each repeat its own noise draw")
        + "):"
    )
    click.echo(
        "| output | flagged non-identifiable [rows] | coverage flagged (%) | coverage rest (%) "
        "| median hi/lo flagged | median hi/lo rest |"
    )
    click.echo("|---|---|---|---|---|---|")
    for name in ("d", "h", "E"):
        c = cov[name]
        click.echo(
            f"| {name} | {c['n_flagged']} | {c['cover_flagged']:.3g} | {c['cover_rest']:.3g} "
            f"| {c['width_flagged']:.3g} | {c['width_rest']:.3g} |"
        )
    return 0


def _print_scores(res: dict) -> None:
    click.echo("| output | MRE all (%) | identifiable: MRE (%) [rows] | rest: MRE (%) [rows] |")
    click.echo("|---|---|---|---|")
    for name in ("d", "h", "E"):
        a, i, r = res[(name, "all")], res[(name, "identifiable")], res[(name, "rest")]
        click.echo(f"| {name} | {a[0]:.3g} | {i[0]:.3g} [{i[1]}] | {r[0]:.3g} [{r[1]}] |")


def coverage(pred: np.ndarray, theta: np.ndarray, idm, mset: str, threshold: float = 0.10) -> dict:
    """Coverage (%) of the truth by the intervals inference reports, flagged rows vs the rest."""
    ok = np.isfinite(pred).all(axis=2).any(axis=0)
    P, T = pred[:, ok], theta[ok]
    mean = np.nanmean(P, axis=0)
    a = idm.assess(
        mean,
        mset,
        threshold,
        p10=np.nanpercentile(P, 10, axis=0),
        p90=np.nanpercentile(P, 90, axis=0),
        target_range=np.stack([theta.min(0), theta.max(0)]),
    )
    inside = (a.lo <= T) & (T <= a.hi)
    ratio = a.hi / np.clip(a.lo, 1e-12, None)
    out = {}
    for j, name in enumerate(("d", "h", "E")):
        f = ~a.identifiable[:, j]
        pct = lambda m, j=j: float(100 * inside[m, j].mean()) if m.any() else float("nan")
        med = lambda m, j=j: float(np.median(ratio[m, j])) if m.any() else float("nan")
        out[name] = {
            "n_flagged": int(f.sum()),
            "cover_flagged": pct(f),
            "cover_rest": pct(~f),
            "width_flagged": med(f),
            "width_rest": med(~f),
        }
    return out


if __name__ == "__main__":
    run(main, prog_name="elastimap study region_score")
