"""Score held-out inverse predictions inside and outside the locally identifiable region.

    python -m identify.region_score --pred runs/image-inverse-loocv/pred-scg-loocv.npz [--set image]

For every row of the prediction file (written by ``python -m identify.imagenet``) the Cramér–Rao
bound of the identifiability map (:mod:`identify.region`; default: the shipped map, the one
inference uses) is evaluated at the row's true (d, h, E) for the chosen measurement set.  A row is
*identifiable for output q* when the bound's relative standard deviation of q is at most
``--threshold`` (default 10 %).  Printed: the mean relative error of each output over all
held-out rows, over the identifiable rows and over the rest, with counts.
"""

from __future__ import annotations

import os

import click
import numpy as np

from elastimap.cli_util import run
from elastimap.errors import UserError

from .region import SETS


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
@click.option("--pred", "pred_path", required=True, help="pred-<algo>-<validation>.npz from identify.imagenet.")
@click.option("--map", "map_path", default="default", show_default=True,
              help="Identifiability map (crb_grid.npz of python -m identify.crbmap) or 'default' (shipped).")
@click.option("--set", "mset", default="image", show_default=True, help="Measurement set: " + ", ".join(SETS) + ".")
@click.option("--threshold", default=0.10, show_default=True, type=float, help="CRB relative std limit.")
def main(pred_path, map_path, mset, threshold):
    """MRE of held-out predictions inside / outside the identifiable region of the map."""
    from .region import IdentifiabilityMap

    if mset not in SETS:
        raise UserError("--set", f"must be one of {', '.join(SETS)} (got {mset!r})")
    if not 0 < threshold < 10:
        raise UserError("--threshold", f"must be in (0, 10) (got {threshold:g})")
    if not os.path.isfile(pred_path):
        raise UserError("--pred", f"no such file: {pred_path}")
    try:
        z = np.load(pred_path, allow_pickle=False)
        pred, theta = z["pred"], z["theta"]
    except Exception as exc:
        raise UserError("--pred", f"{pred_path}: not a prediction file of identify.imagenet ({exc})") from None
    idm = IdentifiabilityMap.load(None if map_path == "default" else map_path)
    crb, _ = idm.bound(theta, mset)
    res = score(pred, theta, crb, threshold)
    click.echo(f"{pred_path}: {pred.shape[0]} repeat(s), {pred.shape[1]} rows; region: map CRB ({mset}) "
               f"rel std <= {100 * threshold:g} % ({idm.source})")
    click.echo("| output | MRE all (%) | identifiable: MRE (%) [rows] | rest: MRE (%) [rows] |")
    click.echo("|---|---|---|---|")
    for name in ("d", "h", "E"):
        a, i, r = res[(name, "all")], res[(name, "identifiable")], res[(name, "rest")]
        click.echo(f"| {name} | {a[0]:.3g} | {i[0]:.3g} [{i[1]}] | {r[0]:.3g} [{r[1]}] |")
    return 0


if __name__ == "__main__":
    run(main, prog_name="python -m identify.region_score")
