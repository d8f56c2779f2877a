"""The flat field's press uncertainty (:class:`elastimap.camera.deflection.PressTerm`) on a SYNTHETIC
variant world, through the camera: the product's fit without and with it.

    python -m elastimap.workflows.studies.pressprior --world-level coarse --product tiny --frames 30
    python -m elastimap.workflows.studies.pressprior --world-level default --product coarse --frames 30

The world: elastimap's remeshing solver at ``--world-level``, sized by d, with the contact interface, at the
nine calibration-phantom designs and three further lesions (:func:`elastimap.workflows.studies.modelform.variant_world`;
its background press differs from the product's).  Each of the twelve is rendered through the nominal
SYNTHETIC camera (``--frames`` lesion and background frames, one draw, seed ``--seed``).  The lab's
calibration as ``camera calibrate --mesh PRODUCT --refine-level PRODUCT`` makes it: the nine phantoms'
FEM solves at ``--product`` (remeshing, fixed sizing, tied), the deflection calibration from their frames
(:func:`elastimap.camera.calibration.deflection_calibration`), the press's sd from elastimap's own other
models of it (:func:`elastimap.camera.calibration.press_uncertainty`: contact at ``--product``, tied at the
neighbouring level; ``after`` only) and the model-form term learnt at ``--product``.

Scored: the product's fit (``infer --refine``'s maps at ``--product``, carrying the term): each phantom with
the term learnt from the other eight (:func:`elastimap.camera.calibration.loo_fits`, start: the other eight's
mean d, h and geometric-mean E), lesions 10-12 with the nine's term from the nine's mean; ``before`` without
and ``after`` with the press term.  Also printed, as a diagnosis only (no setting is taken from it): the
press's prior sd against the world's own press minus the calibration's reference, by distance from the axis.
Self-consistency only (elastimap's own solver on both sides).
"""

from __future__ import annotations

import json
import os
import time

import click
import numpy as np

from elastimap.cli_util import MeshLevel, run

from . import modelform as mf

PIXEL = mf.PIXEL


class _Result:
    def __init__(self, z):
        self.image, self.image_raw, self.pixel = z["image"], z["image_raw"], PIXEL


def calibration_solves(thetas, mesh: str, cache: str) -> list:
    """The phantoms' FEM at ``mesh`` as ``camera calibrate`` solves them (remeshing, fixed sizing, tied)."""
    from elastimap.workflows.solves import cached_solve

    return [_Result(cached_solve(*map(float, th), mesh=mesh, cache=os.path.join(cache, "solves"))) for th in thetas]


def render(world, frames: int, seed: int) -> list:
    """(lesion, background) frame stacks of each world press through the nominal SYNTHETIC camera."""
    from elastimap.camera.optics import SensorModel, render_pair

    rng = np.random.default_rng(seed)
    s = SensorModel()
    return [render_pair(s, ph["ref"] + ph["diff"], ph["diff"], PIXEL, frames, rng) for ph in world]


def press_sd(theta, result, product: str, cache: str) -> np.ndarray:
    """:func:`elastimap.camera.calibration.press_uncertainty` of the first phantom (cached)."""
    from elastimap.camera.calibration import press_uncertainty

    path = os.path.join(cache, f"press_sd_{product}_{mf.key(theta)}.npy")
    if not os.path.exists(path):
        np.save(path, press_uncertainty(theta, result, product))
    return np.load(path)


def product_fits(world, pairs, defl, level: str) -> list[dict]:
    """The product's fit of all twelve (module docstring); rows as :func:`loo_fits` gives them."""
    import pandas as pd

    from elastimap.camera import calibration as C
    from elastimap.camera.optics import SensorModel
    from elastimap.identify.discrepancy import Discrepancy
    from elastimap.identify.fit import fit_on_maps
    from elastimap.identify.forward_maps import fit_maps

    ph = pd.DataFrame(
        [{"name": w["phantom"], "d": w["theta"][0], "h": w["theta"][1], "E": w["theta"][2]} for w in world[: mf.N_CAL]]
    )
    s = SensorModel()
    rec9 = C.learn_discrepancy(ph, pairs[: mf.N_CAL], defl, level, s)
    t0 = time.process_time()
    rows = C.loo_fits(rec9, ph, pairs[: mf.N_CAL], defl, s)["rows"]
    for r in rows:
        r["cpu_s"] = (time.process_time() - t0) / mf.N_CAL
    disc = Discrepancy.from_dict(rec9["term"])  # the term of all nine, as infer --refine loads it
    press = C.press_term(defl, s)
    maps = fit_maps(*C.refine_levels(level))
    th9 = np.array([w["theta"] for w in world[: mf.N_CAL]])
    start = np.array([th9[:, 0].mean(), th9[:, 1].mean(), float(np.exp(np.log(th9[:, 2]).mean()))])
    for w, rec in zip(world[mf.N_CAL :], C.recovered_images(pairs[mf.N_CAL :], defl, s), strict=True):
        th = w["theta"]
        t0 = time.process_time()
        r = fit_on_maps(rec.image, rec.sigma, start, maps, discrepancy=disc, pixel=PIXEL, shared=press)
        rows.append(
            {
                "name": w["phantom"],
                "truth": th.tolist(),
                "theta": r.theta.tolist(),
                "lo": r.lo.tolist(),
                "hi": r.hi.tolist(),
                "covered": [bool(r.lo[j] <= th[j] <= r.hi[j]) for j in range(3)],
                "reported": [bool(r.relstd[j] <= 0.10 and not r.at_bound) for j in range(3)],
                "at_bound": r.at_bound,
                "converged": r.converged,
                "cpu_s": time.process_time() - t0,
            }
        )
    return rows


def fit_summary(rows) -> dict:
    """Coverage and printed counts (d, h, E), MRE and mean signed error where printed (%), printed and
    missed, E on the design edge (and whether any such fit printed a number), mean CPU s a fit."""
    cov = np.array([r["covered"] for r in rows], bool)
    rep = np.array([r["reported"] for r in rows], bool)
    err = np.array([(np.array(r["theta"]) - r["truth"]) / np.array(r["truth"]) for r in rows])
    return {
        "n": len(rows),
        "covered": cov.sum(axis=0).tolist(),
        "reported": rep.sum(axis=0).tolist(),
        "mre_reported_pct": [
            float(100 * np.abs(err[rep[:, j], j]).mean()) if rep[:, j].any() else float("nan") for j in range(3)
        ],
        "bias_reported_pct": [
            float(100 * err[rep[:, j], j].mean()) if rep[:, j].any() else float("nan") for j in range(3)
        ],
        "reported_missed": (rep & ~cov).sum(axis=0).tolist(),
        "E_at_edge": int(sum("E" in r["at_bound"] for r in rows)),
        "at_edge_printed": int(sum(bool(r["at_bound"]) and any(r["reported"]) for r in rows)),
        "cpu_s": float(np.mean([r.get("cpu_s", np.nan) for r in rows])),
    }


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--world-level", type=MeshLevel(), default="coarse", show_default=True, help="The variant world's level.")
@click.option(
    "--product", type=MeshLevel(), default="tiny", show_default=True, help="The calibration's and fit's level."
)
@click.option("--frames", default=30, show_default=True, type=click.IntRange(2, 1000), help="Camera frames per press.")
@click.option("--seed", default=0, show_default=True, type=int, help="Camera noise seed.")
@click.option(
    "--runs",
    type=click.Choice(["both", "before", "after", "none"]),
    default="both",
    show_default=True,
    help="Fit without (before) and/or with (after) the press term (none: only the --power variants).",
)
@click.option(
    "--power",
    "powers",
    multiple=True,
    type=float,
    help="Also the press sd left where the phantoms do not see it, σ_s (1 − q)^POWER (repeatable; "
    "elastimap.camera.deflection.uninformed).",
)
@click.option("--cache", default="runs/modelform-cache", show_default=True, help="Folder of the solves.")
@click.option(
    "--out", default=None, type=click.Path(dir_okay=False), help="Write the rows here (.json; must not exist)."
)
def main(world_level, product, frames, seed, runs, powers, cache, out):
    """The product's fit of a variant world's camera frames without and with the flat field's press term."""
    from elastimap.camera import calibration as C
    from elastimap.camera.optics import SensorModel
    from elastimap.errors import UserError

    if out and os.path.exists(out):
        raise UserError("--out", f"{out} exists; choose another name")
    world = mf.variant_world(world_level, cache)
    thetas = [w["theta"] for w in world]
    results = calibration_solves(thetas[: mf.N_CAL], product, cache)
    pairs = render(world, frames, seed)
    defl = C.deflection_calibration(results, pairs[: mf.N_CAL], SensorModel())
    sd = press_sd(thetas[0], results[0], product, cache)
    world_err = np.abs(np.mean([w["ref"] for w in world], axis=0) - np.asarray(defl["reference"]))
    click.echo(f"press prior sd (µm):                   {C.press_bands(sd, PIXEL)}")
    click.echo(f"|world's press - reference| (µm, diag): {C.press_bands(world_err, PIXEL)}")
    result = {"world": f"elastimap remesh {world_level}, by_d, contact (SYNTHETIC)", "product": product}
    result.update(frames=frames, seed=seed, runs={})
    from elastimap.camera.deflection import uninformed

    variants = {"before": None, "after": sd}
    variants = {k: v for k, v in variants.items() if runs in (k, "both")}
    for pw in powers:
        variants[f"after, power {pw:g}"] = uninformed(sd, [r.image for r in results], pw)
        click.echo(f"press sd, power {pw:g} (µm): {C.press_bands(variants[f'after, power {pw:g}'], PIXEL)}")
    for name, v in variants.items():
        d = defl if v is None else dict(defl, press_sd=v.tolist())
        rows = product_fits(world, pairs, d, product)
        for r in rows:
            click.echo(
                f"  {name} {r['name']} truth {np.round(r['truth'], 2).tolist()} fit {np.round(r['theta'], 2).tolist()}"
                f" lo {np.round(r['lo'], 2).tolist()} hi {np.round(r['hi'], 2).tolist()}"
                f" covered {r['covered']} printed {r['reported']} edge {r['at_bound']}"
            )
        summ = fit_summary(rows)
        click.echo(f"{name}: {json.dumps(summ)}")
        result["runs"][name] = {"rows": rows, "summary": summ}
    if out:
        with open(out, "w") as fh:
            json.dump(result, fh, indent=1)


if __name__ == "__main__":
    import sys

    run(main, sys.argv[1:], prog_name="python -m elastimap.workflows.studies.pressprior")
